"""Memory growth rates come only from runs long enough to measure them.

``hdhil bench``'s memory section (:func:`hdhil.analysis.benchmarks.bench_memory`) and its
speed section's whole-command growth (:mod:`hdhil.analysis.speed`) report a rate per
simulated minute or hour only from a run of their documented minimum length; shorter
runs say "not measured (run shorter than N s)" in the text and give null in the JSON.
"""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

from hdhil.analysis import benchmarks, speed
from hdhil.analysis.benchmarks import (
    MEMORY_GROWTH_MIN_S,
    BenchSettings,
    bench_memory,
    format_memory_section,
)

RATES = (
    "rss_growth_MB_per_sim_minute",
    "rss_slope_second_half_MB_per_sim_minute",
    "rss_growth_MB_per_sim_hour_extrapolated",
)


def _memory(simulated_s: float, **rates: float | None) -> dict:
    mem = {"scenario": "misalignment", "logging": "blf", "simulated_s": simulated_s,
           "wall_s": 1.0, "real_time_factor": 3.0, "frames": 1000, "trace_MB": 0.1,
           "rss_before_MB": 50.0, "rss_after_MB": 50.25, "rss_growth_MB": 0.25,
           "peak_rss_MB": 60.0, "rss_samples": 3}  # fmt: skip
    mem.update(dict.fromkeys(RATES), rss_growth_rate_note=None)
    mem.update(rates)
    return mem


@pytest.mark.slow
def test_bench_memory_gives_rates_only_from_a_long_enough_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    s = dataclasses.replace(BenchSettings.quick(), memory_duration_s=0.3)
    short = bench_memory(s)
    assert short["simulated_s"] == pytest.approx(0.3)
    assert math.isfinite(short["rss_growth_MB"])  # measured: RSS after - before
    assert all(short[key] is None for key in RATES), short
    note = f"not measured (run shorter than {MEMORY_GROWTH_MIN_S:g} s)"
    assert short["rss_growth_rate_note"] == note
    json.dumps(short, allow_nan=False)  # null, not NaN
    text = "\n".join(format_memory_section({**short, "peak_rss_MB": 60.0}))
    assert text.count(note) == 3 and "MB/h" not in text
    # long enough (the minimum lowered for the test): the rates are measured
    monkeypatch.setattr(benchmarks, "MEMORY_GROWTH_MIN_S", 0.2)
    long = bench_memory(s)
    assert all(math.isfinite(long[key]) for key in RATES), long
    assert long["rss_growth_rate_note"] is None
    assert long["rss_growth_MB_per_sim_hour_extrapolated"] == pytest.approx(
        60.0 * long["rss_slope_second_half_MB_per_sim_minute"]
    )


def test_memory_section_prints_rates_or_why_not() -> None:
    note = f"not measured (run shorter than {MEMORY_GROWTH_MIN_S:g} s)"
    short = format_memory_section(_memory(3.0, rss_growth_rate_note=note))
    assert sum(note in line for line in short) == 3
    assert any("+0.25 MB (50.0 -> 50.2 MB)" in line for line in short)
    long = format_memory_section(_memory(120.0, rss_growth_MB_per_sim_minute=0.125,
                                         rss_slope_second_half_MB_per_sim_minute=0.01,
                                         rss_growth_MB_per_sim_hour_extrapolated=0.6))  # fmt: skip
    assert not any("not measured" in line for line in long)
    assert any("+0.12 MB" in line for line in long) and any("+0.6 MB" in line for line in long)


def _speed(duration_s: float, growth: float | None) -> dict:
    whole = {"command": ["hdhil", "run"], "runs": 3, "duration_s": duration_s,
             "long_duration_s": 3 * duration_s, "min_whole_s": 0.8, "max_whole_s": 0.9,
             "real_time_factor": 11.0, "evaluation_share": 0.05, "long_peak_rss_MB": 91.0,
             "rss_growth_MB_per_sim_minute": growth,
             "median": {"start_up_s": 0.2, "loop_s": 0.5, "evaluation_s": 0.05,
                        "finishing_s": 0.05, "whole_s": 0.8, "cpu_s": 0.9,
                        "peak_rss_MB": 90.0}}  # fmt: skip
    ref = {"frames_per_cycle": 7, "cpu_us_per_cycle": 40.0, "us_per_cycle": 45.0,
           "loop_cpu_us_per_cycle": 80.0}  # fmt: skip
    cm = {"scenario": "free-motion", "fit_rms_us": 1.0, "fixed_us": 10.0, "per_joint_us": 40.0,
          "per_frame_us": 3.0, "frames_per_cycle": 7.0,
          "held_out": {"padding": 8, "predicted_us": 90.0, "measured_us": 91.0}}  # fmt: skip
    return {"whole": whole, "reference": ref, "cost_model": cm}


def test_whole_command_growth_is_not_measured_from_short_runs() -> None:
    short = _speed(1.0, None)
    goals = speed.speed_goals(short["whole"], None, short["reference"], 0.25)
    (row,) = [g for g in goals if g["unit"] == "MB/sim min"]
    assert row["value"] is None and row["met"] is None
    note = f"not measured (run shorter than {speed.MIN_GROWTH_RUN_S:g} s)"
    text = "\n".join(speed.format_speed_section(short, goals))
    assert text.count(note) == 2, text  # the goal row and the stage table's line
    long = _speed(10.0, 0.5)
    goals = speed.speed_goals(long["whole"], None, long["reference"], 0.25)
    (row,) = [g for g in goals if g["unit"] == "MB/sim min"]
    assert row["value"] == 0.5 and row["met"] is True
    text = "\n".join(speed.format_speed_section(long, goals))
    assert "not measured" not in text and "+0.5 MB per simulated minute" in text
