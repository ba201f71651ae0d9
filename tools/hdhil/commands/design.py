"""``hdhil design lqg``: the LQG torque regulator of [Vertechy], designed from parameters.

This module reads the joint parameters, weights and options (defaults: the seed's
values), designs the regulator with :func:`hdhil.firmware.lqg_design.design_lqg` and
prints the report of :mod:`hdhil.analysis.lqg_report` (text or ``--json``).  Exit
codes: 0 done, 2 bad parameter or failed design (one line).
"""

from __future__ import annotations

import argparse
import sys

from hdhil.analysis.lqg_report import design_dict, format_design
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.firmware.lqg_design import (
    DesignError,
    Feedforward,
    JointParams,
    LqgDesign,
    LqgWeights,
    ObserverMethod,
    design_lqg,
)

#: (option, help) of the numeric parameters; parsed in :func:`_number` so that a bad
#: value is a one-line error like every other parameter mistake.
_NUMBERS = (
    ("Jm", "motor-side inertia reduced to the output shaft [kg m²]"),
    ("Jl", "link-side inertia [kg m²]"),
    ("k", "joint stiffness [Nm/rad]"),
    ("c", "joint damping [Nms/rad]"),
    ("q1", "LQ weight on (tau_s - tau_sD)² (enters Q linearly)"),
    ("q2", "LQ weight on tau_s'²"),
    ("W", "variance of each 1 kHz torque sample [Nm²]"),
    ("V", "tau_lgd Wiener process, in the convention of W (only V/W sets L)"),
    ("Ts", "sample period of the discrete observer [s]"),
)
_DEFAULTS = {**vars(JointParams()), **vars(LqgWeights()), "Ts": 1e-3}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "design",
        help="controller design (LQG joint-torque regulator of [Vertechy])",
        description="Controller design tools.",
    )
    sub = parser.add_subparsers(dest="design_command", metavar="DESIGN", required=True)
    p = sub.add_parser(
        "lqg",
        help="LQ gains, Kalman gain and 1 kHz observer of the [Vertechy] LQG regulator",
        description="Design the LQG joint-torque regulator of [Vertechy] (Vertechy et al.): "
        "LQ gains k1..k5 (Eqs. 4, 6), continuous Kalman gain L (Eq. 8), closed-loop poles, "
        "the discrete observer at Ts and the sampled loop with one sample of actuation "
        "delay.  Defaults are the seed's values; torques use the seed's sign convention "
        "tau_s = k (theta_l - theta_m).",
    )
    for name, text in _NUMBERS:
        p.add_argument(
            f"--{name}",
            default=None,
            metavar="X",
            help=f"{text} (default {_DEFAULTS[name]:g})",
        )
    p.add_argument(
        "--method",
        choices=[m.value for m in ObserverMethod],
        default=ObserverMethod.ZOH_KALMAN.value,
        help="observer discretisation: discrete Kalman filter of the ZOH model (default) "
        "or ZOH of the continuous observer with the seed's L",
    )
    p.add_argument(
        "--feedforward",
        choices=[f.value for f in Feedforward],
        default=Feedforward.LQ.value,
        help="k3..k5: Friedland's LQ exogenous-input gains, as in the seed (default), "
        "or the zero-steady-state-error feedforward",
    )
    p.add_argument(
        "--delay",
        type=int,
        choices=(0, 1),
        default=1,
        help="actuation delay of the analysed loop in samples (default 1: synchronous PDO)",
    )
    p.add_argument(
        "--no-predict",
        action="store_true",
        help="analyse the loop without the one-step state prediction that compensates the delay",
    )
    p.add_argument("--json", action="store_true", help="print the design as JSON")
    p.set_defaults(func=run)


def _number(args: argparse.Namespace, name: str) -> float:
    raw = getattr(args, name)
    if raw is None:
        return float(_DEFAULTS[name])
    try:
        return float(raw)
    except ValueError:
        raise UserError(f"--{name}: expected a number, got {raw!r}") from None


def _design(args: argparse.Namespace) -> LqgDesign:
    v = {name: _number(args, name) for name, _ in _NUMBERS}
    try:
        params = JointParams(v["Jm"], v["Jl"], v["k"], v["c"])
        weights = LqgWeights(v["q1"], v["q2"], v["W"], v["V"])
        return design_lqg(
            params,
            weights,
            Ts=v["Ts"],
            method=ObserverMethod(args.method),
            feedforward=Feedforward(args.feedforward),
        )
    except DesignError as exc:
        raise UserError(f"design failed: {exc}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    design = _design(args)
    predict = not args.no_predict
    if args.json:
        jsonout.dump(design_dict(design, args.delay, predict), sys.stdout, indent=2)
        print()
    else:
        print(format_design(design, args.delay, predict))
    return 0
