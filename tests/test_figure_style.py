"""How the figures read (``hdhil plot``, ``plot --figure fig8``, ``calibrate --plot``, the
campaign plots): one unit notation, legends clear of the data, the window a title names,
y-scales from the steady part, one axis per quantity and panels only for what the
scenario contains.  Synthetic data, no run: the figures are drawn with Agg."""

from __future__ import annotations

import math
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from hdhil.analysis.paper_figures import Fig8Data, make_calibration_figure, make_fig8
from hdhil.analysis.ripple_figures import (
    JointRow,
    PlotData,
    has_misalignment,
    make_figure,
    make_rig_figure,
    steady_start,
)
from hdhil.core.plotlabels import key_label, split_unit
from hdhil.rig.campaign_file import Axis, Campaign
from hdhil.rig.campaign_metrics import JOINT_METRICS, METRIC_WORDS, METRICS, Criterion
from hdhil.rig.campaign_report import axis_words, is_categorical, metric_words, plot_files

Ts = 1e-3
#: "quantity (unit)" or a dimensionless quantity alone; units never in brackets, after a
#: slash or written "Nm".
_BAD_UNIT = re.compile(r"\[|\]| / |\bNm\b|\(Nm")


def _labels(fig: Figure) -> list[str]:
    return [t for ax in fig.axes for t in (ax.get_xlabel(), ax.get_ylabel()) if t]


def _assert_notation(fig: Figure) -> None:
    for text in _labels(fig):
        assert not _BAD_UNIT.search(text), text
        assert "_" not in text.replace("$", "") or "$" in text, text  # no raw keys


def _assert_legends_clear_of_data(fig: Figure) -> None:
    """No plotted point of any axes lies inside any legend's box (display coordinates)."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    boxes = [ax.get_legend().get_window_extent(renderer) for ax in fig.axes if ax.get_legend()]
    assert boxes
    for ax in fig.axes:
        clip = ax.get_window_extent(renderer)
        for line in ax.get_lines():
            xy = np.column_stack([line.get_xdata(), line.get_ydata()]).astype(float)
            xy = xy[np.isfinite(xy).all(axis=1)]
            if not len(xy):
                continue
            pts = line.get_transform().transform(xy)
            pts = pts[(pts[:, 0] >= clip.x0) & (pts[:, 0] <= clip.x1)
                      & (pts[:, 1] >= clip.y0) & (pts[:, 1] <= clip.y1)]  # fmt: skip
            for box in boxes:
                inside = ((pts[:, 0] > box.x0) & (pts[:, 0] < box.x1)
                          & (pts[:, 1] > box.y0) & (pts[:, 1] < box.y1))  # fmt: skip
                assert not inside.any(), (ax.get_title(), ax.get_ylabel(), line.get_label())


# ------------------------------------------------------------------------- notation
def test_key_labels_read_in_words_and_units() -> None:
    assert split_unit("eval_rms_err_Nm") == ("eval_rms_err", "N·m")
    assert split_unit("faults_injected") == ("faults_injected", "")
    assert key_label("velocity_final_radps", {"velocity_final_radps": "final velocity"}) == (
        "final velocity (rad/s)"
    )
    assert key_label("plant.ripple.amp2_Nm") == "ripple amp2 (N·m)"


def test_every_campaign_metric_has_words() -> None:
    assert set(METRIC_WORDS) == set(METRICS)
    for name in METRICS:
        assert "_" not in key_label(name, METRIC_WORDS), name
    for name in JOINT_METRICS:  # a rig's, per joint and for the worst joint
        for metric in (f"joints.J3.{name}", f"worst.{name}"):
            words = metric_words(metric)
            assert "_" not in words and ("J3" in words or "worst joint" in words), words
    assert axis_words("joints.J3.firmware.control.torque_limit_Nm") == (
        "J3: control torque limit (N·m)"
    )


# -------------------------------------------------------------------------- Fig. 8
def _fig8_data() -> Fig8Data:
    """20 s of a sine tracked, with a start-up transient (|e| 2.6 N·m) before 1 s."""
    t = np.arange(0.0, 4.0, Ts)
    sd = 20.0 * np.cos(0.4 * math.pi * (t - 5.1))  # peaks where a legend in the axes would sit
    e = 0.3 * np.sin(2.0 * math.pi * t) + np.where(t < 1.0, 2.6 * np.exp(-t / 0.05), 0.0)
    tl = 20.0 * np.cos(0.4 * math.pi * (t - 5.0))
    return Fig8Data(t=t, tau_s_meas=sd + e + 0.05, tau_s_hat=sd + e, tau_sD=sd,
                    tau_s_true=sd + e, tau_l_hat=tl + 0.8 * np.sin(t), tau_l_meas=tl,
                    theta_l_deg=30.0 * np.sin(t), omega_l=0.5 * np.cos(t),
                    tau_m=35.0 * np.cos(0.4 * math.pi * (t - 5.1)))  # fmt: skip


def test_fig8_draws_the_window_its_figures_are_over() -> None:
    """The legend's max |e| is the drawn curve's; nothing before ``skip_s`` is drawn."""
    fig = make_fig8(_fig8_data(), "title", skip_s=1.0)
    for ax in fig.axes:
        for line in ax.get_lines():
            x = np.asarray(line.get_xdata(), dtype=float)
            if x.size > 2:
                assert x.min() >= 1.0, line.get_label()
    err = next(ax for ax in fig.axes if ax.get_ylabel() == "error (N·m)")
    e_line = next(line for line in err.get_lines() if line.get_label().startswith("$e ="))
    shown = float(re.search(r"max \$\|e\|\$ ([0-9.]+)", e_line.get_label()).group(1))
    assert shown == pytest.approx(np.max(np.abs(e_line.get_ydata())), abs=0.005)
    assert shown < 0.5  # the 2.6 N·m start-up transient is not in it
    _assert_notation(fig)


def test_fig8_measured_external_torque_shows_over_the_estimate() -> None:
    """τl^m is drawn above τ̂l, dashed and thinner, so that both show where they agree."""
    fig = make_fig8(_fig8_data(), "title", skip_s=1.0)
    ext = next(ax for ax in fig.axes if ax.get_ylabel() == "external torque (N·m)")
    meas = next(ln for ln in ext.get_lines() if ln.get_label().startswith(r"$\tau_l^m$"))
    est = next(ln for ln in ext.get_lines() if ln.get_label().startswith(r"$\hat{\tau}_l$"))
    assert meas.get_zorder() > est.get_zorder()
    assert meas.get_linestyle() != "-" and meas.get_linewidth() < est.get_linewidth()


@pytest.mark.slow
def test_fig8_legends_clear_of_data() -> None:
    _assert_legends_clear_of_data(make_fig8(_fig8_data(), "title", skip_s=1.0))


# ---------------------------------------------------------------- Taghirad97 Figs. 8-11
def _plot_data(misalignment: bool) -> PlotData:
    """6 s at 156 rad/s: ripple (and misalignment) on the measurement; the filtered
    torque starts 3 N·m off (the start-up) and then stays within 0.03 N·m of the truth."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 6.0, Ts)
    v = 156.0 * (1.0 - np.exp(-t / 0.05))
    motor = np.cumsum(v) * Ts
    out = motor / 100.0
    true = np.full_like(t, 0.07)
    meas = true + 0.6 * np.sin(2 * motor) + (5.0 * np.sin(out) if misalignment else 0.0)
    filtered = true + 3.0 * np.exp(-t / 0.6) + rng.normal(0.0, 0.025, t.size)
    return PlotData(sample_period_s=Ts, t=t, T_meas=meas, velocity=v, T_filtered=filtered,
                    filtered_label="filtered", T_expected=np.zeros_like(t), T_true=true,
                    output_angle=out, output_angle_source="truth", mode="recommended")  # fmt: skip


@pytest.mark.parametrize(
    ("scenario", "expected"),
    [("free-motion", False), ("torque-steps", False), ("misalignment", True),
     ("lqg-misalignment", True)],
)  # fmt: skip
def test_which_scenarios_get_misalignment_panels(scenario: str, expected: bool) -> None:
    from hdhil.rig.request import resolve

    assert has_misalignment(resolve(scenario).scenario) is expected


def test_free_motion_has_no_misalignment_panels() -> None:
    fig = make_figure(_plot_data(False), "title", misalignment=False, steady_from_s=0.3)
    titles = " ".join(ax.get_title() for ax in fig.axes)
    assert "Fig. 9" in titles and "Fig. 10" not in titles and "Fig. 11" not in titles
    _assert_notation(fig)


def test_misalignment_after_filtering_is_scaled_to_the_steady_part() -> None:
    """Fig. 11's y-scale comes from t >= steady_from_s (the 0.03 N·m residual fills
    it); the 3 N·m start-up has its own panel."""
    fig = make_figure(_plot_data(True), "title", misalignment=True, steady_from_s=4.0)
    fig11 = next(ax for ax in fig.axes if ax.get_title().startswith("Fig. 11"))
    lo, hi = fig11.get_ylim()
    assert hi - lo < 0.5 and "t >= 4 s" in fig11.get_title()
    start = next(ax for ax in fig.axes if ax.get_title().startswith("start-up"))
    assert start.get_ylim()[1] > 2.5
    _assert_notation(fig)


def test_steady_start_without_a_scenario_is_one_output_revolution() -> None:
    data = _plot_data(True)
    s = steady_start(data)
    k = round(s / Ts)
    turning = int(np.flatnonzero(data.velocity >= 5.0)[0])
    assert data.output_angle[k] - data.output_angle[turning] == pytest.approx(2 * math.pi, 0.01)
    assert steady_start(data, 4.0) == 4.0


def test_one_axis_per_quantity() -> None:
    """Axes drawn over one another (twins) hold different quantities: the Fig. 9
    close-up no longer puts the measured torque on an offset second torque axis."""
    fig = make_figure(_plot_data(True), "title", misalignment=True, steady_from_s=4.0)
    by_place: dict[tuple[float, ...], list[Any]] = {}
    for ax in fig.axes:
        by_place.setdefault(tuple(np.round(ax.get_position().bounds, 4)), []).append(ax)
    for same in by_place.values():
        units = [split_unit(ax.get_ylabel())[1] or ax.get_ylabel().rsplit("(", 1)[-1]
                 for ax in same]  # fmt: skip
        assert len(units) == len(set(units)), [ax.get_ylabel() for ax in same]


@pytest.mark.slow
def test_ripple_figure_legends_clear_of_data() -> None:
    fig = make_figure(_plot_data(True), "title", misalignment=True, steady_from_s=4.0)
    _assert_legends_clear_of_data(fig)


@pytest.mark.slow
def test_rig_figure_rows_labelled_and_legends_clear_of_data() -> None:
    rows = [JointRow("joint A: bus can0", _plot_data(False)),
            JointRow("joint B: bus can1", _plot_data(True), True, 4.0)]  # fmt: skip
    fig = make_rig_figure(rows, "title")
    _assert_notation(fig)
    _assert_legends_clear_of_data(fig)
    assert [sub._suptitle.get_text() for sub in fig.subfigs] == [r.heading for r in rows]
    assert sum(ax.get_title().startswith("Fig. 10") for ax in fig.axes) == 1  # joint B's


# ----------------------------------------------------------------- calibration figure
@pytest.mark.slow
def test_calibration_figure_notation_and_legends() -> None:
    volts = np.linspace(-0.75, 0.75, 11)
    exps = [
        SimpleNamespace(range_Nm=r, index=i, volts=list(volts * r / 5.0),
                        torques_Nm=list(6.6 * volts * r / 5.0), gain_Nm_per_V=6.6, offset_V=0.0)
        for i, r in enumerate((5.0, 5.0, 40.0, 40.0))
    ]  # fmt: skip
    fig = make_calibration_figure(SimpleNamespace(experiments=exps), "title")
    _assert_notation(fig)
    assert all("N·m/V" in t.get_text() for ax in fig.axes for t in ax.get_legend().get_texts())
    _assert_legends_clear_of_data(fig)


# ------------------------------------------------------------------ campaign plots
def _campaign_figures(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Figure]:
    captured: dict[str, Figure] = {}
    real = Figure.savefig

    def savefig(self: Figure, fname: Any, *args: Any, **kwargs: Any) -> None:
        captured[Path(fname).name] = self
        real(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    campaign = Campaign(
        name="c", source="c.toml", scenarios=("free-motion",),
        criteria=(Criterion.parse("eval_rms_err_Nm < 0.06"),),
        axes=(Axis("firmware.ripple.mode", ("paper", "recommended")),
              Axis("faults.control.loss_rate", (0.0, 0.05))),
        zips=((Axis("seed", (1, 2, 3)),),),
    )  # fmt: skip
    table = [
        {"status": "pass", "firmware.ripple.mode": mode, "faults.control.loss_rate": rate,
         "seed": seed, "eval_rms_err_Nm": 0.03 + rate + 0.001 * seed}
        for mode in ("paper", "recommended") for rate in (0.0, 0.05) for seed in (1, 2, 3)
    ]  # fmt: skip
    files = plot_files(campaign, table, tmp_path / "plots")
    assert len(files) == 3 and len(captured) == 3
    return captured


@pytest.mark.slow
def test_campaign_plots_in_words_without_a_line_across_seeds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    figs = _campaign_figures(tmp_path, monkeypatch)
    for name, fig in figs.items():
        ax = fig.axes[0]
        assert ax.get_ylabel() == "RMS error of the filtered torque (N·m)", name
        assert "eval_rms_err_Nm" not in ax.get_title() + ax.get_xlabel()
        _assert_notation(fig)
    seed = figs["eval_rms_err_Nm-over-seed.png"].axes[0]
    assert seed.get_xlabel() == "noise seed"
    for line in seed.get_lines():  # points and mean bars only: no line across seeds
        assert line.get_linestyle() in ("None", "none", "--"), line.get_label()
    rate = figs["eval_rms_err_Nm-over-faults_control_loss_rate.png"].axes[0]
    assert rate.get_xlabel() == "control-bus frame loss rate (%)"
    assert any(ln.get_linestyle() == "-" for ln in rate.get_lines())  # a mean over a quantity
    assert is_categorical("seed", [1, 2]) and is_categorical("x", ["a"])
    assert not is_categorical("faults.control.loss_rate", [0.0, 0.1])


@pytest.mark.slow
def test_campaign_plot_legends_clear_of_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for fig in _campaign_figures(tmp_path, monkeypatch).values():
        _assert_legends_clear_of_data(fig)
