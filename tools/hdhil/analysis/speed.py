"""The speed goals of ``hdhil bench``: the main job as a whole, the loop, and a cost model.

Three measurements, each against a reference taken in the same run, so that a shared,
noisy machine moves figure and reference alike:

- :func:`bench_whole_command`: ``hdhil run --scenario free-motion --duration 10 --seed 5
  --trace a.blf`` as a whole process, the user's main job, split into stages by time
  stamps the child takes at the end of its first and last cycle and around the
  evaluation (:data:`STAGES_CHILD`): start-up, loop, evaluation, finishing. Peak RSS and
  CPU come from the child's own resource usage (``os.wait4``); a run three times as long
  shows whether memory grows with the run's length.
- :func:`bench_virtual_reference`: python-can's ``virtual`` bus carrying one cycle's
  frames of the same run (same identifiers, sizes, channels and receivers) with no node
  behind them: the least python-can needs to move the loop's frames in one process.
- :func:`bench_cost_model`: CPU time per cycle as ``fixed + joints * per_joint + frames *
  per_frame``: ``per_frame`` is the slope of CPU per cycle over padding frames added to
  the control bus (least squares), ``fixed`` the cost of a loop whose only node sends the
  SYNC (minus that frame), ``per_joint`` the rest of a one-joint run (plant, interrupt,
  both nodes' handling of the joint's frames). :func:`predict_cycle_us` applies it.

:func:`speed_goals` turns the figures into the verdicts ``hdhil bench`` prints
(:data:`GOALS`).
"""

from __future__ import annotations

import json
import math
import os
import signal
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from hdhil.core.errors import UserError
from hdhil.rig.request import resolve
from hdhil.rig.runner import run_lockstep

#: The main job, as the README's first command runs it (the trace path is added).
WHOLE_COMMAND = ("run", "--scenario", "free-motion", "--seed", "5")

#: Goals: whole command and loop as real-time factors, the evaluation's share of the
#: whole command, the first cycle after process start (s), peak memory (MB) of a 10 s
#: run, and memory growth with the run's length (MB per simulated minute).
GOALS = {
    "whole_rtf": 10.0,
    "loop_rtf": 25.0,
    "evaluation_share": 0.15,
    "first_cycle_s": 0.3,
    "peak_rss_MB": 150.0,
    "rss_growth_MB_per_sim_minute": 2.0,
}

#: The shortest whole-command run whose memory growth is measured and judged (simulated
#: s): from shorter runs, a few hundred kB of allocator noise would read as a slope.
MIN_GROWTH_RUN_S = 10.0


def _growth_not_measured() -> str:
    return f"not measured (run shorter than {MIN_GROWTH_RUN_S:g} s)"


#: CI's coarse speed guard (tests/test_speed.py): the lockstep loop's CPU µs per cycle
#: (free-motion, BLF trace on; :func:`loop_cpu_us`) over the reference's
#: (:func:`bench_virtual_reference`) must stay below this.  CPU time, not wall time: a
#: shared machine's other processes then slow neither side.
GUARD_RATIO = 0.75

#: Run in a fresh interpreter by :func:`bench_whole_command`: ``hdhil run`` (the CLI's
#: own ``main``) with the node loop's ``cycle``, the run's final evaluation (in process,
#: or the wait for the one beside the trace writer) and the streaming evaluation's
#: in-process chunks wrapped to take wall-clock stamps, printed on stderr at exit.
#: Nothing else is changed.
STAGES_CHILD = """
import atexit, json, sys, time
from hdhil.rig import loop, runner
stamps = {}
_cycle = loop.NodeLoop.cycle
def cycle(self):
    _cycle(self)
    now = time.time()
    stamps.setdefault("first_cycle", now)
    stamps["last_cycle"] = now
loop.NodeLoop.cycle = cycle
from hdhil.rig import evaluate as ev
final = []
_evaluate = runner.evaluate_recording
def evaluate(*args, **kwargs):
    t0 = time.perf_counter()
    final.append(1)
    try:
        return _evaluate(*args, **kwargs)
    finally:
        final.pop()
        stamps["evaluation_s"] = stamps.get("evaluation_s", 0.0) + time.perf_counter() - t0
runner.evaluate_recording = evaluate
_collect = runner.collect_evaluation
def collect(*args, **kwargs):  # the wait for the evaluation run beside the trace writer
    t0 = time.perf_counter()
    try:
        return _collect(*args, **kwargs)
    finally:
        stamps["evaluation_s"] = stamps.get("evaluation_s", 0.0) + time.perf_counter() - t0
runner.collect_evaluation = collect
_feed = ev.StreamingEvaluation.feed
def feed(self, cols):
    t0 = time.perf_counter()
    try:
        return _feed(self, cols)
    finally:
        if not final:  # scored in chunks during the loop
            key = "loop_evaluation_s"
            stamps[key] = stamps.get(key, 0.0) + time.perf_counter() - t0
ev.StreamingEvaluation.feed = feed
def report():
    try:  # the process's own high-water mark (ru_maxrss survives exec: the forking parent's)
        with open("/proc/self/status", encoding="ascii") as fh:
            stamps["peak_rss_kB"] = next(int(l.split()[1]) for l in fh if l.startswith("VmHWM:"))
    except (OSError, StopIteration, ValueError):
        pass
    print("hdhil-stamps " + json.dumps(stamps), file=sys.stderr, flush=True)
atexit.register(report)
from hdhil.cli import main
sys.exit(main(sys.argv[1:]))
"""


#: Exit codes of a child ended by a stopping signal: hdhil's 130, or killed by one.
_INTERRUPTED = frozenset(
    (
        130,
        -signal.SIGINT,
        -signal.SIGTERM,
        *((-signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ()),
    )
)


def timed_process(argv: Sequence[str]) -> dict[str, Any]:
    """One child process: wall time from spawn to exit, its CPU time (``os.wait4``), its
    peak RSS (the high-water mark it reports, :data:`STAGES_CHILD`) and its stamps."""
    import subprocess

    with tempfile.TemporaryFile(mode="w+") as err:
        spawned = time.time()
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err)
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        except BaseException:  # Ctrl-C while waiting: the child ends with the bench
            proc.kill()
            proc.wait()
            raise
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        stderr = err.read()
    if proc.returncode in _INTERRUPTED:
        # Ctrl-C reaches the whole process group: the child may end of it before this
        # process's own KeyboardInterrupt is raised; the bench is interrupted, not failed
        raise KeyboardInterrupt
    if proc.returncode != 0:
        raise UserError(f"bench: {' '.join(argv[2:5])} failed: {stderr.strip()[-300:]}")
    stamps: dict[str, float] = {}
    for line in stderr.splitlines():
        if line.startswith("hdhil-stamps "):
            stamps = json.loads(line.split(" ", 1)[1])
    return {
        "wall_s": wall,
        "spawned": spawned,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_MB": stamps.pop("peak_rss_kB", math.nan) / 1024,
        "stamps": stamps,
    }


def _stages(p: dict[str, Any]) -> dict[str, float]:
    """Start-up (spawn to the end of the first cycle), loop, evaluation, finishing (trace
    close, result, printing, exit) of one child process, in seconds.  The evaluation's
    chunks scored during the loop count as evaluation, not loop."""
    st = p["stamps"]
    if "first_cycle" not in st:
        raise UserError("bench: hdhil run reported no cycle")
    start_up = st["first_cycle"] - p["spawned"]
    # the evaluation scores the run in chunks during the loop, and the rest at its end
    in_loop = st.get("loop_evaluation_s", 0.0)
    loop = st["last_cycle"] - st["first_cycle"] - in_loop
    evaluation = st.get("evaluation_s", 0.0) + in_loop
    return {
        "start_up_s": start_up,
        "loop_s": loop,
        "evaluation_s": evaluation,
        "finishing_s": max(0.0, p["wall_s"] - start_up - loop - evaluation),
        "whole_s": p["wall_s"],
        "cpu_s": p["cpu_s"],
        "peak_rss_MB": p["peak_rss_MB"],
    }


def bench_whole_command(duration_s: float, runs: int) -> dict[str, Any]:
    """The main job as a whole process, ``runs`` times, and once per round a run three
    times as long (memory growth); medians per stage."""
    py = sys.executable
    per_run: list[dict[str, float]] = []
    long_rss: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        trace = str(Path(tmp) / "a.blf")

        def argv(d: float) -> list[str]:
            return [py, "-c", STAGES_CHILD, *WHOLE_COMMAND, "--duration", f"{d:g}",
                    "--trace", trace]  # fmt: skip

        for _ in range(runs):
            per_run.append(_stages(timed_process(argv(duration_s))))
        for _ in range(max(1, runs // 2)):
            long_rss.append(timed_process(argv(3 * duration_s))["peak_rss_MB"])
    med = {k: statistics.median(r[k] for r in per_run) for k in per_run[0]}
    short_rss = med["peak_rss_MB"]
    growth = (
        (statistics.median(long_rss) - short_rss) / (2 * duration_s / 60.0)
        if duration_s >= MIN_GROWTH_RUN_S
        else None  # not measured (MIN_GROWTH_RUN_S)
    )
    return {
        "command": ["hdhil", *WHOLE_COMMAND, "--duration", f"{duration_s:g}", "--trace", "a.blf"],
        "duration_s": duration_s,
        "runs": runs,
        "median": med,
        "min_whole_s": min(r["whole_s"] for r in per_run),
        "max_whole_s": max(r["whole_s"] for r in per_run),
        "real_time_factor": duration_s / med["whole_s"],
        "loop_real_time_factor": duration_s / med["loop_s"] if med["loop_s"] > 0 else None,
        "evaluation_share": med["evaluation_s"] / med["whole_s"],
        "long_duration_s": 3 * duration_s,
        "long_peak_rss_MB": statistics.median(long_rss),
        "rss_growth_MB_per_sim_minute": growth,
    }


# ------------------------------------------------------------------ the reference
@dataclass(frozen=True)
class CycleFrame:
    """One frame of a cycle: its bus (0 control, 1 truth), identifier, size, data."""

    channel: int
    arbitration_id: int
    is_extended_id: bool
    data: bytes


class _CycleRecorder(can.Listener):
    """Keeps the frames of one cycle of a run: those between two SYNCs mid-run."""

    def __init__(self, cycle: int) -> None:
        self.cycle = cycle
        self.syncs = 0
        self.frames: list[CycleFrame] = []

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == 0x080 and not msg.is_extended_id:
            self.syncs += 1
        if self.syncs == self.cycle:
            self.frames.append(CycleFrame(int(msg.channel or 0), msg.arbitration_id,
                                          msg.is_extended_id, bytes(msg.data)))  # fmt: skip


def cycle_frames(scenario: str = "free-motion", cycle: int = 200) -> list[CycleFrame]:
    """The frames of cycle ``cycle`` of a lockstep run of ``scenario`` (SYNC first)."""
    recorder = _CycleRecorder(cycle)
    run_lockstep(resolve(scenario, duration_s=(cycle + 10) * 1e-3), evaluate=False,
                 extra_listeners=[recorder])  # fmt: skip
    if not recorder.frames:
        raise UserError(f"bench: no frames in cycle {cycle} of {scenario}")
    return recorder.frames


def bench_virtual_reference(
    frames: Sequence[CycleFrame], cycles: int, repeat: int
) -> dict[str, Any]:
    """python-can's ``virtual`` bus carrying ``frames`` every cycle for ``cycles`` cycles:
    on the control channel two node handles and a listen-only tap, on the truth channel a
    sender and the tap, as in a run; each frame is sent once and received by every other
    handle with ``recv(0)``.  Returns wall and CPU µs per cycle (medians of ``repeat``)."""
    channel_names = {0: "hdhil-ref-control", 1: "hdhil-ref-truth"}
    per_cycle: list[float] = []
    cpu_per_cycle: list[float] = []
    for _ in range(repeat):
        buses = {
            0: [can.Bus(interface="virtual", channel=channel_names[0]) for _ in range(3)],
            1: [can.Bus(interface="virtual", channel=channel_names[1]) for _ in range(2)],
        }
        try:
            msgs = [(f.channel, can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                            is_extended_id=f.is_extended_id))
                    for f in frames]  # fmt: skip
            t0, c0 = time.perf_counter(), time.thread_time()
            for _ in range(cycles):
                for ch, msg in msgs:
                    handles = buses[ch]
                    handles[0].send(msg)
                    for rx in handles[1:]:
                        while rx.recv(0) is not None:
                            pass
            per_cycle.append((time.perf_counter() - t0) / cycles * 1e6)
            cpu_per_cycle.append((time.thread_time() - c0) / cycles * 1e6)
        finally:
            for handles in buses.values():
                for b in handles:
                    b.shutdown()
    return {"frames_per_cycle": len(frames), "us_per_cycle": statistics.median(per_cycle),
            "cpu_us_per_cycle": statistics.median(cpu_per_cycle), "cycles": cycles,
            "runs": repeat}  # fmt: skip


# ------------------------------------------------------------------ the cost model
#: Identifier of the padding frames (not in the DBC: every node counts and ignores them).
PADDING_ID = 0x6F0
#: Padding frames per cycle of the cost model's runs.
PADDING_STEPS = (0, 8, 16, 32)
#: Shortest run of the cost model (simulated s).
MIN_COST_MODEL_S = 1.0
#: Bit rate of the cost model's runs: room for 32 padding frames within the 1 ms cycle.
COST_MODEL_BITRATE = 8_000_000


def _padded(factory: Callable[..., Any], k: int) -> Callable[..., Any]:
    """A drive factory whose drive also sends ``k`` 8-byte padding frames every cycle."""
    pad = [can.Message(arbitration_id=PADDING_ID, data=bytes(8), is_extended_id=False)
           for _ in range(k)]  # fmt: skip

    def make(site: Any) -> Any:
        drive = factory(site)
        tick = drive.tick
        send = drive.bus.send

        def padded_tick(now: float) -> None:
            tick(now)
            for msg in pad:
                send(msg)

        drive.tick = padded_tick
        return drive

    return make


def loop_cpu_us(request: Any, trace: Path, factory: Callable[..., Any] | None = None) -> float:
    """CPU µs per cycle of one lockstep run's loop alone (set-up and teardown left out):
    the CPU time of the loop's thread between the first and the last poll of the run's
    stop hook, which the loop polls once per cycle (a thread's time: a math library's
    idle worker threads spinning in the same process do not count)."""
    stamps: list[float] = []

    def at_cycle() -> bool:
        stamps.append(time.thread_time())
        return False

    r = run_lockstep(request, trace=trace, evaluate=False, stop_requested=at_cycle,
                     drive_factories=None if factory is None else [factory])  # fmt: skip
    if r.interrupted:  # the hook never asks to stop: Ctrl-C ended the run; end the bench
        raise KeyboardInterrupt
    if len(stamps) < 2:
        raise UserError("bench: the cost model's run has no cycles")
    return (stamps[-1] - stamps[0]) / (len(stamps) - 1) * 1e6


def bench_cost_model(
    duration_s: float, repeat: int, scenario: str = "free-motion"
) -> dict[str, Any]:
    """CPU µs per cycle as fixed + per joint + per frame (module docstring); trace writing
    on, as in ``hdhil run`` (the writer's own process is not counted: it runs on the
    other core).  One warm-up run, then ``repeat`` rounds over :data:`PADDING_STEPS` in
    turns; the fit is over the per-step medians."""
    from hdhil.rig.factories import scenario_drive

    # runs of at least a second: shorter ones are mostly the start-up walk
    duration_s = max(duration_s, MIN_COST_MODEL_S)
    request = resolve(scenario, duration_s=duration_s, bitrate=COST_MODEL_BITRATE)
    samples: dict[int, list[float]] = {k: [] for k in PADDING_STEPS}
    sync_only: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        trace = Path(tmp) / "cost.blf"
        r = run_lockstep(request, trace=trace, evaluate=False)  # warm-up, and the frame count
        frames_per_cycle = r.frames_total / r.cycles
        for _ in range(repeat):
            for k in PADDING_STEPS:
                factory = _padded(scenario_drive(request.scenario), k)
                samples[k].append(loop_cpu_us(request, trace, factory))
            sync_only.append(_sync_only_us(duration_s, trace))
    ks = np.array(PADDING_STEPS, dtype=float)
    us = np.array([statistics.median(samples[k]) for k in PADDING_STEPS])
    per_frame, intercept = (float(v) for v in np.polyfit(ks, us, 1))
    sync_med = statistics.median(sync_only)
    fixed = max(0.0, sync_med - per_frame)
    per_joint = intercept - fixed - frames_per_cycle * per_frame
    residual = us - (intercept + per_frame * ks)
    # Linearity check: the largest step predicted from a fit over the others.
    slope_h, icpt_h = np.polyfit(ks[:-1], us[:-1], 1)
    return {
        "scenario": scenario,
        "duration_s": duration_s,
        "runs": repeat,
        "points": [
            {"padding": k, "cpu_us_per_cycle": float(u)}
            for k, u in zip(PADDING_STEPS, us, strict=True)
        ],
        "frames_per_cycle": frames_per_cycle,
        "one_joint_cpu_us_per_cycle": intercept,
        "sync_only_cpu_us_per_cycle": sync_med,
        "fixed_us": fixed,
        "per_joint_us": per_joint,
        "per_frame_us": per_frame,
        "fit_rms_us": float(np.sqrt(np.mean(residual**2))),
        "held_out": {
            "padding": PADDING_STEPS[-1],
            "measured_us": float(us[-1]),
            "predicted_us": float(icpt_h + slope_h * ks[-1]),
        },
    }


def _sync_only_us(duration_s: float, trace: Path) -> float:
    """CPU µs per cycle of the node loop with one node sending SYNC, the tap and the
    trace writer: the loop's fixed cost plus one frame."""
    from hdhil.can.simbus import SimBus, SimClock
    from hdhil.can.traces.tap import BusTap
    from hdhil.can.traces.writer import WriterProcess
    from hdhil.rig.loop import NodeLoop

    clock = SimClock()
    name = f"hdhil-bench-sync-{os.getpid()}"
    sender = SimBus(channel=name, clock=clock)
    tap_bus = SimBus(channel=name, clock=clock)
    truth_name = name + "-truth"
    truth_bus = SimBus(channel=truth_name, clock=clock, bitrate=0)
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)

    class SyncNode:
        bus = sender

        def boot(self, now: float) -> None:
            pass

        def tick(self, now: float) -> None:
            pass

        def poll(self) -> int:
            return sender.dispatch(lambda msg: None)

        def on_message(self, msg: can.Message) -> None:
            pass

        def send_sync(self) -> bool:
            sender.send(sync)
            return True

    node = SyncNode()
    writer = WriterProcess(trace)
    try:
        tap = BusTap({0: tap_bus, 1: truth_bus}, [writer])
        loop = NodeLoop([node], producer=node, listeners=[tap], listen_every=10,  # type: ignore[list-item]
                        sim_clock=clock, node_time=None, pump=sender)  # fmt: skip
        cycles = max(1, round(duration_s * 1e3))
        t0 = time.thread_time()
        for _ in range(cycles):
            loop.cycle()
        tap.poll()
        return (time.thread_time() - t0) / cycles * 1e6
    finally:
        writer.stop()
        for b in (sender, tap_bus, truth_bus):
            b.shutdown()


def predict_cycle_us(model: dict[str, Any], joints: int, frames: float) -> float:
    """CPU µs per cycle the cost model predicts for ``joints`` joints and ``frames``
    frames per cycle in one process."""
    return model["fixed_us"] + joints * model["per_joint_us"] + frames * model["per_frame_us"]


# --------------------------------------------------------------------- the goals
def speed_goals(whole: dict[str, Any], loop: dict[str, Any] | None, reference: dict[str, Any],
                first_cycle_s: float) -> list[dict[str, Any]]:  # fmt: skip
    """The goals' rows (figure, value, goal, verdict) from the whole command's figures,
    the lockstep table's free-motion row with BLF logging (``loop``; None: the section
    did not run), the reference (:func:`bench_speed`'s, with the loop's CPU per cycle
    beside it) and the start-up section's first cycle."""
    med = whole["median"]
    rows: list[tuple[str, float | None, str, float, str]] = [
        (f"whole command (hdhil run, {whole['duration_s']:g} s, BLF, evaluation): "
         "real-time factor", whole["real_time_factor"], ">=", GOALS["whole_rtf"], "x"),
    ]  # fmt: skip
    if loop is not None:
        rows.append(("loop (free-motion, BLF on, in-process runs): real-time factor",
                     loop["median"], ">=", GOALS["loop_rtf"], "x"))  # fmt: skip
    rows += [
        ("evaluation share of the whole command", 100 * whole["evaluation_share"], "<=",
         100 * GOALS["evaluation_share"], "%"),
        ("first cycle after process start", first_cycle_s, "<=", GOALS["first_cycle_s"], "s"),
        ("peak memory of the whole command", med["peak_rss_MB"], "<=", GOALS["peak_rss_MB"], "MB"),
        (f"memory growth from a {whole['duration_s']:g} s to a {whole['long_duration_s']:g} s run",
         whole["rss_growth_MB_per_sim_minute"], "<=", GOALS["rss_growth_MB_per_sim_minute"],
         "MB/sim min"),
    ]  # fmt: skip
    out: list[dict[str, Any]] = []
    for label, value, op, goal, unit in rows:
        text = f"{op} {goal:g} {unit}"
        met: bool | None
        if value is None or (unit == "MB/sim min" and whole["duration_s"] < MIN_GROWTH_RUN_S):
            value, met = None, None  # not measured (MIN_GROWTH_RUN_S)
        else:
            met = value >= goal if op == ">=" else value <= goal
        out.append({"figure": label, "value": value, "goal": text, "unit": unit,
                    "met": None if met is None else bool(met)})  # fmt: skip
    out.append({"figure": "loop's speed against python-can virtual carrying its frames (CPU)",
                "value": reference["cpu_us_per_cycle"] / reference["loop_cpu_us_per_cycle"],
                "goal": "", "unit": "x", "met": None})  # fmt: skip
    return out


# -------------------------------------------------------------------- the report
def bench_speed(whole_duration_s: float, whole_runs: int, model_duration_s: float,
                repeat: int, reference_cycles: int, scaling_steps: int = 200,
                joints: Sequence[int] = (1, 4, 7, 16)) -> dict[str, Any]:  # fmt: skip
    """The speed section: the whole command, the reference, the cost model, and N joints
    stepped one by one against one array step (:mod:`hdhil.analysis.joint_scaling`)."""
    from threadpoolctl import threadpool_limits

    from hdhil.analysis.joint_scaling import joint_scaling

    # One BLAS thread in this process: idle BLAS workers spin for a while after each call
    # and would take the core the measured child's trace writer runs on.
    with threadpool_limits(limits=1):
        whole = bench_whole_command(whole_duration_s, whole_runs)
        frames = cycle_frames()
        cost_model = bench_cost_model(model_duration_s, repeat)
        scaling = joint_scaling(joints, steps=scaling_steps, repeats=max(3, repeat))
    return {
        "joint_scaling": scaling,
        "whole": whole,
        "reference": {
            **bench_virtual_reference(frames, reference_cycles, repeat),
            "frames": [[f.channel, f.arbitration_id, len(f.data)] for f in frames],
            # the loop's CPU per cycle with no padding frame (the cost model's first point)
            "loop_cpu_us_per_cycle": cost_model["points"][0]["cpu_us_per_cycle"],
        },
        "cost_model": cost_model,
    }


#: Share of the 1 ms period a real-time loop may spend on its cycle's work (the rest is
#: the pacer's spin window and the machine's jitter, docs/design.md).
REALTIME_BUDGET_SHARE = 0.6


def joints_within(model: dict[str, Any], period_us: float = 1000.0) -> int:
    """Joints one process carries within :data:`REALTIME_BUDGET_SHARE` of the period,
    each with the frames of today's one-joint layout."""
    per = model["per_joint_us"] + model["frames_per_cycle"] * model["per_frame_us"]
    budget = REALTIME_BUDGET_SHARE * period_us - model["fixed_us"]
    return max(0, int(budget // per)) if per > 0 else 0


def format_speed_section(speed: dict[str, Any], goals: list[dict[str, Any]]) -> list[str]:
    """The speed goals, the whole command by stage, the reference and the cost model."""
    from hdhil.analysis.tables import markdown_table

    w, ref, cm = speed["whole"], speed["reference"], speed["cost_model"]
    med = w["median"]
    lines = ["Speed goals (verdicts against the goals; references measured in this run)"]
    rows = []
    for g in goals:
        if g["value"] is None:
            value = _growth_not_measured()
        elif g["unit"] == "x":
            value = f"{g['value']:.1f}x"
        else:
            value = f"{g['value']:.2f} {g['unit']}"
        verdict = "" if g["met"] is None else ("met" if g["met"] else "NOT met")
        rows.append([g["figure"], value, g["goal"], verdict])
    lines += markdown_table(["figure", "value", "goal", "verdict"], rows,
                            [False, True, False, False])  # fmt: skip
    lines += [
        "",
        f"Whole command by stage (`{' '.join(w['command'])}`, median of {w['runs']} "
        f"processes; whole {w['min_whole_s']:.2f}-{w['max_whole_s']:.2f} s)",
    ]
    whole = med["whole_s"]
    rows = [
        [label, f"{med[key]:.3f}", f"{100 * med[key] / whole:.0f}%"]
        for label, key in (
            ("start-up (spawn to the end of the first cycle)", "start_up_s"),
            ("loop (first to last cycle, recording for the evaluation)", "loop_s"),
            ("evaluation (every candidate against truth)", "evaluation_s"),
            ("finishing (trace closed, result, printing, exit)", "finishing_s"),
            ("whole process", "whole_s"),
        )
    ]
    lines += markdown_table(["stage", "s", "share"], rows, [False, True, True])
    growth = w["rss_growth_MB_per_sim_minute"]
    lines.append(
        f"CPU {med['cpu_s']:.2f} s; peak RSS {med['peak_rss_MB']:.1f} MB, "
        f"{w['long_peak_rss_MB']:.1f} MB for a {w['long_duration_s']:g} s run"
        + (
            f" ({growth:+.1f} MB per simulated minute)"
            if growth is not None
            else f"; growth per simulated minute {_growth_not_measured()}"
        )
    )
    lines += [
        "",
        f"Reference: python-can `virtual` carrying one cycle's {ref['frames_per_cycle']} frames "
        f"(same identifiers and sizes, every receiver, no nodes): {ref['cpu_us_per_cycle']:.0f} "
        f"us of CPU per cycle ({ref['us_per_cycle']:.0f} us wall); the whole loop: "
        f"{ref['loop_cpu_us_per_cycle']:.0f} us of CPU per cycle",
        "",
        f"Cost model (CPU us per cycle, {cm['scenario']}, BLF on, "
        f"{COST_MODEL_BITRATE / 1e6:g} Mbit/s; slope over {', '.join(map(str, PADDING_STEPS))} "
        f"padding frames, fit residual {cm['fit_rms_us']:.1f} us rms)",
    ]
    rows = [
        ["fixed (node loop, tap, trace hand-off)", f"{cm['fixed_us']:.1f}"],
        ["per joint (plant, interrupt, both nodes' work on its frames)",
         f"{cm['per_joint_us']:.1f}"],
        ["per frame (bus, receivers, tap, trace)", f"{cm['per_frame_us']:.2f}"],
        [f"one joint + {cm['held_out']['padding']} padding frames, from a fit without "
         "them: predicted / measured",
         f"{cm['held_out']['predicted_us']:.1f} / {cm['held_out']['measured_us']:.1f}"],
        [f"joints per process within {REALTIME_BUDGET_SHARE:.0%} of a 1 ms cycle",
         str(joints_within(cm))],
    ]  # fmt: skip
    lines += markdown_table(["term", "us"], rows, [False, True])
    if speed.get("joint_scaling"):
        from hdhil.analysis.joint_scaling import format_joint_scaling

        lines += [
            "",
            "N joints per 1 ms cycle: N scalar plant steps / filter steps against one numpy "
            "step over arrays of N (us per cycle, medians)",
            *format_joint_scaling(speed["joint_scaling"]),
        ]
    return lines
