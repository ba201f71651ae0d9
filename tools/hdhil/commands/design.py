"""``hdhil design lqg``: the LQG torque regulator of [Vertechy], designed from parameters.

Prints the LQ gains k1..k5 (Eq. 4 and the §IV τsD' feedforward), the continuous
Kalman gain L (Eq. 8), the closed-loop poles, the discrete observer actually used at
``--Ts`` and the poles/margins of the sampled loop with the actuation delay.  All the
numerics are in :mod:`firmware.lqg_design` (whose docstring gives the reading of the seed that
reproduces its printed gains).  Defaults are the seed's values.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

from hdhil.core.errors import UserError
from hdhil.firmware.lqg_design import (
    ControlLaw,
    DesignError,
    Feedforward,
    JointParams,
    LoopAnalysis,
    LqgDesign,
    LqgWeights,
    ObserverMethod,
    design_lqg,
    loop_analysis,
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
        help="k3..k5: Friedland's LQ exogenous-input gains (default, reproduces the seed) "
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


def _fmt_poles(p: np.ndarray) -> str:
    out = []
    z_all = np.asarray(p, complex)
    scale = max(1.0, float(np.max(np.abs(z_all)))) if z_all.size else 1.0
    z_all = np.where(np.abs(z_all) < 1e-12 * scale, 0.0, z_all)
    for z in sorted(z_all, key=lambda z: (z.real, -z.imag)):
        if z.imag < -1e-9 * max(1.0, abs(z)):
            continue
        if abs(z.imag) <= 1e-9 * max(1.0, abs(z)):
            out.append(f"{z.real:.6g}")
        else:
            out.append(f"{z.real:.6g} ± {z.imag:.6g}j")
    return ", ".join(out)


def _fmt_matrix(m: np.ndarray, indent: str) -> str:
    text = np.array2string(np.atleast_2d(m), precision=6, max_line_width=120, separator=", ")
    return "\n".join(indent + line for line in text.splitlines())


def _verdict(loop: LoopAnalysis) -> str:
    if not loop.stable:
        return f"UNSTABLE: max |z| = {loop.spectral_radius:.6g} (margins not meaningful)"
    return (
        f"{'stable' if loop.stable else 'UNSTABLE'}: max |z| = {loop.spectral_radius:.6g}; "
        f"gain margin {loop.gain_margin_db:.3g} dB, phase margin "
        f"{loop.phase_margin_deg:.3g} deg, modulus margin {loop.modulus_margin:.3g}"
    )


def format_design(design: LqgDesign, delay: int, predict: bool) -> str:
    p, w, g, ob = design.params, design.weights, design.gains, design.observer
    loop = loop_analysis(design, ControlLaw.JTF1, delay_samples=delay, predict=predict)
    clamped = loop_analysis(
        design, ControlLaw.JTF1, delay_samples=delay, predict=predict, clamped=True
    )
    j2, j3 = design.gains_for(ControlLaw.JTF2), design.gains_for(ControlLaw.JTF3)
    lines = [
        "LQG joint-torque regulator ([Vertechy]), sign convention tau_s = k (theta_l - theta_m)",
        f"  joint: Jm = {p.Jm:g} kg m², Jl = {p.Jl:g} kg m², k = {p.k:g} Nm/rad, "
        f"c = {p.c:g} Nms/rad (J = {p.J:.6g} kg m², f_n = {p.natural_frequency_hz:.4g} Hz)",
        f"  weights: q1 = {w.q1:g}, q2 = {w.q2:g} (Q = diag(q1, q2), R = 1); "
        f"W = {w.W:g}, V = {w.V:g}",
        f"LQ gains (Eq. 4, feedforward {design.feedforward.value}):",
        f"  k1 = {g.k1:.6g}   k2 = {g.k2:.6g}   k3 = {g.k3:.6g}   k4 = {g.k4:.6g}",
        f"  k5 = {g.k5:.6g} (on tau_sD', JTF1_FF law)",
        f"  JTF2: k3 = {j2.k3:g}, k4 = {j2.k4:.6g};  JTF3: k3 = {j3.k3:g}, k4 = {j3.k4:g}",
        f"  closed-loop poles [rad/s]: {_fmt_poles(design.lq_poles)}",
        "Kalman gain (Eq. 8, continuous):",
        f"  L = [{', '.join(f'{v:.6g}' for v in design.L)}]",
        f"  observer poles [rad/s]: {_fmt_poles(design.observer_poles)}",
        f"Discrete observer ({ob.method.value}, Ts = {ob.Ts:g} s):",
        "  x̂(k) = z(k) + M (y(k) - C z(k));  z(k+1) = Ad z(k) + Bd [tau_m(k); y(k)]",
        "  Ad =",
        _fmt_matrix(ob.Ad, "    "),
        "  Bd =",
        _fmt_matrix(ob.Bd, "    "),
        "  M =",
        _fmt_matrix(ob.M, "    "),
        f"  poles (z): {_fmt_poles(ob.poles)}",
        f"  poles (log z / Ts) [rad/s]: {_fmt_poles(ob.poles_s)}",
        f"Sampled loop (JTF1, delay {delay} sample(s), "
        f"{'with' if predict and delay else 'without'} prediction):",
        f"  poles (z): {_fmt_poles(loop.poles)}",
        f"  {_verdict(loop)}",
        "  same loop with the link clamped (stiff contact; tau_lgd no longer exogenous):",
        f"  {_verdict(clamped)}",
    ]
    return "\n".join(lines)


def design_dict(design: LqgDesign, delay: int, predict: bool) -> dict[str, Any]:
    out = design.as_dict()
    for key, clamped in (("loop", False), ("loop_clamped", True)):
        loop = loop_analysis(
            design, ControlLaw.JTF1, delay_samples=delay, predict=predict, clamped=clamped
        )
        out[key] = {
            "delay_samples": delay,
            "predict": bool(predict and delay),
            **loop.as_dict(),
            "poles": [[float(z.real), float(z.imag)] for z in np.asarray(loop.poles, complex)],
        }
    return out


def run(args: argparse.Namespace) -> int:
    design = _design(args)
    predict = not args.no_predict
    if args.json:
        json.dump(design_dict(design, args.delay, predict), sys.stdout, indent=2)
        print()
    else:
        print(format_design(design, args.delay, predict))
    return 0
