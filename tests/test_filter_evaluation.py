"""The ripple-filter evaluation shows what each filter does to a varying torque: gain and
lag beside the RMS error for every candidate (a dash, with the reason, where the true
torque hardly varies), a 5 Hz low-pass among them, the best candidate named, a line on
when a low-pass wins and why the firmware's filter is worse than raw where it is; no
ripple table where the ripple filter is out of the loop; the same figures from the
trace as from the run."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hdhil.rig.evaluate import (
    BUTTERWORTH_CUTOFFS_HZ,
    MIN_TRUE_STD_NM,
    estimate_alignment,
    evaluation_notes,
    format_evaluation,
)
from hdhil.rig.scenario import load_scenario

Ts = 1e-3


def _steps(n: int = 6000, seed: int = 0) -> np.ndarray:
    """A true torque of steps every 0.5 s, ±1 Nm."""
    rng = np.random.default_rng(seed)
    levels = rng.uniform(-1.0, 1.0, n // 500 + 1)
    return np.repeat(levels, 500)[:n]


@pytest.mark.parametrize("gain", [1.0, 0.36])
@pytest.mark.parametrize("delay", [0, 5, 22])
def test_gain_and_lag_of_a_scaled_delayed_copy(gain: float, delay: int) -> None:
    truth = _steps()
    x = np.empty_like(truth)
    x[:delay] = truth[0] * gain
    x[delay:] = gain * truth[: len(truth) - delay]
    x += 0.05 * np.random.default_rng(1).standard_normal(len(x))  # sensor noise
    a = estimate_alignment(x, truth, Ts)
    assert a.lag_ms == pytest.approx(delay, abs=0.3)
    assert a.gain == pytest.approx(gain, abs=0.01)


def test_lag_resolves_fractions_of_a_sample() -> None:
    t = np.arange(6000) * Ts
    truth = np.sin(2 * np.pi * 3.0 * t) + 0.5 * np.sin(2 * np.pi * 7.0 * t)
    delayed = np.sin(2 * np.pi * 3.0 * (t - 2.5e-3)) + 0.5 * np.sin(2 * np.pi * 7.0 * (t - 2.5e-3))
    a = estimate_alignment(delayed, truth, Ts)
    assert a.lag_ms == pytest.approx(2.5, abs=0.1)
    assert a.gain == pytest.approx(1.0, abs=0.01)


def test_no_gain_or_lag_where_the_true_torque_hardly_varies() -> None:
    rng = np.random.default_rng(2)
    truth = 0.07 + 0.007 * rng.standard_normal(3000)  # free motion: std ~7 mNm
    assert MIN_TRUE_STD_NM > 0.007
    a = estimate_alignment(truth + 0.02 * rng.standard_normal(3000), truth, Ts)
    assert a.lag_ms is None and a.gain is None


def test_a_five_hertz_low_pass_is_a_candidate() -> None:
    assert 5.0 in BUTTERWORTH_CUTOFFS_HZ


def _candidate(name: str, rms: float, raw: float, gain: float | None = 1.0,
               lag: float | None = 0.0, dB: float = 30.0) -> dict[str, Any]:  # fmt: skip
    return {
        "name": name, "rms_error": rms, "rms_ratio": rms / raw, "gain": gain, "lag_ms": lag,
        "reduction_dB": {"2x motor": dB, "4x motor": dB, "1x output": 0.0},
        "harmonics": {}, "misalignment_pp": 0.001,
    }  # fmt: skip


def _evaluation(candidates: list[dict[str, Any]], std: float, ripple: float = 0.5) -> dict:
    return {
        "samples": 5000, "skip_s": 0.3, "rms_true": 0.5, "std_true": std,
        "true_ripple": {"2x motor": ripple, "4x motor": ripple / 2, "1x output": 0.0},
        "candidates": candidates,
    }  # fmt: skip


def test_notes_name_the_best_candidate_and_the_dash() -> None:
    ev = _evaluation(
        [
            _candidate("raw", 0.45, 0.45, None, None, 0.0),
            _candidate("firmware (recommended)", 0.0256, 0.45, None, None),
            _candidate("butterworth 5 Hz", 0.0056, 0.45, None, None),
        ],
        std=0.007,
    )
    notes = evaluation_notes(ev)
    assert notes[0].startswith("best by RMS error: butterworth 5 Hz")
    assert "0.0256" in notes[0]  # the firmware's figure beside it
    assert notes[1].startswith("a low-pass wins here: the true torque hardly varies")
    assert any(n.startswith("gain, lag —: the true torque varies too little") for n in notes)
    text = format_evaluation(ev)
    assert "std 0.0070 Nm" in text
    row = next(line for line in text.splitlines() if "butterworth 5 Hz" in line)
    assert row.split()[5:7] == ["—", "—"]  # gain, lag


def test_notes_on_a_varying_torque_where_the_kalman_filter_wins() -> None:
    ev = _evaluation(
        [
            _candidate("raw", 0.45, 0.45, 0.998, 0.6, 0.0),
            _candidate("firmware (recommended)", 0.0305, 0.45, 0.996, 0.0),
            _candidate("butterworth 10 Hz", 0.107, 0.45, 0.979, 21.6),
        ],
        std=0.43,
    )
    notes = evaluation_notes(ev)
    assert notes[0] == ("best by RMS error: firmware (recommended), "
                        "0.0305 Nm")  # fmt: skip
    assert notes[1].startswith("a low-pass wins only on a near-constant load")
    assert not any("—" in n or "worse than raw" in n for n in notes)
    header = format_evaluation(ev).splitlines()[1].split()
    assert header[header.index("raw") + 1 :][:2] == ["gain", "lag/ms"]  # beside the RMS


def test_a_firmware_filter_worse_than_raw_is_explained() -> None:
    """The chirp case: no ripple in the plant, a torque sweeping through the ripple
    frequencies; the filter takes true torque for ripple."""
    ev = _evaluation(
        [
            _candidate("raw", 0.121, 0.121, 1.0, 0.0, 0.0),
            _candidate("firmware (recommended)", 0.948, 0.121, 0.994, 0.54, -26.3),
        ],
        std=11.6,
        ripple=0.0,
    )
    notes = evaluation_notes(ev)
    assert notes[0].startswith("best by RMS error: raw, 0.1210 Nm")
    worse = next(n for n in notes if "worse than raw" in n)
    assert "7.8x raw's RMS error" in worse
    assert "no ripple" in worse and "26 dB above raw's" in worse


def test_no_ripple_score_where_the_ripple_filter_is_out_of_the_loop() -> None:
    import dataclasses

    tracking = load_scenario("lqg-tracking")  # JTF1 on the measured torque
    assert tracking.scored == ("tracking",)
    asked = dataclasses.replace(tracking, scores=("tracking", "ripple"))
    assert asked.scored == ("tracking",)
    only_ripple = dataclasses.replace(tracking, scores=("ripple",))
    assert only_ripple.scored == ("tracking",)
    # the regulator on the ripple-filtered torque: the filter is in the loop, scored
    assert load_scenario("lqg-misalignment").scored == ("tracking", "ripple")
    assert load_scenario("chirp").scored == ("ripple",)  # no law: the telemetry's torque


def test_sine_load_is_shipped_and_documented() -> None:
    sc = load_scenario("sine-load")
    load = sc.plant.load
    assert load.kind == "sine" and load.frequency_Hz == 3.0
    assert sc.scored == ("ripple",)
    reference = Path(__file__).parents[1] / "docs" / "reference" / "scenarios.md"
    assert "sine-load" in reference.read_text(encoding="utf-8")


# ----------------------------------------------------------------- runs (slow)


def _by_name(evaluation: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {c["name"].split(" (")[0]: c for c in evaluation["candidates"]}


@pytest.mark.slow
def test_sine_load_shows_gain_and_lag() -> None:
    from runs import lockstep

    r = lockstep("sine-load", duration_s=3.0, trace=None)
    ev = r.evaluation
    assert ev["std_true"] > MIN_TRUE_STD_NM
    c = _by_name(ev)
    assert c["kalman recommended"]["gain"] == pytest.approx(1.0, abs=0.02)
    assert c["kalman recommended"]["lag_ms"] < 1.0
    assert c["kalman paper"]["gain"] < 0.5  # listing A.1 absorbs the slow torque
    assert c["butterworth 10 Hz"]["lag_ms"] > 15.0
    assert c["butterworth 5 Hz"]["lag_ms"] > c["butterworth 10 Hz"]["lag_ms"]
    assert c["butterworth 5 Hz"]["gain"] < c["butterworth 10 Hz"]["gain"]


@pytest.mark.slow
def test_free_motion_prints_dashes_and_names_the_low_pass() -> None:
    from runs import lockstep

    r = lockstep("free-motion", trace=None)
    ev = r.evaluation
    assert ev["std_true"] < MIN_TRUE_STD_NM
    assert all(c["gain"] is None and c["lag_ms"] is None for c in ev["candidates"])
    best = min(ev["candidates"], key=lambda c: c["rms_error"])
    assert best["name"].startswith("butterworth")
    text = format_evaluation(ev)
    assert f"best by RMS error: {best['name']}" in text
    assert "a low-pass wins here" in text


@pytest.mark.slow
def test_evaluate_of_the_trace_gives_the_runs_gain_and_lag(tmp_path: Path) -> None:
    from runs import lockstep

    from hdhil.rig.trace_score import score_trace

    trace = tmp_path / "ts.blf"
    r = lockstep("torque-steps", duration_s=2.0, trace=trace)
    replayed, damage = score_trace(trace)
    assert damage == ""
    assert replayed["headline"] == r.headline
    assert replayed["std_true"] == pytest.approx(r.evaluation["std_true"], rel=1e-12)
    for live, again in zip(r.evaluation["candidates"], replayed["candidates"], strict=True):
        assert live["name"] == again["name"]
        for key in ("gain", "lag_ms", "rms_error"):
            assert again[key] is not None and not math.isnan(again[key]), key
            assert again[key] == pytest.approx(live[key], rel=1e-9), (live["name"], key)


def test_the_firmware_row_under_a_law_is_named_for_the_laws_estimate() -> None:
    """With a law the telemetry's torque is τ̂s, not the ripple filter's output."""
    from hdhil.rig.evaluate import _Candidates

    lqg = load_scenario("lqg-misalignment").firmware
    assert _Candidates(lqg, "raw", None)._firmware == "firmware (LQG on recommended)"
    plain = load_scenario("free-motion").firmware
    assert _Candidates(plain, "raw", None)._firmware == "firmware (recommended)"
    rows = [
        _candidate("raw", 0.84, 0.84),
        _candidate("firmware (LQG on recommended)", 0.0178, 0.84),
    ]
    ev = _evaluation(rows, std=0.34)
    assert any("regulator's estimate τ̂s" in n for n in evaluation_notes(ev))
