"""The report of an LQG joint-torque regulator design ([Vertechy]): text and JSON.

:func:`format_design` writes what ``hdhil design lqg`` prints: the LQ gains k1..k5
(Eq. 4 and the §IV τsD' feedforward), the continuous Kalman gain L (Eq. 8), the
closed-loop poles, the discrete observer actually used at Ts and the poles/margins of
the sampled loop with the actuation delay (also with the link clamped).
:func:`design_dict` is the same as a JSON-ready dict.  The numerics are all in
:mod:`hdhil.firmware.lqg_design` (:func:`~hdhil.firmware.lqg_design.design_lqg`,
:func:`~hdhil.firmware.lqg_design.loop_analysis`); this module only reports them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hdhil.firmware.lqg_design import ControlLaw, LoopAnalysis, LqgDesign, loop_analysis

__all__ = ["design_dict", "format_design"]


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
