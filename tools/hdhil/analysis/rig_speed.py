"""The loop's cost with N joints and the shipped rigs' whole command: ``hdhil bench``'s
joints section (``hdhil bench --only joints`` runs it alone).

- :func:`bench_joint_loop`: the lockstep loop of a rig of N joints
  (:func:`hdhil.rig.rigrun.run_rig`) for N = 1, 2, 4, 7 (:data:`JOINT_COUNTS`): each joint
  free-motion's (its plant, ripple filter and frames), the plants independent (no
  ``[robot]``), laid out as ``arm7`` lays out its buses: two joints a classical 1 Mbit/s
  bus, each bus with its controller node (:func:`joint_rig_overrides`). No trace. CPU
  time of the loop's thread and wall time per cycle in operation, between the first and
  the last poll of the run's stop hook (once a cycle), the counts taking turns in each
  round, medians over the rounds. With the ``arm`` extra, the same for the shipped rigs
  whose plant is the arm's (``rehabexos``, ``arm7``: :data:`ARM_RIGS`).
- :func:`linearity`: whether the cost grows no faster than linearly with N: the CPU per
  joint at each N, ``cost(N) / N``, against one joint's ``cost(1)``; met when no ratio
  exceeds :data:`LINEAR_TOLERANCE` (a fixed part shared by the joints makes it fall; a
  cost growing faster than N makes it climb with N). The least-squares line over N gives
  the cost of each further joint and the fixed part.
- :func:`bench_rig_whole`: ``hdhil run --scenario NAME --duration 10 --trace a.blf`` of
  each rig of :data:`RIG_GOALS` as a whole process (:func:`hdhil.analysis.speed.
  timed_process`, stamped as the speed section's), median real-time factor (wall time)
  against its goal, and simulated seconds per CPU second of the process and its trace
  writer (what a machine with a core free for each would give at most).

:func:`format_joints_section` writes the section of the report.
"""

from __future__ import annotations

import importlib.util
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hdhil.analysis.tables import markdown_table
from hdhil.core.errors import UserError
from hdhil.rig.request import RunRequest, resolve

__all__ = [
    "ARM_RIGS",
    "JOINT_COUNTS",
    "LINEAR_TOLERANCE",
    "RIG_GOALS",
    "bench_joint_loop",
    "bench_joints",
    "bench_rig_whole",
    "format_joints_section",
    "joint_rig_overrides",
    "linearity",
]

#: The joint counts of the loop's cost: one joint, two on a bus, rehabexos's four and an
#: arm of seven.
JOINT_COUNTS: tuple[int, ...] = (1, 2, 4, 7)
#: Joints a bus of the measured rigs, as arm7 and rehabexos lay them out.
JOINTS_PER_BUS = 2
#: The scenario each measured joint is (plant, ripple filter, frames).
JOINT_SCENARIO = "free-motion"
#: The growth is linear when no joint count's CPU per joint exceeds one joint's by more
#: than this factor (room for a shared machine's noise; a quadratic term at 7 joints
#: would show as well over it).
LINEAR_TOLERANCE = 1.25
#: Shipped rigs whose plant is the arm's (MuJoCo, the ``arm`` extra), measured beside.
ARM_RIGS: tuple[str, ...] = ("rehabexos", "arm7")
#: Whole-command goals: real-time factor of a 10 s lockstep run (issue: several joints).
RIG_GOALS: dict[str, float] = {"rehabexos": 5.0, "arm7": 2.0}


def joint_rig_overrides(joints: int) -> dict[str, Any]:
    """The layout of the measured rig of ``joints`` joints: ``J1`` .. ``JN`` two a bus
    on classical 1 Mbit/s buses ``can0``, ``can1``, ..., node-IDs from 2 on each."""
    if joints < 1:
        raise ValueError(f"a rig has at least one joint, got {joints}")
    buses = -(-joints // JOINTS_PER_BUS)
    return {
        "buses": {f"can{b}": {"bitrate": 1_000_000} for b in range(buses)},
        "joints": {f"J{k + 1}": {"bus": f"can{k // JOINTS_PER_BUS}"} for k in range(joints)},
    }


def _request(label: str | int, duration_s: float) -> RunRequest:
    if isinstance(label, int):
        return resolve(JOINT_SCENARIO, overrides=[joint_rig_overrides(label)],
                       duration_s=duration_s)  # fmt: skip
    return resolve(label, duration_s=duration_s)


def loop_cost_us(request: RunRequest) -> tuple[float, float, int]:
    """CPU and wall µs per cycle in operation of one lockstep run of ``request``'s rig
    (no trace), and the cycles measured: the loop's thread time and the wall time
    between the first and the last poll of the run's stop hook, which the rig's loop
    polls once a cycle in operation (start-up and stop left out)."""
    from hdhil.rig.rigrun import run_rig

    cpu: list[float] = []
    wall: list[float] = []

    def at_cycle() -> bool:
        cpu.append(time.thread_time())
        wall.append(time.perf_counter())
        return False

    r = run_rig(request, stop_requested=at_cycle, evaluate=False)  # the loop alone
    if r.interrupted:  # the hook never asks to stop: Ctrl-C ended the run; end the bench
        raise KeyboardInterrupt
    if r.verdict is not None or len(cpu) < 2:
        raise UserError(f"bench: the {request.name} rig did not run: {r.verdict}")
    n = len(cpu) - 1
    return (cpu[-1] - cpu[0]) / n * 1e6, (wall[-1] - wall[0]) / n * 1e6, n


def arm_available() -> bool:
    """Whether the arm's plant can run (MuJoCo, the ``arm`` extra)."""
    return importlib.util.find_spec("mujoco") is not None


def bench_joint_loop(
    duration_s: float,
    repeat: int,
    ns: Sequence[int] = JOINT_COUNTS,
    arm_rigs: Sequence[str] = ARM_RIGS,
) -> list[dict[str, Any]]:
    """Rows ``{"label", "joints", "buses", "plant", "cpu_us", "wall_us", "cpu_us_per_joint",
    "wall_us_per_joint", "cpu_min_us", "cpu_max_us", "cycles", "runs"}``: the loop's cost
    per cycle of each rig (module docstring), the medians of ``repeat`` rounds, after a
    warm-up run of each; ``arm_rigs`` only with the ``arm`` extra."""
    if duration_s <= 0 or repeat < 1 or not ns or min(ns) < 1:
        raise ValueError(f"need duration > 0, repeat >= 1 and N >= 1, got {duration_s}, "
                         f"{repeat}, {ns}")  # fmt: skip
    labels: list[str | int] = [*ns, *(arm_rigs if arm_available() else ())]
    requests = {label: _request(label, duration_s) for label in labels}
    for request in requests.values():  # warm-up: imports, codecs, the arm's model
        loop_cost_us(_request_short(request))
    samples: dict[str | int, list[tuple[float, float, int]]] = {k: [] for k in labels}
    for rnd in range(repeat):
        order = labels[rnd % len(labels) :] + labels[: rnd % len(labels)]
        for label in order:
            samples[label].append(loop_cost_us(requests[label]))
    rows = []
    for label in labels:
        s = requests[label].scenario
        cpu = [c for c, _, _ in samples[label]]
        wall = statistics.median(w for _, w, _ in samples[label])
        cpu_med = statistics.median(cpu)
        n = len(s.joints)
        rows.append({
            "label": f"{n} joint{'s' if n > 1 else ''}" if isinstance(label, int) else label,
            "joints": n,
            "buses": len({j.bus for j in s.joints}),
            "plant": "independent" if s.robot is None else "arm",
            "cpu_us": cpu_med, "wall_us": wall,
            "cpu_us_per_joint": cpu_med / n, "wall_us_per_joint": wall / n,
            "cpu_min_us": min(cpu), "cpu_max_us": max(cpu),
            "cycles": samples[label][0][2], "runs": repeat,
        })  # fmt: skip
    return rows


def _request_short(request: RunRequest) -> RunRequest:
    """``request`` for 50 cycles (a warm-up run)."""
    import dataclasses

    return dataclasses.replace(request, duration_s=min(request.duration_s, 0.05))


def linearity(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The growth verdict over the rows of independent plants (:func:`bench_joint_loop`):
    CPU per joint at each N over one joint's (``ratios``, by N written out: the JSON
    report's keys), the largest of them,
    ``met`` when it is at most :data:`LINEAR_TOLERANCE`, and the least-squares line
    ``cpu = fixed + N * per_joint`` (µs). None without a one-joint row."""
    rows = sorted((r for r in rows if r["plant"] == "independent"), key=lambda r: r["joints"])
    one = next((r for r in rows if r["joints"] == 1), None)
    if one is None or one["cpu_us"] <= 0:
        return {"met": None, "ratios": {}, "worst_ratio": None, "tolerance": LINEAR_TOLERANCE}
    ratios = {str(r["joints"]): r["cpu_us_per_joint"] / one["cpu_us"] for r in rows}
    worst = max(ratios.values())
    out: dict[str, Any] = {
        "ratios": ratios,
        "worst_ratio": worst,
        "tolerance": LINEAR_TOLERANCE,
        "met": worst <= LINEAR_TOLERANCE,
    }
    if len(rows) >= 2:
        xs = [float(r["joints"]) for r in rows]
        ys = [float(r["cpu_us"]) for r in rows]
        slope, intercept = statistics.linear_regression(xs, ys)
        out.update(per_joint_us=slope, fixed_us=intercept)
    return out


def bench_rig_whole(
    duration_s: float, runs: int, rigs: Sequence[str] = tuple(RIG_GOALS)
) -> list[dict[str, Any]]:
    """Rows per rig: ``hdhil run --scenario NAME --duration D --trace a.blf`` as a whole
    process ``runs`` times, in turns; median whole-process wall time, its real-time
    factor against :data:`RIG_GOALS`, the loop's and the start-up's share (stamps of
    :data:`hdhil.analysis.speed.STAGES_CHILD`). Empty without the ``arm`` extra."""
    from hdhil.analysis.speed import STAGES_CHILD, timed_process

    if not arm_available():
        return []
    per: dict[str, list[dict[str, Any]]] = {name: [] for name in rigs}
    with tempfile.TemporaryDirectory() as tmp:
        trace = str(Path(tmp) / "a.blf")
        for _ in range(runs):
            for name in rigs:
                argv = [sys.executable, "-c", STAGES_CHILD, "run", "--scenario", name,
                        "--duration", f"{duration_s:g}", "--trace", trace]  # fmt: skip
                p = timed_process(argv)
                st = p["stamps"]
                if "first_cycle" not in st:
                    raise UserError(f"bench: hdhil run --scenario {name} reported no cycle")
                per[name].append({
                    "whole_s": p["wall_s"], "cpu_s": p["cpu_s"],
                    "start_up_s": st["first_cycle"] - p["spawned"],
                    "loop_s": st["last_cycle"] - st["first_cycle"],
                })  # fmt: skip
    rows = []
    for name in rigs:
        med = {k: statistics.median(r[k] for r in per[name]) for k in per[name][0]}
        goal = RIG_GOALS.get(name)
        rtf = duration_s / med["whole_s"]
        rows.append({
            "scenario": name, "duration_s": duration_s, "runs": runs, **med,
            "min_whole_s": min(r["whole_s"] for r in per[name]),
            "max_whole_s": max(r["whole_s"] for r in per[name]),
            "real_time_factor": rtf,
            "cpu_factor": duration_s / med["cpu_s"] if med["cpu_s"] > 0 else None,
            "loop_real_time_factor": duration_s / med["loop_s"] if med["loop_s"] > 0 else None,
            "goal": goal, "met": None if goal is None else rtf >= goal,
        })  # fmt: skip
    return rows


def bench_joints(
    loop_s: float, repeat: int, whole_duration_s: float, whole_runs: int
) -> dict[str, Any]:
    """The joints section: the loop's cost by joint count (``loop_s`` simulated seconds a
    run, ``repeat`` rounds), its growth verdict, and the rigs' whole command
    (``whole_duration_s`` a run, ``whole_runs`` runs)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        loop = bench_joint_loop(loop_s, repeat)
        whole = bench_rig_whole(whole_duration_s, whole_runs)
    return {
        "loop_s": loop_s,
        "scenario": JOINT_SCENARIO,
        "joints_per_bus": JOINTS_PER_BUS,
        "loop": loop,
        "linearity": linearity(loop),
        "whole": whole,
        "arm": arm_available(),
    }


def _factor(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}x"


def _verdict(met: bool | None) -> str:
    return "" if met is None else ("met" if met else "NOT met")


def format_joints_section(j: dict[str, Any]) -> list[str]:
    """The joints section of the text report: the loop's cost per cycle and per joint,
    the growth verdict, the rigs' whole command against their goals."""
    runs = j["loop"][0]["runs"] if j["loop"] else 0
    lines = [
        f"Loop cost by joint count (lockstep on simbus, no trace; N joints of {j['scenario']} "
        f"with independent plants, {j['joints_per_bus']} a classical 1 Mbit/s bus; the arm's "
        f"plant: the shipped rigs; median of {runs} runs of {j['loop_s']:g} s, in turns)"
    ]
    rows = [
        [r["label"], str(r["joints"]), str(r["buses"]), r["plant"], f"{r['cpu_us']:.0f}",
         f"{r['cpu_min_us']:.0f}-{r['cpu_max_us']:.0f}", f"{r['cpu_us_per_joint']:.1f}",
         f"{r['wall_us']:.0f}", f"{r['wall_us_per_joint']:.1f}"]
        for r in j["loop"]
    ]  # fmt: skip
    lines += markdown_table(
        ["rig", "joints", "buses", "plant", "CPU us/cycle", "min-max", "CPU us/joint",
         "wall us/cycle", "wall us/joint"],
        rows, [False, True, True, False, True, True, True, True, True],
    )  # fmt: skip
    lin = j["linearity"]
    if lin.get("worst_ratio") is not None:
        ratios = ", ".join(
            f"N={n}: {v:.2f}" for n, v in sorted(lin["ratios"].items(), key=lambda kv: int(kv[0]))
        )
        fit = (
            f"; least squares: {lin['fixed_us']:.0f} us + N x {lin['per_joint_us']:.1f} us"
            if "per_joint_us" in lin
            else ""
        )
        lines.append(
            f"growth: CPU per joint over one joint's ({ratios}); goal no faster than linear "
            f"(every ratio <= {lin['tolerance']:g}): {_verdict(lin['met'])}{fit}"
        )
    if not j["arm"]:
        lines.append("arm plant and the rigs' whole command: not measured (needs the arm extra)")
        return lines
    lines += ["", "Rigs' whole command (hdhil run --scenario NAME --duration D --trace a.blf, "
              "lockstep; median of the processes, in turns; CPU: the process and its trace "
              "writer; the verdict is on the real-time factor, wall time)"]  # fmt: skip
    rows = [
        [r["scenario"], f"{r['duration_s']:g}", f"{r['whole_s']:.2f}",
         f"{r['min_whole_s']:.2f}-{r['max_whole_s']:.2f}", f"{r['start_up_s']:.2f}",
         f"{r['cpu_s']:.2f}", _factor(r.get("cpu_factor")), f"{r['real_time_factor']:.2f}x",
         "" if r["goal"] is None else f">= {r['goal']:g}x", _verdict(r["met"])]
        for r in j["whole"]
    ]  # fmt: skip
    lines += markdown_table(
        ["scenario", "sim s", "whole s", "min-max s", "start-up s", "CPU s", "sim s / CPU s",
         "real-time factor", "goal", "verdict"],
        rows, [False, True, True, True, True, True, True, True, False, False],
    )  # fmt: skip
    return lines
