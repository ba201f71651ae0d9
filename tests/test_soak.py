"""Tests of ``hdhil soak`` (hdhil.analysis.soak) on short runs.

The per-block figures are checked against the run's own whole-run scorers (nothing lost
between blocks), and each verdict is made to fail by a fault injected into the running
firmware through the ``after_block`` hook: a non-finite value, a broken covariance, a
sensor-gain drift, a memory leak.  No timing is asserted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import itertools
import json
import math
import mmap
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from runs import lockstep

import hdhil.commands.soak as soak_command
from hdhil.analysis.soak import Block, SoakLimits, SoakReport, run_soak, stationarity
from hdhil.cli import main
from hdhil.core.dataconf import ConfigError
from hdhil.firmware.controller import ControllerNode
from hdhil.rig.request import resolve
from hdhil.rig.scenario import load_scenario

VERDICTS = [
    "run completed",
    "no non-finite value",
    "covariance SPD",
    "torque error stationary",
    "tracking error stationary",
    "memory growth",
]


def _strict_json(text: str) -> Any:
    def no_constant(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=no_constant)


def _cli_report(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict[str, Any]]:
    code = main(["soak", *args, "--json"])
    return code, _strict_json(capsys.readouterr().out)


def _verdict(report: dict[str, Any] | SoakReport, name: str) -> Any:
    verdicts = report["verdicts"] if isinstance(report, dict) else report.verdicts
    (v,) = [v for v in verdicts if (v["name"] if isinstance(v, dict) else v.name) == name]
    return v


def _short(after_block: Any, duration_s: float = 12.0, block_s: float = 3.0) -> SoakReport:
    return run_soak(
        resolve("lqg-tracking", duration_s=duration_s),
        block_s=block_s,
        limits=SoakLimits(settle_s=block_s),
        after_block=after_block,
    )


# ------------------------------------------------------------------ a healthy short soak
@pytest.fixture(scope="module")
def healthy(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, dict[str, Any], Path]:
    """lqg-tracking (LQG + ripple filter), 20 s in blocks of 5 s, BLF trace, via the CLI."""
    trace = tmp_path_factory.mktemp("soak") / "soak.blf"
    out = io.StringIO()  # capsys is function-scoped: capture by hand

    with contextlib.redirect_stdout(out):
        code = main(
            ["soak", "--scenario", "lqg-tracking", "--duration", "20", "--every", "5",
             "--settle", "5", "--trace", str(trace), "--json"]
        )  # fmt: skip
    return code, _strict_json(out.getvalue()), trace


@pytest.mark.slow
def test_healthy_soak_blocks_partition_the_run(healthy: tuple[int, dict, Path]) -> None:
    _code, r, _trace = healthy
    blocks = r["blocks"]
    assert [b["index"] for b in blocks] == [1, 2, 3, 4]
    assert [b["end_s"] for b in blocks] == pytest.approx([5.0, 10.0, 15.0, 20.0])
    assert [b["start_s"] for b in blocks] == pytest.approx([0.0, 5.0, 10.0, 15.0])
    assert r["samples_done"] == r["samples_expected"] == 20_000
    # Every telemetry sample the run's own scorer saw is in exactly one block ...
    whole = r["run"]["torque"]
    n = np.array([b["samples"] for b in blocks])
    assert n.sum() == whole["samples"] == 20_000
    # ... and the per-block RMS errors recombine into the whole-run figures.
    for key in ("rms_error_filtered", "rms_error_raw"):
        rms = np.array([b[key] for b in blocks])
        assert math.sqrt((n * rms**2).sum() / n.sum()) == pytest.approx(whole[key], rel=1e-9)
    assert max(b["max_error_filtered"] for b in blocks) == pytest.approx(
        whole["max_error_filtered"]
    )
    tracking = r["run"]["tracking"]
    t_rms = np.array([b["tracking_rms"] for b in blocks])
    assert math.sqrt((n * t_rms**2).sum() / n.sum()) == pytest.approx(
        tracking["rms_error"], rel=1e-9
    )
    assert max(b["tracking_max"] for b in blocks) == pytest.approx(tracking["max_abs_error"])


@pytest.mark.slow
def test_healthy_soak_filter_health_resources_and_verdicts(
    healthy: tuple[int, dict, Path],
) -> None:
    code, r, trace = healthy
    blocks = r["blocks"]
    states = r["run"]["controller"]["filter_states"]
    assert states == 5  # lqg-tracking: the 4th-order model plus the residual
    for b in blocks:
        assert b["nonfinite"] == {}
        assert b["covariance_resets"] == 0 and b["skipped_samples"] == 0
        assert b["covariance_symmetric"] is True
        assert b["covariance_min_eigenvalue"] > 0
        assert b["rss_MB"] > 0 and b["wall_s"] > 0
    # The final block's covariance is the one the run reports after it ended.
    assert blocks[-1]["covariance_min_eigenvalue"] == pytest.approx(
        r["run"]["controller"]["covariance_min_eigenvalue"], rel=1e-12
    )
    sizes = [b["trace_MB"] for b in blocks]
    assert all(later > earlier for earlier, later in itertools.pairwise(sizes))
    assert trace.stat().st_size / 2**20 >= sizes[-1]
    assert [v["name"] for v in r["verdicts"]] == VERDICTS
    assert all(v["passed"] for v in r["verdicts"]), r["verdicts"]
    assert r["passed"] is True and code == 0
    tracking = _verdict(r, "tracking error stationary")["values"]
    assert tracking["blocks"] == 3  # blocks starting at or after --settle 5 s
    rms = [b["tracking_rms"] for b in blocks[1:]]
    middles = [(b["start_s"] + b["end_s"]) / 2 for b in blocks[1:]]
    slope = np.polyfit(middles, rms, 1)[0]
    assert tracking["mean"] == pytest.approx(np.mean(rms))
    assert tracking["relative_change"] == pytest.approx(slope * 10.0 / np.mean(rms))


@pytest.mark.slow
def test_text_report_lists_every_block_and_verdict(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["soak", "--scenario", "misalignment", "--duration", "4", "--every", "2",
                 "--settle", "0", "--trace", ""])  # fmt: skip
    text = capsys.readouterr().out
    # Block 1 holds the filter's learning of the misalignment: not stationary from 0 s.
    (torque,) = [line for line in text.splitlines() if "torque error stationary" in line]
    assert "FAIL" in torque and code == 1
    rows = [line.split() for line in text.splitlines() if line.strip()[:1].isdigit()]
    assert [row[0] for row in rows] == ["1", "2"]
    for name in VERDICTS:
        if name != "tracking error stationary":  # no control law in this scenario
            assert name in text
    assert "tracking error stationary" not in text
    assert "result: " in text


@pytest.mark.slow
def test_default_scenario_runs_the_six_order_filter_under_lqg(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, r = _cli_report(capsys, "--duration", "8", "--every", "4", "--trace", "")
    assert r["scenario"] == "lqg-misalignment"
    assert r["run"]["controller"]["filter_states"] == 7  # 2x, 4x motor, 1x output, residual
    assert r["run"]["tracking"]["law"] == "jtf1"
    assert all(v["passed"] for v in r["verdicts"][:3])
    # 8 s ends before the scenario's settling time: stationarity cannot be shown.
    stat = _verdict(r, "torque error stationary")
    assert not stat["passed"] and "needs at least 3 blocks" in stat["detail"]
    assert code == 1


# --------------------------------------------------------------- faults fail verdicts
def _poison_differentiator(controller: ControllerNode, block: Block) -> None:
    if block.index == 1:
        controller.isr.chain.differentiator.a_1 = math.nan


@pytest.mark.slow
def test_injected_nan_fails_the_non_finite_verdict_and_exits_1(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(
        soak_command, "run_soak", functools.partial(run_soak, after_block=_poison_differentiator)
    )
    code, r = _cli_report(capsys, "--scenario", "lqg-tracking", "--duration", "9",
                          "--every", "3", "--settle", "3", "--trace", "")  # fmt: skip
    assert code == 1
    first, *later = r["blocks"]
    assert first["nonfinite"] == {} and first["skipped_samples"] == 0
    for b in later:
        assert b["nonfinite"].get("interrupt outputs", 0) > 0  # acceleration, T_expected, ...
        assert b["skipped_samples"] == 3000  # the filter skips every NaN input
    v = _verdict(r, "no non-finite value")
    assert not v["passed"]
    assert v["values"]["blocks_with_nonfinite"] == [2, 3]
    assert v["values"]["skipped_samples"] == 6000
    assert _verdict(r, "run completed")["passed"]


@pytest.mark.slow
def test_broken_covariance_fails_the_spd_verdict() -> None:
    def break_P(controller: ControllerNode, block: Block) -> None:
        if block.index == 1:
            kalman = controller.isr.chain.kalman
            kalman._P = tuple(-abs(p) for p in kalman._P)  # negative diagonal: not SPD

    r = _short(break_P, duration_s=9.0)
    assert [b.covariance_resets for b in r.blocks] == [0, 1, 0]
    v = _verdict(r, "covariance SPD")
    assert not v.passed and v.values["covariance_resets"] == 1
    assert _verdict(r, "no non-finite value").passed
    assert not r.passed


@pytest.mark.slow
def test_sensor_gain_drift_fails_the_stationarity_verdicts() -> None:
    def drift(controller: ControllerNode, block: Block) -> None:
        if block.index == 3:  # the firmware's torque gain 10 % off from block 4 on
            isr = controller.isr
            cal = dataclasses.replace(
                isr.cfg.calibration, volt2Nm=isr.cfg.calibration.volt2Nm * 1.1
            )
            isr.cfg = dataclasses.replace(isr.cfg, calibration=cal)

    r = _short(drift, duration_s=18.0)
    torque = _verdict(r, "torque error stationary")
    tracking = _verdict(r, "tracking error stationary")
    # a step up: the fitted line's change, and its interval, beyond the tolerance
    assert not torque.passed and torque.values["relative_change"] > 0.1
    assert not tracking.passed and tracking.values["relative_change"] > 0.1
    assert _verdict(r, "covariance SPD").passed


@pytest.mark.slow
def test_memory_growth_verdict_sees_a_leak() -> None:
    kept: list[mmap.mmap] = []

    def leak(controller: ControllerNode, block: Block) -> None:
        if block.index == 1:
            # 32 MB of fresh pages, every one touched: an anonymous mapping, not the heap,
            # where earlier tests may have left freed memory resident for reuse
            region = mmap.mmap(-1, 32 * 2**20)
            region.write(b"\x01" * len(region))
            kept.append(region)

    r = _short(leak, duration_s=6.0, block_s=2.0)
    v = _verdict(r, "memory growth")
    assert not v.passed and v.values["growth_MB"] > 20.0
    assert r.blocks[1].rss_MB - r.blocks[0].rss_MB > 30.0


# ------------------------------------------------------------------- verdict arithmetic
def _blocks(values: list[float], block_s: float = 60.0) -> list[Block]:
    return [
        Block(index=i + 1, start_s=i * block_s, end_s=(i + 1) * block_s, samples=1000,
              rms_error_filtered=v, rms_error_raw=1.0, max_error_filtered=v,
              tracking_rms=None, tracking_max=None, covariance_asymmetry=0.0,
              covariance_min_eigenvalue=1e-4, covariance_symmetric=True, nonfinite={},
              covariance_resets=0, skipped_samples=0, rss_MB=100.0, trace_MB=None, wall_s=1.0)
        for i, v in enumerate(values)
    ]  # fmt: skip


def _printed_change(detail: str) -> tuple[float, float]:
    """The relative change and its 95 % half-width, as the verdict's detail prints them."""
    m = re.search(r"changes by ([-+][\d.]+)% ± ([\d.]+)% \(95 %\)", detail)
    assert m, detail
    return float(m[1]) / 100, float(m[2]) / 100


def _agrees(v: Any, tolerance: float) -> bool:
    """The verdict is the one its printed figures give (to their printed rounding)."""
    change, ci = _printed_change(v.detail)
    return v.passed == (abs(change) + ci <= tolerance + 0.001)


def test_stationarity_verdict_follows_the_printed_trend() -> None:
    rng = np.random.default_rng(7)
    limits = SoakLimits(settle_s=60.0, tolerance=0.05)
    flat = list(0.026 + 0.0005 * rng.standard_normal(60))
    v = stationarity("torque", _blocks(flat), flat, limits)
    kept = flat[1:]  # the first block starts before the settling time
    hours = [(i + 1.5) / 60.0 for i in range(59)]  # the blocks' middles
    slope = np.polyfit(hours, kept, 1)[0]
    assert v.values["blocks"] == 59 and v.values["span_s"] == pytest.approx(58 * 60.0)
    assert v.values["slope_per_hour"] == pytest.approx(slope)
    assert v.values["relative_change"] == pytest.approx(slope * 58 / 60 / np.mean(kept))
    assert v.passed and _agrees(v, 0.05)
    drifting = [x * (1.0 + 0.5 * i / 60) for i, x in enumerate(flat)]
    d = stationarity("torque", _blocks(drifting), drifting, limits)
    assert not d.passed and _agrees(d, 0.05)
    assert d.values["relative_change"] - d.values["relative_change_ci95"] > 0.05
    short = stationarity("torque", _blocks(flat[:3]), flat[:3], limits)
    assert not short.passed and "needs at least 3 blocks" in short.detail


def test_stationarity_fails_a_trend_the_half_means_hid() -> None:
    # 4 blocks after settling, +15 % from the first to the last block's middle: the last
    # half's mean is only ~9.8 % above the first half's, but the fitted change and its
    # interval are well beyond the 10 % tolerance.
    values = [1.0, 1.05, 1.10, 1.15]
    v = stationarity("torque", _blocks(values, 20.0), values, SoakLimits())
    assert v.values["relative_change"] == pytest.approx(0.15 / np.mean(values))
    assert not v.passed and _agrees(v, 0.10)
    # a step between two flat halves is not a line: wide interval, not shown stationary
    step = [1.0, 1.0, 1.0, 10.0, 10.0, 10.0]
    s = stationarity("torque", _blocks(step, 3.0), step, SoakLimits())
    assert not s.passed and _agrees(s, 0.10)


def test_stationarity_passes_a_small_change_over_a_short_run() -> None:
    # `hdhil soak --duration 120`'s torque error: +153 % of the mean per hour, which over
    # the 60 s tested is +2.5 % ± 0.6 %: stationary, and the detail says so.
    values = [0.43331, 0.03508, 0.01654, 0.01669, 0.01685, 0.01696]
    v = stationarity("torque", _blocks(values, 20.0), values, SoakLimits(settle_s=40.0))
    assert v.passed and _agrees(v, 0.10)
    assert v.values["relative_slope_per_hour"] > 1.0
    assert "+2.5% ± 0.6% (95 %)" in v.detail and "over the 60 s" in v.detail
    assert "within ±10%" in v.detail and "per hour" not in v.detail


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0.0, 10.0), min_size=3, max_size=12),
    st.floats(0.01, 1.0),
)
def test_stationarity_verdict_agrees_with_its_figures(values: list[float], tol: float) -> None:
    v = stationarity("torque", _blocks(values, 5.0), values, SoakLimits(tolerance=tol))
    change, ci = v.values["relative_change"], v.values["relative_change_ci95"]
    assert v.passed == (abs(change) + ci <= tol)
    if math.isfinite(change):
        assert f"{change:+.1%} ± {ci:.1%} (95 %)" in v.detail
        assert ("not within" not in v.detail) == v.passed


# ------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--every", "0"], "--every"),
        (["--every", "0.0005"], "whole number"),
        (["--duration", "0"], "--duration: must be > 0"),
        (["--tolerance", "0"], "--tolerance: must be > 0"),
        (["--settle", "-1"], "--settle: must be >= 0"),
        (["--scenario", "no-such-scenario"], "no-such-scenario"),
        (["--trace", "/nonexistent-dir/x.blf"], "does not exist"),
    ],
)
def test_bad_input_is_a_one_line_error(
    capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    code = main(["soak", "--duration", "1", *args])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("hdhil: error:") and message in err
    assert len(err.strip().splitlines()) == 1


def test_run_lockstep_monitor_is_called_every_n_samples() -> None:
    seen: list[int] = []
    lockstep(
        load_scenario("free-motion"),
        duration_s=1.0,
        evaluate=False,
        monitor=lambda c: seen.append(c.isr.samplecount),
        monitor_every=300,
    )
    assert seen == [300, 600, 900]
    with pytest.raises(ConfigError, match="monitor_every"):
        lockstep(load_scenario("free-motion"), duration_s=0.01, monitor=print, monitor_every=0)
