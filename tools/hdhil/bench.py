"""``hdhil bench``: throughput figures, measured in the run itself, reported as medians.

Benchmarks are run here, never as timed unit tests: these machines are shared and
noisy, so every figure is the median of ``--repeat`` runs and comes with its spread.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from hdhil.run import run_lockstep
from hostsim.scenario import load_scenario


def _median_spread(values: list[float]) -> dict[str, float]:
    return {
        "median": statistics.median(values),
        "min": min(values),
        "max": max(values),
        "runs": len(values),
    }


def bench_lockstep(
    scenario: str, duration_s: float, repeat: int, logging: bool, interface: str = "simbus"
) -> dict[str, Any]:
    """Real-time factor of a lockstep run (simulated seconds per wall second)."""
    sc = load_scenario(scenario)
    factors = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeat):
            trace = Path(tmp) / f"bench{i}.blf" if logging else None
            r = run_lockstep(
                sc, duration_s=duration_s, trace=trace, interface=interface, evaluate=False
            )
            factors.append(r.real_time_factor)
            cycles = r.cycles
            frames = r.frames_total
    stats = _median_spread(factors)
    stats.update(
        scenario=scenario,
        duration_s=duration_s,
        logging=logging,
        interface=interface,
        cycles=cycles,
        frames=frames,
        us_per_cycle=1e6 * duration_s / cycles / stats["median"],
    )
    return stats


def run_benchmarks(duration_s: float = 10.0, repeat: int = 3) -> dict[str, Any]:
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    results = {
        "lockstep_free_motion_blf": bench_lockstep("free-motion", duration_s, repeat, True),
        "lockstep_free_motion_nolog": bench_lockstep("free-motion", duration_s, repeat, False),
        "lockstep_free_motion_virtual_bus": bench_lockstep(
            "free-motion", min(duration_s, 2.0), repeat, False, interface="virtual"
        ),
    }
    return {"started": started, "python": sys.version.split()[0], "results": results}


def format_bench(report: dict[str, Any]) -> str:
    lines = [f"hdhil bench ({report['started']}, Python {report['python']}; medians)"]
    for name, r in report["results"].items():
        lines.append(
            f"  {name:<36} {r['median']:6.1f}x real time  "
            f"({r['us_per_cycle']:.0f} us/cycle; min {r['min']:.1f}x, max {r['max']:.1f}x, "
            f"{r['runs']} runs of {r['duration_s']:g} s)"
        )
    return "\n".join(lines)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure throughput (real-time factors, medians)")
    p.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run")
    p.add_argument("--repeat", type=int, default=3, help="runs per figure (median reported)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hdhil.cli import UserError

    if args.duration <= 0 or args.repeat < 1:
        raise UserError("--duration must be > 0 and --repeat >= 1")
    report = run_benchmarks(args.duration, args.repeat)
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        print()
    else:
        print(format_bench(report))
    return 0
