"""Tests of ``hdhil bench`` (tools/hdhil/bench.py): the report's structure on a tiny run.

Only the shape of the report and the sanity of its figures (positive, finite) are
checked, never a timing threshold: the machines running the tests are shared and noisy.
"""

from __future__ import annotations

import json
import math

import pytest

from hdhil.bench import LOCKSTEP_SCENARIOS, format_bench, run_benchmarks
from hdhil.cli import main


def _positive(x: float) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.fixture(scope="module")
def report() -> dict:
    return run_benchmarks(duration_s=0.1, repeat=1, quick=True)


def test_machine_and_settings(report: dict) -> None:
    m = report["machine"]
    assert m["cpu"] and m["python"].count(".") == 2
    assert m["cores"] >= 1 and m["cores_usable"] >= 1
    assert report["mode"] == "quick"
    assert report["settings"]["repeat"] == 1
    assert _positive(report["wall_s"])


def test_lockstep_rows(report: dict) -> None:
    rows = report["lockstep"]
    simbus = [(r["scenario"], r["logging"]) for r in rows if r["interface"] == "simbus"]
    assert simbus == [(name, log) for name, _ in LOCKSTEP_SCENARIOS for log in (True, False)]
    virtual = [r for r in rows if r["interface"] == "virtual"]
    assert [r["scenario"] for r in virtual] == ["free-motion"]
    states = {r["scenario"]: r["filter_states"] for r in rows}
    assert states["misalignment"] > states["free-motion"]
    for r in rows:
        for key in ("median", "min", "max", "us_per_cycle", "frames_per_cycle", "cycles"):
            assert _positive(r[key]), (r["scenario"], key, r[key])
        assert r["min"] <= r["median"] <= r["max"]
        assert r["runs"] == 1


def test_stage_rows(report: dict) -> None:
    stages = report["stages"]
    assert _positive(stages["timer_overhead_us"])
    names = {r["stage"] for r in stages["rows"]}
    assert {
        "ADC read + calibration",
        "differentiator",
        "ripple Kalman, 4th order",
        "ripple Kalman, 6th order",
        "LQG control stage",
        "whole interrupt",
        "plant step (advance + sample)",
    } <= names
    kalman = [r["config"] for r in stages["rows"] if r["stage"].startswith("ripple Kalman")]
    assert sum("paper" in c for c in kalman) == 2
    assert sum("recommended" in c for c in kalman) == 2
    for r in stages["rows"]:
        assert r["calls"] == report["settings"]["stage_calls"]
        assert _positive(r["median_us"]) and _positive(r["p99_us"])
        assert r["p99_us"] >= r["median_us"]


def test_filter_and_memory(report: dict) -> None:
    assert [r["mode"] for r in report["filter"]] == ["recommended", "paper"]
    for r in report["filter"]:
        assert r["rows"] == report["settings"]["filter_rows"]
        assert _positive(r["median"])
    mem = report["memory"]
    for key in ("peak_rss_MB", "rss_before_MB", "rss_after_MB", "simulated_s", "trace_MB"):
        assert _positive(mem[key]), key
    assert mem["peak_rss_MB"] >= mem["rss_after_MB"] * 0.99
    for key in ("rss_growth_MB", "rss_growth_MB_per_sim_minute",
                "rss_growth_MB_per_sim_hour_extrapolated"):  # fmt: skip
        assert math.isfinite(mem[key]), key
    assert mem["simulated_s"] == pytest.approx(report["settings"]["memory_duration_s"])


def test_text_report_and_json_roundtrip(report: dict) -> None:
    text = format_bench(report)
    assert report["machine"]["cpu"] in text
    for heading in ("Lockstep real-time factor", "Firmware compute per call",
                    "Offline `hdhil filter`", "Memory"):  # fmt: skip
        assert heading in text
    assert "| free-motion" in text and "| lqg-tracking" in text
    assert json.loads(json.dumps(report)) == report


def test_cli_rejects_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--quick", "--repeat", "0"]) == 2
    assert "--repeat" in capsys.readouterr().err
