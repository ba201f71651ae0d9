"""Tests of ``hdhil tune`` (hdhil.analysis.tuning): maximum innovation-likelihood tuning of the
recommended ripple filter, and of the innovation attributes it reads from the firmware's
filters (firmware/ripple.py ``RippleKalman`` / ``HarmonicKalman``, [Taghirad97] Eqs. 8-10)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import can
import numpy as np
import pytest
from runs import lockstep

from hdhil.analysis.tuning import (
    filter_inputs,
    mean_nll,
    paper_innovations,
    recommended_innovations,
    ripple_toml,
    tune_signals,
    with_tuning,
)
from hdhil.can.traces.reader import read_trace
from hdhil.cli import main
from hdhil.core.dataconf import from_dict
from hdhil.firmware.config import (
    LISTING_A1_RIPPLE,
    RECOMMENDED_SECTION5_RIPPLE,
    FirmwareConfig,
    paper_config,
    recommended_config,
)
from hdhil.firmware.isr import TorqueFilterChain
from hdhil.firmware.ripple import HarmonicKalman, RippleKalman
from hdhil.rig.scenario import load_scenario

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

Ts = 1e-3
CPR = 8000
#: The emulator's torque measurement noise: bridge noise 0.02 Nm rms (free-motion.toml
#: [plant.sensors]) plus 12-bit quantisation at 6.6 Nm/V (LSB 0.0322 Nm, LSB²/12).
EMULATOR_R = 0.02**2 + (20.0 / 4096 * 6.6) ** 2 / 12


# ------------------------------------------------------------------ innovation attributes
def test_harmonic_kalman_innovation_is_y_minus_prediction_and_its_variance() -> None:
    kf = HarmonicKalman(RECOMMENDED_SECTION5_RIPPLE, 100.0)
    assert math.isnan(kf.innovation) and math.isnan(kf.innovation_variance)
    rng = np.random.default_rng(3)
    angle = 0.0
    for k in range(300):
        velocity = 0.0 if k < 50 else 150.0  # standstill (Schmidt update) first, then moving
        angle += velocity * Ts
        y = 0.5 * math.cos(2 * angle) + 0.2 + rng.normal(0.0, 0.03)
        if kf.initialized:
            C = kf.regressor(angle)
            e_expected = y - float(C @ kf.x)
            S_expected = float(C @ kf.P @ C) + kf.cfg.r
        kf.step(y, velocity, angle)
        if k == 0:  # initialised from y: r = y, so nothing is left to explain
            assert kf.innovation == pytest.approx(0.0, abs=1e-15)
            C = kf.regressor(angle)  # P(0) = p0 I: S = p0 |C|² + R
            assert kf.innovation_variance == pytest.approx(kf.cfg.p0 * float(C @ C) + kf.cfg.r)
        else:
            assert kf.innovation == pytest.approx(e_expected, rel=1e-9, abs=1e-12)
            assert kf.innovation_variance == pytest.approx(S_expected, rel=1e-9)
    kf.step(math.nan, 150.0, angle)
    assert math.isnan(kf.innovation) and math.isnan(kf.innovation_variance)
    kf.reset()
    assert math.isnan(kf.innovation)


def test_ripple_kalman_innovation_and_variance_follow_eqs_8_9() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, Ts, 100.0)
    assert math.isnan(kf.innovation) and math.isnan(kf.innovation_variance)
    y0 = 0.7
    kf.step(y0, 150.0)  # listing: x[0] = x[2] = Delta_T, so C x = 2 y and e = -y
    assert kf.innovation == pytest.approx(-y0)
    assert kf.innovation_variance == pytest.approx(LISTING_A1_RIPPLE.r + 2 * LISTING_A1_RIPPLE.p0)
    rng = np.random.default_rng(4)
    for k in range(1, 200):
        y = 0.6 * math.sin(300.0 * k * Ts) + rng.normal(0.0, 0.05)
        C, x, P = kf.C, kf.x, kf.P
        kf.step(y, 150.0)
        assert kf.innovation == pytest.approx(y - float(C @ x), rel=1e-12, abs=1e-12)
        assert kf.innovation_variance == pytest.approx(LISTING_A1_RIPPLE.r + float(C @ P @ C))
    kf.step(0.1, math.inf)
    assert math.isnan(kf.innovation) and math.isnan(kf.innovation_variance)


def test_tuner_reads_the_same_innovations_as_the_firmware_chain() -> None:
    """Pre-computed filter inputs + the filter alone == the whole firmware chain."""
    n = 800
    rng = np.random.default_rng(5)
    velocity = np.minimum(np.arange(n) * 0.5, 150.0) + rng.normal(0.0, 0.05, n)
    theta = np.cumsum(velocity) * Ts
    encoder = np.round(theta * CPR / (2 * math.pi)).astype(np.int64) % 65536
    T_meas = 0.6 * np.cos(2 * theta) + 0.1 + rng.normal(0.0, 0.02, n)
    cfg = FirmwareConfig()
    e, S = recommended_innovations(filter_inputs(T_meas, velocity, encoder, cfg), cfg.ripple, 100.0)
    chain = TorqueFilterChain(cfg)
    for k in range(n):
        chain.step(float(T_meas[k]), float(velocity[k]), int(encoder[k]))
        assert e[k] == chain.kalman.innovation
        assert S[k] == chain.kalman.innovation_variance
    e_p, S_p = paper_innovations(T_meas, velocity, cfg)
    paper = TorqueFilterChain(paper_config(cfg))
    for k in range(n):
        paper.step(float(T_meas[k]), float(velocity[k]))
    assert e_p[-1] == paper.kalman.innovation and S_p[-1] == paper.kalman.innovation_variance


def test_mean_nll_is_the_gaussian_negative_log_likelihood() -> None:
    e = np.array([math.nan, 0.1, -0.2, 0.3])
    S = np.array([math.nan, 0.01, 0.04, 0.09])
    expected = np.mean(0.5 * (np.log(2 * np.pi * S[1:]) + e[1:] ** 2 / S[1:]))
    assert mean_nll(e, S) == pytest.approx(expected)
    assert mean_nll(e, S, 2, 3) == pytest.approx(0.5 * (math.log(2 * math.pi * 0.04) + 1.0))
    assert mean_nll(e, np.array([1.0, 0.0, 1.0, 1.0])) == math.inf


# ------------------------------------------------------------------------- synthetic data
def synthetic(n: int, R: float, q_h: float, q_r: float, seed: int) -> tuple[np.ndarray, ...]:
    """Data that follows the recommended filter's model exactly: 2x/4x motor-angle
    harmonics with random-walk coefficients (variance q_h per step), a random-walk residual
    (q_r) and white measurement noise (R), at a constant 150 rad/s (so T_exp = 0)."""
    rng = np.random.default_rng(seed)
    theta = 0.3 + 150.0 * np.arange(n) * Ts
    encoder = np.round(theta * CPR / (2 * math.pi)).astype(np.int64) % 65536
    y = 0.3 + np.cumsum(rng.normal(0.0, math.sqrt(q_r), n)) + rng.normal(0.0, math.sqrt(R), n)
    for m, a0, b0 in ((2.0, 0.6, 0.1), (4.0, 0.2, -0.15)):
        a = a0 + np.cumsum(rng.normal(0.0, math.sqrt(q_h), n))
        b = b0 + np.cumsum(rng.normal(0.0, math.sqrt(q_h), n))
        y += a * np.cos(m * theta) + b * np.sin(m * theta)
    return y, np.full(n, 150.0), encoder


@pytest.mark.slow
@pytest.mark.parametrize(
    ("R", "q_h", "q_r"),
    [(1e-3, 1e-6, 1e-4), (4e-4, 1e-5, 1e-5), (1e-2, 1e-7, 1e-3)],
)
def test_tuned_values_recover_the_true_noise_variances(R: float, q_h: float, q_r: float) -> None:
    res = tune_signals(*synthetic(4000, R, q_h, q_r, seed=11), FirmwareConfig(), max_evals=150)
    assert R / 2 < res.tuned["r"] < R * 2
    assert q_r / 3 < res.tuned["residual_q"] < q_r * 3
    assert q_h / 5 < res.tuned["q_motor"] < q_h * 5
    assert res.loglik_tuned >= res.loglik_default >= res.loglik_paper
    assert res.innovations["tuned"]["nis"] == pytest.approx(1.0, abs=0.05)  # S fits e
    assert res.evaluations <= 150 + 5  # Nelder-Mead may finish its last iteration
    assert res.rms is None  # arrays only: no truth


def test_budget_and_window() -> None:
    y, v, enc = synthetic(3000, 1e-3, 1e-6, 1e-4, seed=2)
    res = tune_signals(y, v, enc, FirmwareConfig(), max_evals=10, skip_s=0.5, max_window=1000)
    assert res.window == (500, 1500)
    assert res.evaluations <= 12
    assert res.loglik_tuned >= res.loglik_default


def test_with_tuning_sets_each_harmonic_group() -> None:
    ripple = with_tuning(
        RECOMMENDED_SECTION5_RIPPLE, {"q_motor": 1e-7, "q_output": 2e-9, "residual_q": 3e-3}
    )
    assert [o.q for o in ripple.oscillators] == [1e-7, 1e-7, 2e-9]
    assert ripple.residual_q == 3e-3 and ripple.r == RECOMMENDED_SECTION5_RIPPLE.r
    text = ripple_toml(ripple, ["a comment"])
    parsed = tomllib.loads(text)
    assert list(parsed) == ["firmware"] and list(parsed["firmware"]) == ["ripple"]
    assert from_dict(FirmwareConfig, parsed["firmware"], "firmware").ripple == ripple


# ------------------------------------------------------------------- emulated trace, CLI
@pytest.fixture(scope="module")
def traces(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 3 s misalignment run ([Taghirad97] §5), and the same trace without the truth channel
    and with only the controller's frames (no DRIVE_TPDO1)."""
    d = tmp_path_factory.mktemp("tune")
    full = d / "mis.blf"
    lockstep(load_scenario("misalignment"), duration_s=3.0, trace=full, evaluate=False)
    no_truth, no_sensor = d / "no_truth.blf", d / "no_sensor.blf"
    with (
        read_trace(full) as trace,
        can.Logger(str(no_truth)) as log_a,
        can.Logger(str(no_sensor)) as log_b,
    ):
        for msg in trace:
            if not msg.is_extended_id:
                log_a(msg)
                if msg.arbitration_id != 0x182:
                    log_b(msg)
    return {"full": full, "no_truth": no_truth, "no_sensor": no_sensor}


def _tune_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    assert main(["tune", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_cli_tunes_emulated_misalignment_and_writes_a_mergeable_toml(
    traces: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "tuned.toml"
    res = _tune_json(
        capsys, str(traces["full"]), "--scenario", "misalignment", "--max-evals", "80",
        "--out", str(out),
    )  # fmt: skip
    assert res["parameters"] == ["q_motor", "q_output", "residual_q", "r"]
    assert EMULATOR_R / 2 < res["tuned"]["r"] < EMULATOR_R * 2
    ll = res["loglik_per_sample"]
    assert ll["tuned"] >= ll["default"] >= ll["paper"]
    assert res["improvement_over_paper"] == pytest.approx(ll["tuned"] - ll["paper"])
    # 3000 operational samples, plus the few of the stop walk while the drive is enabled.
    start, end = res["window_samples"]
    assert start == 200 and 3000 <= end <= 3005 and res["evaluations"] <= 85
    rms = res["rms_vs_truth"]  # the check the tuner did not use
    assert rms["tuned"] < rms["default"] < rms["raw"]

    parsed = tomllib.loads(out.read_text())
    assert list(parsed) == ["firmware"] and list(parsed["firmware"]) == ["ripple"]
    merged = load_scenario("misalignment", overrides=parsed)
    ripple = from_dict(FirmwareConfig, merged.firmware, "firmware").ripple
    assert ripple.mode == "recommended"
    assert ripple.r == pytest.approx(res["tuned"]["r"], rel=1e-3)
    assert ripple.residual_q == pytest.approx(res["tuned"]["residual_q"], rel=1e-3)
    assert [o.q for o in ripple.oscillators] == pytest.approx(
        [res["tuned"]["q_motor"]] * 2 + [res["tuned"]["q_output"]], rel=1e-3
    )
    assert merged.plant == load_scenario("misalignment").plant  # only the filter changes


@pytest.mark.slow
def test_cli_text_report(traces: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        main(["tune", str(traces["full"]), "--scenario", "misalignment", "--max-evals", "5"]) == 0
    )
    text = capsys.readouterr().out
    for needle in ("paper", "default", "tuned", "improvement over the paper's tuning",
                   "NOT used by the tuner", "loglik/sample"):  # fmt: skip
        assert needle in text


@pytest.mark.slow
def test_truth_is_not_used(traces: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    argv = ("--scenario", "misalignment", "--max-evals", "30")
    with_truth = _tune_json(capsys, str(traces["full"]), *argv)
    without = _tune_json(capsys, str(traces["no_truth"]), *argv)
    assert without["tuned"] == with_truth["tuned"]
    assert without["loglik_per_sample"] == with_truth["loglik_per_sample"]
    assert without["rms_vs_truth"] is None


@pytest.mark.slow
def test_tune_recording_from_python_gives_what_the_command_prints(
    traces: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """The library alone (no argparse) tunes a recording as ``hdhil tune --json`` does."""
    from hdhil.analysis.tuning import tune_recording
    from hdhil.rig.evaluate import recording_from_trace

    fw = from_dict(FirmwareConfig, load_scenario("misalignment").firmware, "firmware")
    rec, damage = recording_from_trace(traces["full"], fw.sample_period_s)
    assert not damage
    res = tune_recording(rec, fw, max_evals=20).to_json()
    cli = _tune_json(capsys, str(traces["full"]), "--scenario", "misalignment", "--max-evals", "20")
    for key in ("parameters", "default", "tuned", "paper", "loglik_per_sample", "innovations",
                "window_samples", "evaluations", "converged", "rms_vs_truth"):  # fmt: skip
        assert res[key] == cli[key], key


def test_paper_mode_scenario_is_tuned_as_recommended(tmp_path: Path) -> None:
    """A paper-mode configuration is compared with, but the tuned filter is recommended."""
    cfg = paper_config(FirmwareConfig())
    res = tune_signals(*synthetic(1500, 1e-3, 1e-6, 1e-4, seed=1), cfg, max_evals=20)
    assert res.tuned_ripple.mode == "recommended"
    assert res.default == pytest.approx(
        {"q_motor": recommended_config(cfg).ripple.oscillators[0].q,
         "residual_q": recommended_config(cfg).ripple.residual_q,
         "r": recommended_config(cfg).ripple.r}
    )  # fmt: skip
    assert res.paper == {"q_motor": 1e3, "r": 1.0}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["/nonexistent/trace.blf"], "no such file"),
        (["{no_sensor}"], "no DRIVE_TPDO1 frames"),
        (["{full}", "--skip", "2.9"], "too few samples"),
        (["{full}", "--out", "{tmp}/tuned.json"], "must be a .toml file"),
        (["{full}", "--out", "{tmp}/missing/tuned.toml"], "does not exist"),
        (["{full}", "--max-evals", "0"], "--max-evals: must be >= 1"),
        (["{full}", "--skip", "-1"], "--skip: must be"),
        (["{full}", "--scenario", "no-such-scenario"], "no-such-scenario"),
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
    assert main(["tune", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error: ") and message in err
    assert err.count("\n") == 1


def test_a_filter_of_too_many_harmonics_is_refused_before_any_work() -> None:
    """Every likelihood evaluation runs the filter over the window at a cost growing with
    the square of the harmonics: 32 of them made the default budget take most of an
    hour.  Past MAX_TUNED_HARMONICS the tuner refuses in one line, before evaluating."""
    import dataclasses

    from hdhil.analysis.tuning import MAX_TUNED_HARMONICS
    from hdhil.core.errors import UserError
    from hdhil.firmware.config import Oscillator, RippleFilterConfig

    y, v, enc = synthetic(600, 1e-3, 1e-6, 1e-4, seed=2)

    def tuned(harmonics: int) -> None:
        ripple = RippleFilterConfig(
            oscillators=tuple(Oscillator("motor", float(m)) for m in range(1, harmonics + 1))
        )
        cfg = dataclasses.replace(FirmwareConfig(), ripple=ripple)

        def evaluated(n: int) -> None:
            raise AssertionError("a likelihood evaluation ran")

        tune_signals(y, v, enc, cfg, max_evals=1, max_window=300, on_evaluation=evaluated)

    with pytest.raises(
        UserError, match=f"33 harmonics; hdhil tune takes at most {MAX_TUNED_HARMONICS}"
    ):
        tuned(33)
    with pytest.raises(AssertionError, match="a likelihood evaluation ran"):
        tuned(MAX_TUNED_HARMONICS)  # at the cap it tunes
