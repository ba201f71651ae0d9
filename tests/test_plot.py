"""Tests of ``hdhil plot`` (hdhil.analysis.ripple_figures): the [Taghirad97] Figs. 8-11
views of a trace, the flat-velocity window and the spectrum peak finder (Fig. 8: peaks at
2x and 4x the motor velocity)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import can
import numpy as np
import pytest
from runs import lockstep

from hdhil.analysis.ripple_figures import (
    PlotData,
    flat_velocity_window,
    make_figure,
    plot_data,
    ripple_peaks,
    spectrum_peaks,
    torque_spectrum,
)
from hdhil.can.traces.reader import read_trace
from hdhil.cli import main
from hdhil.core.dataconf import from_dict
from hdhil.firmware.config import FirmwareConfig
from hdhil.rig.evaluate import recording_from_trace
from hdhil.rig.scenario import load_scenario

Ts = 1e-3
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------- analysis
def test_spectrum_peaks_of_two_sines_in_noise() -> None:
    """[Taghirad97] Fig. 8: 0.3 s at 156 rad/s gives peaks at 312 and 624 rad/s."""
    rng = np.random.default_rng(1)
    t = np.arange(300) * Ts
    x = (0.6 * np.sin(312.0 * t + 0.4) + 0.25 * np.sin(624.0 * t + 1.3) + 0.1 * t
         + rng.normal(0.0, 0.02, t.size))  # fmt: skip
    omega, power = torque_spectrum(x, Ts)
    assert omega[1] - omega[0] < 2 * math.pi / (300 * Ts) / 4  # zero-padded
    peaks = spectrum_peaks(omega, power, count=2, min_omega=60.0)
    np.testing.assert_allclose(peaks, [312.0, 624.0], atol=2.0)
    assert len(spectrum_peaks(omega, power, count=1)) == 1
    assert spectrum_peaks(omega, power, count=1, min_omega=400.0) == pytest.approx([624.0], abs=2)
    assert len(spectrum_peaks(omega, power, min_omega=5000.0)) == 0


def test_spectrum_peaks_finds_the_strongest_not_the_first() -> None:
    omega = np.linspace(0.0, 1000.0, 1001)
    power = (1e-6 + 1.0 * np.exp(-((omega - 700.0) / 5) ** 2)
             + 0.1 * np.exp(-((omega - 200.0) / 5) ** 2)
             + 0.5 * np.exp(-((omega - 400.3) / 5) ** 2))  # fmt: skip
    np.testing.assert_allclose(spectrum_peaks(omega, power, count=2), [400.3, 700.0], atol=0.05)


def test_flat_velocity_window() -> None:
    t = np.arange(2000) * Ts
    v = 156.0 * (1.0 - np.exp(-t / 0.19)) + np.random.default_rng(2).normal(0.0, 0.05, t.size)
    k0, k1 = flat_velocity_window(v, Ts)
    assert k1 - k0 == 300 and k0 >= 1400  # the flattest 0.3 s: at the end of the run-up
    assert flat_velocity_window(np.zeros(1000), Ts) is None  # never turning
    assert flat_velocity_window(np.full(100, 50.0), Ts) == (0, 100)  # shorter than 0.3 s
    assert flat_velocity_window(np.full(10, 50.0), Ts) is None


# ------------------------------------------------------------------ emulated traces
@pytest.fixture(scope="module")
def traces(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """2 s of free motion ([Taghirad97] Fig. 8-9) and 3 s of misalignment (Figs. 10-11); the
    misalignment trace also without truth and with the drive's sensor frames only."""
    d = tmp_path_factory.mktemp("plot")
    out = {"free": d / "free.blf", "mis": d / "mis.blf"}
    lockstep(load_scenario("free-motion"), duration_s=2.0, trace=out["free"], evaluate=False)
    lockstep(load_scenario("misalignment"), duration_s=3.0, trace=out["mis"], evaluate=False)
    out["no_truth"], out["sensor_only"], out["no_sensor"] = (
        d / "no_truth.blf", d / "sensor_only.blf", d / "no_sensor.blf")  # fmt: skip
    with (
        read_trace(out["mis"]) as trace,
        can.Logger(str(out["no_truth"])) as no_truth,
        can.Logger(str(out["sensor_only"])) as sensor_only,
        can.Logger(str(out["no_sensor"])) as no_sensor,
    ):
        for msg in trace:
            if msg.is_extended_id:
                continue
            no_truth(msg)
            (sensor_only if msg.arbitration_id in (0x182, 0x282) else no_sensor)(msg)
    return out


def _data(path: Path, scenario: str) -> PlotData:
    fw = from_dict(FirmwareConfig, load_scenario(scenario).firmware, "firmware")
    return plot_data(recording_from_trace(path)[0], fw)


@pytest.mark.slow
def test_free_motion_spectrum_peaks_at_2x_and_4x_velocity(traces: dict[str, Path]) -> None:
    """[Taghirad97] Fig. 8: peaks at twice and four times the (flat) motor velocity."""
    data = _data(traces["free"], "free-motion")
    k0, k1 = flat_velocity_window(data.velocity, Ts)
    v = float(np.mean(data.velocity[k0:k1]))
    assert 150.0 < v < 160.0
    _, _, peaks = ripple_peaks(data.T_meas[k0:k1], Ts)
    np.testing.assert_allclose(peaks, [2 * v, 4 * v], rtol=0.01)


@pytest.mark.slow
def test_output_angle_from_encoder_matches_truth(traces: dict[str, Path]) -> None:
    with_truth = _data(traces["mis"], "misalignment")
    without = _data(traces["no_truth"], "misalignment")
    assert with_truth.output_angle_source == "truth" and with_truth.T_true is not None
    assert without.output_angle_source == "encoder / gear ratio" and without.T_true is None
    a = with_truth.output_angle - with_truth.output_angle[0]
    b = without.output_angle - without.output_angle[0]
    assert a[-1] > 2.0  # the output turned (1.56 rad/s)
    np.testing.assert_allclose(b, a, atol=2e-3)
    np.testing.assert_array_equal(with_truth.T_filtered, without.T_filtered)  # telemetry


@pytest.mark.slow
def test_sensor_only_trace_gets_offline_filtered_torque(traces: dict[str, Path]) -> None:
    full = _data(traces["mis"], "misalignment")
    sensor_only = _data(traces["sensor_only"], "misalignment")
    assert "offline" in sensor_only.filtered_label and "telemetry" in full.filtered_label
    # Telemetry is the same filter, quantised to 0.004 Nm (where the firmware ran: the
    # last samples of the stop walk have no telemetry).
    ran = np.isfinite(full.T_filtered)
    assert ran.sum() >= len(ran) - 5
    np.testing.assert_allclose(sensor_only.T_filtered[ran], full.T_filtered[ran], atol=0.0021)


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["free", "mis"])
def test_cli_writes_a_png(
    name: str, traces: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenario = {"free": "free-motion", "mis": "misalignment"}[name]
    out = tmp_path / "fig.png"
    assert main(["plot", str(traces[name]), "--scenario", scenario, "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    # Figs. 10-11 only where the scenario has misalignment.
    assert _png_size(out) == {"free": (1400, 850), "mis": (1400, 1600)}[name]
    assert 50_000 < out.stat().st_size < 5_000_000


@pytest.mark.slow
def test_cli_pdf_svg_and_window(
    traces: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pdf, svg = tmp_path / "fig.pdf", tmp_path / "fig.svg"
    assert main(["plot", str(traces["free"]), "--out", str(pdf), "--window", "0.8", "1.1"]) == 0
    assert pdf.read_bytes().startswith(b"%PDF")
    assert main(["plot", str(traces["sensor_only"]), "--out", str(svg)]) == 0
    text = svg.read_text()
    assert "<svg" in text and "offline firmware chain" in text


@pytest.mark.slow
def test_figure_titles_name_the_window(traces: dict[str, Path]) -> None:
    fig = make_figure(_data(traces["free"], "free-motion"), "title", window=(0.8, 1.1))
    titles = [ax.get_title() for ax in fig.axes]
    assert any("power spectrum, 0.80-1.10 s" in t for t in titles)
    assert any(t.startswith("Fig. 10: misalignment before") for t in titles)
    assert any(t.startswith("Fig. 11: misalignment after") for t in titles)
    assert fig.get_suptitle() == "title"
    # Legends sit outside the data: below each axes (anchored under its bottom edge).
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is not None:
            assert legend.get_bbox_to_anchor()._bbox.y1 < 0  # type: ignore[attr-defined]


@pytest.mark.slow
def test_every_curve_is_inside_its_axes(traces: dict[str, Path]) -> None:
    """Each panel's y limits hold every curve drawn on it (no curve clipped)."""
    import numpy as np

    fig = make_figure(_data(traces["free"], "free-motion"), "title")
    for ax in fig.axes:
        lo, hi = ax.get_ylim()
        if ax.get_yscale() != "linear":
            continue
        for line in ax.get_lines():
            y = np.asarray(line.get_ydata(), dtype=float)
            y = y[np.isfinite(y)]
            if y.size and line.get_label() and not line.get_label().startswith("_"):
                assert lo <= y.min() and y.max() <= hi, (ax.get_title(), line.get_label())


@pytest.mark.slow
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["{free}", "--out", "{tmp}/fig.jpg"], "unsupported figure format '.jpg'"),
        (["{free}", "--out", "{tmp}/fig"], "unsupported figure format"),
        (["{free}", "--out", "{tmp}/missing/fig.png"], "does not exist"),
        (["{free}", "--out", "{tmp}"], "unsupported figure format"),
        (["/nonexistent/trace.blf", "--out", "{tmp}/fig.png"], "no such file"),
        (["{no_sensor}", "--out", "{tmp}/fig.png"], "no DRIVE_TPDO1 frames"),
        (["{free}", "--out", "{tmp}/fig.png", "--window", "1.1", "0.8"], "need T0 < T1"),
        (["{free}", "--out", "{tmp}/fig.png", "--window", "5", "6"], "within the trace"),
    ],
)
def test_cli_errors_are_one_line_exit_2(
    argv: list[str],
    message: str,
    traces: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    args = [a.format(tmp=tmp_path, **traces) for a in argv]
    assert main(["plot", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error: ") and message in err
    assert err.count("\n") == 1
    assert not (tmp_path / "fig.png").exists()
