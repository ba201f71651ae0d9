"""Tests of ``hdhil bench`` (hdhil.analysis.benchmarks): the report's structure on a tiny run.

Only the shape of the report and the sanity of its figures (positive, finite) are
checked, never a timing threshold: the machines running the tests are shared and noisy.
"""

from __future__ import annotations

import json
import math
import os

import pytest

from hdhil.analysis.benchmarks import (
    LOCKSTEP_SCENARIOS,
    REALTIME_GOALS,
    format_bench,
    run_benchmarks,
)
from hdhil.cli import main
from hdhil.firmware.isr import STAGES


def _positive(x: float) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.fixture(scope="module")
def report() -> dict:
    return run_benchmarks(duration_s=0.1, repeat=1, quick=True)


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_machine_and_settings(report: dict) -> None:
    m = report["machine"]
    assert m["cpu"] and m["python"].count(".") == 2
    assert m["cores"] >= 1 and m["cores_usable"] >= 1
    assert report["mode"] == "quick"
    assert report["settings"]["repeat"] == 1
    assert _positive(report["wall_s"])


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
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
        if os.path.exists("/proc/stat"):  # the hypervisor's steal time over the runs
            assert 0 <= r["steal_share"] <= 1


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
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


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_filter_and_memory(report: dict) -> None:
    assert [r["mode"] for r in report["filter"]] == ["recommended", "paper"]
    for r in report["filter"]:
        assert r["rows"] == report["settings"]["filter_rows"]
        assert _positive(r["median"])
    mem = report["memory"]
    for key in ("peak_rss_MB", "rss_before_MB", "rss_after_MB", "simulated_s", "trace_MB"):
        assert _positive(mem[key]), key
    assert mem["peak_rss_MB"] >= mem["rss_after_MB"] * 0.99
    assert math.isfinite(mem["rss_growth_MB"])
    # a quick run is too short for a growth rate: not measured, never extrapolated
    for key in ("rss_growth_MB_per_sim_minute", "rss_slope_second_half_MB_per_sim_minute",
                "rss_growth_MB_per_sim_hour_extrapolated"):  # fmt: skip
        assert mem[key] is None, key
    assert mem["rss_growth_rate_note"].startswith("not measured (run shorter than")
    assert report["speed"]["whole"]["rss_growth_MB_per_sim_minute"] is None
    assert mem["simulated_s"] == pytest.approx(report["settings"]["memory_duration_s"])


def _ordered(p: dict) -> bool:
    return (
        p["min"] <= p["p50"] <= p["p99"] <= p["p99.9"] <= p["max"]
        and p["min"] <= p["mean"] <= p["max"]
    )


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_realtime_section(report: dict) -> None:
    rt = report["realtime"]
    st = report["settings"]
    assert rt["scenario"] == "free-motion" and rt["logging"] is False
    assert rt["duration_s"] == st["realtime_s"] > 0
    assert rt["cycles"] == round(st["realtime_s"] / rt["sample_period_s"])
    assert rt["interrupts"] == rt["cycles"]
    assert 0 <= rt["deadline_misses"] <= rt["cycles"]
    assert rt["misses_per_100k"] == pytest.approx(1e5 * rt["deadline_misses"] / rt["cycles"])
    for key in ("jitter_us", "latency_us", "isr_us", "cycle_work_us", "sleep_overshoot_us"):
        assert _ordered(rt[key]), (key, rt[key])
    assert [k for k, _ in STAGES] == list(rt["stages_us"])
    stage_sum = sum(s["mean"] for s in rt["stages_us"].values())
    assert stage_sum == pytest.approx(rt["isr_us"]["mean"], rel=1e-9, abs=1e-6)
    for s in rt["stages_us"].values():
        assert _ordered(s) and s["p50"] >= 0
    # the verdicts follow the figures
    g = rt["goals"]
    assert g["p99_us"]["met"] == (rt["jitter_us"]["p99"] <= REALTIME_GOALS["p99_us"])
    assert g["p99.9_us"]["met"] == (rt["jitter_us"]["p99.9"] <= REALTIME_GOALS["p99.9_us"])
    assert g["misses_per_100k"]["met"] == (
        rt["misses_per_100k"] <= REALTIME_GOALS["misses_per_100k"]
    )
    floor = rt["floor"]
    assert floor["cycles"] == round(st["floor_s"] / rt["sample_period_s"])
    assert floor["spin_us"] == rt["pacing"]["spin_us"]
    assert floor["work_us"] == pytest.approx(rt["cycle_work_us"]["p50"], abs=1e-6)
    assert _ordered(floor["jitter_us"]) and 0 <= floor["deadline_misses"] <= floor["cycles"]


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_text_report_and_json_roundtrip(report: dict) -> None:
    text = format_bench(report)
    assert report["machine"]["cpu"] in text
    for heading in ("Lockstep real-time factor", "Firmware compute per call",
                    "Offline `hdhil filter`", "Memory", "Real-time mode"):  # fmt: skip
        assert heading in text
    assert "| free-motion" in text and "| lqg-tracking" in text
    assert "| SYNC jitter (late)" in text and "machine floor" in text
    assert "| steal |" in text
    assert "deadline misses:" in text and "per 100 000" in text
    for _, label in STAGES:
        assert label in text
    assert json.loads(json.dumps(report)) == report


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_realtime_section_can_be_left_out(report: dict, monkeypatch) -> None:
    import hdhil.analysis.benchmarks as bench

    def fail(*args: object, **kwargs: object) -> None:
        raise AssertionError("a section ran")

    for name in ("bench_lockstep_all", "bench_stages", "bench_filter", "bench_realtime"):
        monkeypatch.setattr(bench, name, fail if name == "bench_realtime" else lambda s: [])
    monkeypatch.setattr(bench, "bench_memory", lambda s: {})
    monkeypatch.setattr(bench, "bench_joints_section", lambda s: {})
    import hdhil.analysis.speed as speed

    whole = {"median": {"peak_rss_MB": 1.0}, "duration_s": 1.0, "long_duration_s": 3.0,
             "real_time_factor": 1.0, "evaluation_share": 0.1,
             "rss_growth_MB_per_sim_minute": 0.0}  # fmt: skip
    monkeypatch.setattr(
        speed, "bench_speed",
        lambda *a: {"whole": whole, "reference": {"us_per_cycle": 1.0, "cpu_us_per_cycle": 1.0,
                                                  "loop_cpu_us_per_cycle": 1.0}},
    )  # fmt: skip
    assert run_benchmarks(quick=True, realtime_s=0)["realtime"] is None
    assert "Real-time mode" not in format_bench({**report, "realtime": None})


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--repeat", "0"], "--repeat"),
        (["--realtime-s", "-1"], "--realtime-s"),
        (["--realtime-s", "nan"], "--realtime-s"),
        (["--startup-runs", "0"], "--startup-runs"),
    ],
)
def test_cli_rejects_bad_arguments(
    argv: list[str], fragment: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--quick", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error:") and fragment in err


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_campaign_section(report: dict) -> None:
    c = report["campaign"]
    assert c["variants"] == 4 and c["workers"] == (os.cpu_count() or 1)
    for key in ("reference_s", "run_s_per_variant", "wall_s_1", "wall_s_n", "report_s"):
        assert _positive(c[key]), key
    # the figures follow from the measured wall times
    assert c["variants_per_min_1"] == pytest.approx(c["variants"] / c["wall_s_1"] * 60)
    assert c["variants_per_min_n"] == pytest.approx(c["variants"] / c["wall_s_n"] * 60)
    assert c["speedup"] == pytest.approx(c["wall_s_1"] / c["wall_s_n"])
    assert c["speedup_goal"] == pytest.approx(0.85 * c["workers"])
    assert c["overhead_share"] == pytest.approx(
        c["overhead_s_per_variant"] / c["run_s_per_variant"]
    )
    # the machinery's time is what the campaign took beyond its variants' own runs
    assert c["run_s_per_variant"] * c["variants"] < c["wall_s_1"]
    text = format_bench(report)
    assert "Campaign (4 variants of 0.5 s free-motion" in text and "speed-up" in text


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_startup_section(report: dict) -> None:
    """Whole-process start-up figures with their ratio to ``import can`` of the same
    rounds; the goals are judged, not asserted (no timing thresholds in tests)."""
    st = report["startup"]
    assert st["runs"] == report["settings"]["startup_runs"] >= 1
    rows = {r["figure"]: r for r in st["rows"]}
    assert list(rows) == ["import_can", "can_logger_help", "hdhil_help", "dump_help",
                          "run_first_cycle", "run_whole"]  # fmt: skip
    ref = rows["import_can"]["median"]
    for key, r in rows.items():
        assert _positive(r["median"]) and r["runs"] == st["runs"], key
        assert r["min"] <= r["median"] <= r["max"]
        assert r["to_import_can"] == pytest.approx(r["median"] / ref)
    assert rows["import_can"]["to_import_can"] == 1.0
    logger = rows["can_logger_help"]["median"]
    for key in ("hdhil_help", "dump_help"):
        assert rows[key]["to_can_logger_help"] == pytest.approx(rows[key]["median"] / logger)
        assert rows[key]["goal_met"] == (rows[key]["median"] <= st["help_goal_factor"] * logger)
    # the first cycle ends before the process does
    assert rows["run_first_cycle"]["median"] < rows["run_whole"]["median"]
    text = format_bench(report)
    assert "Start-up" in text and "hdhil dump --help" in text


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_speed_section(report: dict) -> None:
    """The main job by stage, the reference, the cost model and the goals' verdicts,
    which follow the figures (judged, not asserted)."""
    sp, goals = report["speed"], report["goals"]
    med = sp["whole"]["median"]
    assert 0 < med["start_up_s"] < med["whole_s"] and med["loop_s"] > 0
    assert med["evaluation_s"] > 0 and med["finishing_s"] >= 0
    parts = med["start_up_s"] + med["loop_s"] + med["evaluation_s"] + med["finishing_s"]
    assert parts == pytest.approx(med["whole_s"], rel=0.05)
    assert sp["whole"]["real_time_factor"] == pytest.approx(
        sp["whole"]["duration_s"] / med["whole_s"]
    )
    assert 50 < med["peak_rss_MB"] < 1000
    assert sp["reference"]["frames_per_cycle"] == len(sp["reference"]["frames"]) >= 7
    assert [r["joints"] for r in sp["joint_scaling"]] == [1, 4, 7, 16]
    cm = sp["cost_model"]
    assert cm["per_frame_us"] > 0 and math.isfinite(cm["per_joint_us"])
    for g in goals:
        if g["met"] is not None:
            op, goal = g["goal"].split()[:2]
            assert g["met"] == (
                g["value"] >= float(goal) if op == ">=" else g["value"] <= float(goal)
            )
    text = format_bench(report)
    assert "Speed goals" in text and "Whole command by stage" in text and "Cost model" in text
    assert "N joints per 1 ms cycle" in text


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.realtime
def test_joints_section(report: dict) -> None:
    """The loop's cost for 1, 2, 4, 7 joints, its growth verdict, the rigs' whole
    command against their goals (judged, not asserted)."""
    j = report["joints"]
    independent = [r for r in j["loop"] if r["plant"] == "independent"]
    assert [r["joints"] for r in independent] == [1, 2, 4, 7]
    for r in j["loop"]:
        assert _positive(r["cpu_us"]) and _positive(r["wall_us"])
        assert r["cpu_us_per_joint"] == pytest.approx(r["cpu_us"] / r["joints"])
    lin = j["linearity"]
    assert lin["met"] == (lin["worst_ratio"] <= lin["tolerance"])
    for r in j["whole"]:
        assert r["met"] == (r["real_time_factor"] >= r["goal"])
    assert "Loop cost by joint count" in format_bench(report)


def test_realtime_s_zero_leaves_the_real_time_section_out(monkeypatch) -> None:
    """`--realtime-s 0` is accepted, as its help says, and passed on as 0 (no section)."""
    from hdhil.commands import bench as command

    seen: dict[str, object] = {}

    def fake_run_benchmarks(*args, **kwargs):
        seen.update(kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "run_benchmarks", fake_run_benchmarks)
    code = main(["bench", "--quick", "--realtime-s", "0", "--quiet"])
    assert code == 130 and seen.get("realtime_s") == 0.0
