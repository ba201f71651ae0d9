"""[Vertechy] §VI: the LQ gains k1..k4 and the Kalman gain L, from scipy's Riccati solvers.

Independent of hdhil (numpy and scipy only).  The model is the paper's Eq. 3 (error
state ``[τs − τsD, τs']``, exogenous ``[τlgd, τsD]``) and Eq. 7 (meta-state ``[τs, τs',
τlgd]``, ``τlgd' = v``).  k1, k2 are the LQ state-feedback gains of Eq. 6; k3, k4 are
Friedland's steady-state gains on constant exogenous inputs, ``G0 = −R⁻¹Bᵀ(A − BG)⁻ᵀPE``.
Eq. 6 prints the weights squared (``q1² (τs − τsD)²``); the printed gains need them
linear, ``Q = diag(q1, q2)``.  Run ``python vertechy_gains.py`` for the numbers.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_continuous_are

#: [Vertechy] §I-II: Jm, Jl (kg m²), k (Nm/rad), c (Nms/rad), reduced to the output.
JM, JL, K, C = 2.5, 0.7, 6300.0, 11.8
#: [Vertechy] §VI: the printed gains and the weights they come from.
PRINTED_K = (-18.3, -0.33, -2.81, 3.62)
PRINTED_L = (199.0, 19854.0, 289.0)
Q1, Q2, W, V = 500.0, 0.1, 0.12, 1e4


def lq_gains(
    q1: float = Q1, q2: float = Q2, *, squared: bool = False, jl: float = JL
) -> np.ndarray:
    """k1..k4 of Eq. 4 for the weights of Eq. 6: ``Q = diag(q1, q2)`` (the reading that
    reproduces the printed gains) or, with ``squared``, ``diag(q1², q2²)`` as printed."""
    j = JM * jl / (JM + jl)
    a = np.array([[0.0, 1.0], [-K / j, -C / j]])
    b = np.array([[0.0], [-K / JM]])
    e = np.array([[0.0, 0.0], [K / jl, -K / j]])
    q = np.diag([q1**2, q2**2] if squared else [q1, q2])
    p = solve_continuous_are(a, b, q, np.eye(1))
    g = b.T @ p
    g0 = -b.T @ np.linalg.inv((a - b @ g).T) @ p @ e
    return np.concatenate([g.ravel(), g0.ravel()])


def kalman_gain(w: float = W, v: float = V, *, jl: float = JL) -> np.ndarray:
    """L of Eq. 8, the steady-state Kalman gain of the meta-system Eq. 7 (W and V as
    numbers in one convention: L depends on V/W only)."""
    j = JM * jl / (JM + jl)
    a = np.array([[0.0, 1.0, 0.0], [-K / j, -C / j, K / jl], [0.0, 0.0, 0.0]])
    c = np.array([[1.0, 0.0, 0.0]])
    gamma = np.array([[0.0], [0.0], [1.0]])
    p = solve_continuous_are(a.T, c.T, gamma @ gamma.T * v, np.eye(1) * w)
    return (p @ c.T / w).ravel()


def main() -> None:
    print("[Vertechy] §VI gains (numpy/scipy only)")
    print("  printed        k =", PRINTED_K, " L =", PRINTED_L)
    for label, jl in (("Jl = 0.7", JL), ("Jl = 0.7125", 0.7125)):
        k = lq_gains(jl=jl)
        L = kalman_gain(jl=jl)
        print(f"  {label:13}  k = {np.array2string(k, precision=4)}  L = {L.round(2)}")
    print("  Eq. 6 squared  k =", np.array2string(lq_gains(squared=True), precision=4))


if __name__ == "__main__":
    main()
