"""[Vertechy] Fig. 7: the §VI tracking simulation, solved in closed form.

Independent of hdhil (numpy and scipy only).  §VI: JTF1 tracks ``τsD = 20 sin(0.4πt)`` Nm
while the link is moved as ``θl = 20 sin(2πt)`` deg, ``τd = τg = W = 0``; the paper
reports ``|e| ≤ 0.3 Nm``.  The plant is the motor side of Eq. 1 with the link on its
trajectory, ``Jm θm'' = τm + τs + (c/k) τs'``, ``τs = k (θl − θm)``; the exogenous torque
is ``τlgd = Jl θl'' + τs + (c/k) τs'``.  The loop is linear and its inputs are two
sines, so the steady state is exact from the closed loop's frequency response at 0.2 and
1 Hz, summed over their common period (5 s): no time step, no start-up transient, no
sampling and no actuation delay (the ideal the 1 kHz loop over CAN approximates).

- ``perfect``: Eq. 4 with the printed gains on the true τs, τs', τlgd: what the gains
  can do at best with a perfect observer (about 0.75 Nm).
- ``lqg``: Eq. 4 on the continuous observer of Eq. 8 with the printed L, the ideal
  continuous LQG (about 1.15 Nm); JTF2 and JTF3 on the same observer give the ranking.
- Two readings approach 0.3 Nm: the link at 0.5 Hz (the link's share of the error grows
  with the cube of its frequency; scored over the 10 s common period of the two sines)
  and Eq. 6's weights squared as printed (Q = diag(q1², q2²)).

Run ``python vertechy_fig7.py`` for the numbers.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_continuous_are

#: [Vertechy] §I-II: Jm, Jl (kg m²), k (Nm/rad), c (Nms/rad), reduced to the output.
JM, JL, K, C = 2.5, 0.7, 6300.0, 11.8
#: [Vertechy] §VI: the printed LQ gains k1..k4 and Kalman gain L.
PRINTED_K = (-18.3, -0.33, -2.81, 3.62)
PRINTED_L = (199.0, 19854.0, 289.0)
#: §VI's conditions: τsD amplitude (Nm) and frequency (Hz), link amplitude (deg), frequency.
DESIRED_NM, DESIRED_HZ = 20.0, 0.2
LINK_DEG, LINK_HZ = 20.0, 1.0


def lq_gains_squared(q1: float = 500.0, q2: float = 0.1) -> tuple[float, float, float, float]:
    """k1..k4 with Eq. 6's weights squared as printed, ``Q = diag(q1², q2²)``, R = 1
    (k3, k4: Friedland's steady-state gains ``G0 = −R⁻¹Bᵀ(A − BG)⁻ᵀPE``)."""
    j = JM * JL / (JM + JL)
    a = np.array([[0.0, 1.0], [-K / j, -C / j]])
    b = np.array([[0.0], [-K / JM]])
    e = np.array([[0.0, 0.0], [K / JL, -K / j]])
    p = solve_continuous_are(a, b, np.diag([q1**2, q2**2]), np.eye(1))
    g = b.T @ p
    g0 = -b.T @ np.linalg.inv((a - b @ g).T) @ p @ e
    k1, k2, k3, k4 = np.concatenate([g.ravel(), g0.ravel()])
    return float(k1), float(k2), float(k3), float(k4)


def law_gains(law: str, gains: tuple[float, ...] = PRINTED_K) -> tuple[float, ...]:
    """k1..k4 of JTF1 (``gains``), JTF2 (k3 = 0, k4 = 1 + Jm/Jl) or JTF3 (k3 = 0, k4 = 1)."""
    k1, k2, k3, k4 = gains
    if law == "jtf2":
        return k1, k2, 0.0, 1.0 + JM / JL
    if law == "jtf3":
        return k1, k2, 0.0, 1.0
    if law != "jtf1":
        raise ValueError(f"law must be jtf1, jtf2 or jtf3, got {law!r}")
    return k1, k2, k3, k4


def max_error(
    gains: tuple[float, ...] = PRINTED_K,
    observer: tuple[float, ...] | None = PRINTED_L,
    *,
    link_Hz: float = LINK_HZ,
    link_deg: float = LINK_DEG,
    points_per_s: int = 20_000,
) -> float:
    """Steady-state max |τs − τsD| (Nm) of Eq. 4 on the observer of Eq. 8 with gain
    ``observer`` (None: on the true states, a perfect observer)."""
    k1, k2, k3, k4 = gains
    j = JM * JL / (JM + JL)
    # columns: x = [θm, θm', x̂1, x̂2, x̂3], then the inputs w = [θl, θl', θl'', τsD]
    n = 2 if observer is None else 5
    cols = n + 4
    ts, tsd, sd = np.zeros(cols), np.zeros(cols), np.zeros(cols)
    ts[0], ts[n] = -K, K  # τs = k (θl − θm)
    tsd[1], tsd[n + 1] = -K, K  # τs' = k (θl' − θm')
    sd[n + 3] = 1.0
    if observer is None:
        tlgd = ts + (C / K) * tsd
        tlgd[n + 2] += JL
        est = (ts, tsd, tlgd)
    else:
        est = tuple(np.eye(cols)[i] for i in (2, 3, 4))
    tau_m = -(k1 * (est[0] - sd) + k2 * est[1] + k3 * est[2] + k4 * sd)
    m = np.zeros((n, cols))
    m[0, 1] = 1.0
    m[1] = (tau_m + ts + (C / K) * tsd) / JM
    if observer is not None:
        a_obs = np.array([[0.0, 1.0, 0.0], [-K / j, -C / j, K / JL], [0.0, 0.0, 0.0]])
        b_obs = np.array([0.0, -K / JM, 0.0])
        xh = np.zeros((3, cols))
        xh[:, 2:5] = np.eye(3)
        m[2:5] = a_obs @ xh + np.outer(b_obs, tau_m) + np.outer(observer, ts - est[0])
    a, b = m[:, :n], m[:, n:]
    if np.max(np.linalg.eigvals(a).real) >= 0.0:
        raise ValueError("the closed loop is unstable")
    period = 1.0 / math.gcd(round(link_Hz * 1000), round(DESIRED_HZ * 1000)) * 1000
    t = np.linspace(0.0, period, round(period * points_per_s) + 1)
    e = np.zeros_like(t)
    amp = math.radians(link_deg)
    wl, wd = 2 * math.pi * link_Hz, 2 * math.pi * DESIRED_HZ
    for w, u in (
        (wl, np.array([amp, 1j * wl * amp, -(wl**2) * amp, 0.0])),
        (wd, np.array([0.0, 0.0, 0.0, DESIRED_NM])),
    ):
        x = np.linalg.solve(1j * w * np.eye(n) - a, b @ u)
        z = np.concatenate([x, u])
        e += np.imag((ts - sd) @ z * np.exp(1j * w * t))  # each input is amplitude × sin
    return float(np.max(np.abs(e)))


def figures() -> dict[str, float]:
    """The numbers of Fig. 7's row, max |e| in Nm."""
    squared = lq_gains_squared()
    return {
        "perfect_state": max_error(observer=None),
        "ideal_lqg": max_error(),
        "ideal_jtf2": max_error(law_gains("jtf2")),
        "ideal_jtf3": max_error(law_gains("jtf3")),
        "slow_link": max_error(link_Hz=0.5),
        "squared_weights": max_error(squared),
        "held_link": max_error(link_deg=0.0),
    }


def main() -> None:
    f = figures()
    print("[Vertechy] Fig. 7, steady state, continuous, no delay (numpy/scipy only): max |e|")
    print(f"  JTF1, printed gains, perfect state estimates   {f['perfect_state']:.3f} Nm")
    print(f"  JTF1, ideal continuous LQG (printed k, L)      {f['ideal_lqg']:.3f} Nm")
    print(
        f"  JTF3 / JTF2 on the same observer               {f['ideal_jtf3']:.3f} / "
        f"{f['ideal_jtf2']:.3f} Nm"
    )
    print(f"  JTF1, link at 0.5 Hz                           {f['slow_link']:.3f} Nm")
    print(f"  JTF1, Eq. 6 weights squared                    {f['squared_weights']:.3f} Nm")
    print(f"  JTF1, link held                                {f['held_link']:.3f} Nm")


if __name__ == "__main__":
    main()
