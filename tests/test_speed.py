"""The speed section of ``hdhil bench`` (hdhil.analysis.speed) and the CI speed guard.

The figures themselves are judged by ``hdhil bench``, never asserted here, except for one
coarse guard: the loop against python-can's ``virtual`` bus carrying the same frames,
measured in turns in the same test, so a machine that is slow or busy slows both.
"""

from __future__ import annotations

import math
import statistics
import sys
from pathlib import Path

import pytest

from hdhil.analysis import speed
from hdhil.rig.factories import scenario_drive
from hdhil.rig.request import resolve
from hdhil.rig.runner import run_lockstep


def _whole(**median: float) -> dict:
    base = {"start_up_s": 0.2, "loop_s": 0.5, "evaluation_s": 0.1, "finishing_s": 0.05,
            "whole_s": 0.85, "cpu_s": 0.9, "peak_rss_MB": 90.0}  # fmt: skip
    base.update(median)
    return {"median": base, "duration_s": 10.0, "long_duration_s": 30.0,
            "real_time_factor": 10.0 / base["whole_s"],
            "evaluation_share": base["evaluation_s"] / base["whole_s"],
            "rss_growth_MB_per_sim_minute": 0.5}  # fmt: skip


def test_stages_split_the_process_by_its_stamps() -> None:
    p = {"spawned": 100.0, "wall_s": 2.0, "cpu_s": 1.5, "peak_rss_MB": 80.0,
         "stamps": {"first_cycle": 100.4, "last_cycle": 101.2, "evaluation_s": 0.3}}  # fmt: skip
    st = speed._stages(p)
    assert st["start_up_s"] == pytest.approx(0.4)
    assert st["loop_s"] == pytest.approx(0.8)
    assert st["evaluation_s"] == 0.3
    assert st["finishing_s"] == pytest.approx(2.0 - 0.4 - 0.8 - 0.3)
    # chunks scored during the loop count as evaluation
    inner = speed._stages({**p, "stamps": {**p["stamps"], "loop_evaluation_s": 0.1}})
    assert inner["loop_s"] == pytest.approx(0.7) and inner["evaluation_s"] == pytest.approx(0.4)
    assert inner["finishing_s"] == pytest.approx(st["finishing_s"])
    with pytest.raises(Exception, match="no cycle"):
        speed._stages({**p, "stamps": {}})


@pytest.mark.parametrize(
    "whole_s, eval_s, rtf_met, share_met", [(0.9, 0.1, True, True), (1.2, 0.3, False, False)]
)
def test_goal_verdicts_follow_the_figures(whole_s, eval_s, rtf_met, share_met) -> None:
    loop = {"median": 30.0, "us_per_cycle": 33.0}
    ref = {"cpu_us_per_cycle": 100.0, "loop_cpu_us_per_cycle": 50.0}
    rows = speed.speed_goals(_whole(whole_s=whole_s, evaluation_s=eval_s), loop, ref, 0.25)
    by = {r["figure"].split(" (")[0].split(":")[0]: r for r in rows}
    assert by["whole command"]["met"] is rtf_met
    assert by["evaluation share of the whole command"]["met"] is share_met
    assert by["first cycle after process start"]["met"] is True
    assert rows[-1]["value"] == pytest.approx(2.0) and rows[-1]["met"] is None
    growth = next(r for r in rows if r["unit"] == "MB/sim min")
    assert growth["met"] is True  # 10 s runs: judged
    short = speed.speed_goals({**_whole(), "duration_s": 1.0}, loop, ref, 0.25)
    assert next(r for r in short if r["unit"] == "MB/sim min")["met"] is None
    # without the lockstep table there is no loop goal
    assert len(speed.speed_goals(_whole(), None, ref, 0.25)) == len(rows) - 1


def test_cost_model_prediction_and_capacity() -> None:
    model = {"fixed_us": 10.0, "per_joint_us": 40.0, "per_frame_us": 3.0,
             "frames_per_cycle": 7.0}  # fmt: skip
    assert speed.predict_cycle_us(model, 3, 21) == pytest.approx(10 + 120 + 63)
    # 600 us budget - 10 fixed = 590; 61 us per joint -> 9 joints
    assert speed.joints_within(model) == 9
    assert speed.joints_within({**model, "per_joint_us": 1000.0}) == 0


@pytest.mark.slow
def test_cycle_frames_and_padding_are_what_the_bus_carries(tmp_path: Path) -> None:
    frames = speed.cycle_frames(cycle=50)
    assert frames[0].arbitration_id == 0x080 and frames[0].channel == 0
    truth = [f for f in frames if f.channel == 1]
    assert len(truth) == 3 and all(f.is_extended_id for f in truth)
    # the padding drive adds exactly its frames to every cycle, and the run still works
    request = resolve("free-motion", duration_s=0.2, bitrate=speed.COST_MODEL_BITRATE)
    plain = run_lockstep(request, evaluate=False)
    padded = run_lockstep(
        request, evaluate=False,
        drive_factories=[speed._padded(scenario_drive(request.scenario), 5)],
    )  # fmt: skip
    ticks = plain.cycles + plain.startup_cycles + plain.stop_cycles  # every loop cycle
    assert padded.frames_total - plain.frames_total == 5 * ticks
    assert padded.torque == plain.torque


@pytest.mark.slow
@pytest.mark.subprocess
def test_cost_model_terms_are_measured() -> None:
    cm = speed.bench_cost_model(0.1, 1)  # runs of MIN_COST_MODEL_S
    assert [p["padding"] for p in cm["points"]] == list(speed.PADDING_STEPS)
    for key in ("fixed_us", "per_frame_us", "per_joint_us", "one_joint_cpu_us_per_cycle"):
        assert math.isfinite(cm[key]), key
    assert cm["per_frame_us"] > 0 and cm["per_joint_us"] > 0
    assert cm["frames_per_cycle"] > 6 and cm["duration_s"] == speed.MIN_COST_MODEL_S


@pytest.mark.slow
@pytest.mark.subprocess
def test_speed_guard_loop_against_python_can_virtual(tmp_path: Path) -> None:
    """CI's coarse guard: the whole lockstep loop (free-motion, BLF trace on) must stay
    well under python-can's ``virtual`` bus merely carrying the same frames, in CPU time
    per cycle (other processes on a shared machine slow neither side); each measured
    five times in turns, medians compared.  ``hdhil bench`` reports the figures; this
    catches a large regression, not a small one."""
    request = resolve("free-motion", duration_s=1.0)
    frames = speed.cycle_frames(cycle=50)
    speed.loop_cpu_us(request, tmp_path / "warm.blf")
    loop, ref = [], []
    for i in range(5):
        loop.append(speed.loop_cpu_us(request, tmp_path / f"g{i}.blf"))
        ref.append(speed.bench_virtual_reference(frames, 1000, 1)["cpu_us_per_cycle"])
    ratio = statistics.median(loop) / statistics.median(ref)
    assert ratio < speed.GUARD_RATIO, (
        f"the loop takes {statistics.median(loop):.0f} us of CPU a cycle, "
        f"{ratio:.2f}x python-can virtual carrying its frames "
        f"({statistics.median(ref):.0f} us/cycle); guard {speed.GUARD_RATIO}x"
    )


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_timed_child_ended_by_ctrl_c_interrupts_the_bench() -> None:
    """Ctrl-C reaches the whole process group: a timed child that ended of it first
    interrupts the bench (KeyboardInterrupt, exit 130), it is no failed run (exit 2)."""
    from hdhil.analysis.speed import timed_process
    from hdhil.core.errors import UserError

    with pytest.raises(KeyboardInterrupt):
        timed_process([sys.executable, "-c", "raise SystemExit(130)"])
    with pytest.raises(KeyboardInterrupt):
        timed_process(
            [sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGTERM)"]
        )
    with pytest.raises(UserError, match="failed"):
        timed_process([sys.executable, "-c", "raise SystemExit(3)"])
