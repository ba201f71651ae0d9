"""``hdhil plan``: a scenario's buses checked before it runs: worst-case load and CPU.

For each bus of the scenario's rig (one bus for a single-joint scenario; the
``[buses]``/``[joints]`` layout otherwise) it prints the cyclic frames the rig's
database holds, each at its worst-case time, the bus's worst-case load and its SYNC to
last frame time, with a verdict against the 60 % limit; then the CPU a cycle needs
predicted by the speed cost model, measured on this machine unless ``--no-cpu``. A bus
over the limit is refused: the figures, the suggestions computed from them, one line on
standard error and exit 2. The computation is :mod:`hdhil.analysis.rigplan`.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from hdhil.commands.options import add_scenario_arguments, request_from_args
from hdhil.commands.progress import add_quiet_argument, wanted
from hdhil.core import jsonout


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        help="worst-case load of each bus of a scenario's rig, and the CPU a cycle needs",
        description="Check a scenario's buses before it runs: each bus's cyclic frames at "
        "their worst case, its load against the 60 %% limit, and the CPU per cycle the "
        "speed cost model predicts. Exit 2 when a bus is over the limit.",
    )
    add_scenario_arguments(p)
    p.add_argument(
        "--no-cpu",
        action="store_true",
        help="leave out the CPU prediction (it measures the cost model first: a few seconds)",
    )
    p.add_argument("--json", action="store_true", help="print the plan as JSON")
    add_quiet_argument(p)
    p.set_defaults(func=run_plan)


def _cost_model(args: argparse.Namespace) -> dict[str, Any]:
    from hdhil.analysis.speed import MIN_COST_MODEL_S, bench_cost_model

    if wanted(args):
        print("hdhil plan: measuring the CPU cost model (a few seconds) ...", file=sys.stderr)
    return bench_cost_model(MIN_COST_MODEL_S, 1)


def _plan_data(plan: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"scenario": plan.scenario, "fits": plan.fits, "buses": []}
    for p in plan.buses:
        s = p.schedule
        out["buses"].append(
            {
                "bus": s.name,
                "bitrate": s.bitrate,
                "data_bitrate": s.data_bitrate,
                "joints": list(plan.joints[s.name]),
                "worst_case_load": p.load,
                "sync_to_last_frame_s": p.busiest_cycle_s,
                "fits": p.fits,
                "frames": [
                    {
                        "name": t.frame.name,
                        "id": t.frame.can_id,
                        "bytes": t.frame.length,
                        "every_cycles": t.frame.period_cycles,
                        "fd": t.frame.fd,
                        "worst_case_s": t.worst_case_s,
                    }
                    for t in p.frames
                ],
                "notes": list(p.notes),
                "suggestions": list(p.suggestions),
            }
        )
    if plan.cpu is not None:
        c = plan.cpu
        out["cpu"] = {
            "model": {k: c.model[k] for k in ("fixed_us", "per_joint_us", "per_frame_us")},
            "joints": c.joints,
            "frames_per_cycle": c.frames,
            "one_process_us": c.one_process_us,
            "per_bus_us": c.per_bus_us,
            "period_us": c.period_us,
        }
    return out


def _print_plan(plan: Any) -> None:
    n = sum(len(j) for j in plan.joints.values())
    print(f"hdhil plan: scenario {plan.scenario}: {n} joint(s) on {len(plan.buses)} bus(es)")
    for p in plan.buses:
        s = p.schedule
        print()
        print(p.verdict())
        print(f"  joints: {', '.join(plan.joints[s.name])}")
        print(f"  {'frame':<28} {'id':>8} {'bytes':>5} {'every':>6} {'worst case':>11}")
        for t in p.frames:
            f = t.frame
            ident = f"0x{f.can_id:0{8 if f.extended else 3}X}"
            kind = " FD" if f.fd else ""
            print(
                f"  {f.name:<28} {ident:>8} {f.length:>5} {f.period_cycles:>4} c"
                f" {t.worst_case_s * 1e6:>8.0f} us{kind}"
            )
        for line in (*p.notes, *p.suggestions):
            print(f"  - {line}")
    if plan.cpu is not None:
        c = plan.cpu
        m = c.model
        print()
        print(
            f"CPU per cycle (cost model measured now: {m['fixed_us']:.1f} + joints x "
            f"{m['per_joint_us']:.1f} + frames x {m['per_frame_us']:.2f} us):"
        )
        print(
            f"  one process: {c.joints} joint(s), {c.frames:.1f} frames per cycle (truth "
            f"included): {c.one_process_us:.0f} us, {c.one_process_share * 100:.0f} % of "
            f"the {c.period_us:g} us period"
        )
        if len(c.per_bus_us) > 1:
            parts = ", ".join(f"{b} {us:.0f} us" for b, us in c.per_bus_us.items())
            print(f"  one process per bus: {parts}")


def run_plan(args: argparse.Namespace) -> int:
    from hdhil.analysis.rigplan import plan_scenario
    from hdhil.core.errors import UserError

    request = request_from_args(args)
    model = None if args.no_cpu else _cost_model(args)
    mapping = request.mapping
    plan = plan_scenario(request.scenario, mapping.label, model, mapping.dcf)
    if args.json:
        print(jsonout.dumps(_plan_data(plan), indent=2))
    else:
        _print_plan(plan)
    refusal = plan.refusal()
    if refusal is not None:
        raise UserError(refusal)
    return 0
