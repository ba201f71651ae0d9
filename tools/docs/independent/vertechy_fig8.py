"""[Vertechy] Fig. 8 computed from the paper's equations with numpy and scipy only.

An independent check of ``hdhil run --scenario lqg-experiment``: nothing here imports
hdhil.  The joint is Eq. 1 with the link's motion prescribed (a person moving the
handle), the sensor torque ``tau_s = k (theta_l - theta_m)`` is measured with white
noise of standard deviation W, and the regulator is JTF1 with the friction
compensation of Eq. 5 on the Kalman observer of Eq. 8:

- LQ gains k1..k4 of Eq. 6 from the continuous Riccati equation with ``Q = diag(q1,
  q2)``, ``R = 1`` (q1, q2 weighting the squared errors, as hdhil's design reads Eq. 6, which
  prints them squared), k3 and k4 as the steady-state gains on the constant exogenous
  inputs ``tau_0 = [tau_lgd, tau_s^D]`` (``-R⁻¹ Bᵀ (A - B K)⁻ᵀ P E``);
- the Kalman gain L of Eq. 8 from the continuous Riccati equation of the meta-system
  (Eq. 7) with noise intensities ``W Ts`` and ``V Ts``, the observer discretised by a
  zero-order hold over one sample; it is fed ``tau_m + tau_d_hat`` (§V), so its third
  state is ``tau_lg`` (the handle torque, ``tau_g = 0``);
- one sample of actuation delay: the command computed at sample k from the observer's
  estimate for sample k+1 acts from sample k+1; a first-order current lag;
- the plant's motor friction ``-C tanh(w_m / s) - b w_m`` (``w_m`` the motor-shaft
  speed, ``C`` 13.7 Nm, ``s`` 2 rad/s, ``b`` output-referred torque per motor rad/s, 0 in
  the scenario: the model exact; 0.15 the motor-viscous reading),
  and the firmware's model in either reading of the garbled Eq. 5 (``"tanh"``:
  ``-C tanh(w/s)``; ``"fade-in"``: ``-C sgn(w) (1 + tanh(|w|/s - 4)) / 2``), on a
  tachometer with white noise;
- a Coulomb friction in the output-shaft bearings, on the link side of the joint's
  torque sensor and before the handle (``link_coulomb_Nm``, 3 Nm as in the scenario):
  the person at the handle overcomes it, so the handle's sensor (``tau_l``, the
  handle torque the estimate is scored against) does not see it, and the observer,
  which sees all torque on the link, counts it as external torque;
- the person: five sinusoids of 0.05-0.25 Hz from ``numpy.random.default_rng(seed)``,
  amplitudes ∝ 1/f, scaled to a 60 deg peak over the first 20 s and to at most 1000 rpm of
  the motor (the same recipe as the emulator's ``person`` link, rebuilt here).

The emulator adds what this leaves out (12-bit ADC and DAC quantisation, the CAN
loop's timing, its own noise sequence), so the two agree within a tolerance, not to the
digit (``tests/test_independent_fig8.py``).

Run ``python tools/docs/independent/vertechy_fig8.py`` to print the figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm, solve_continuous_are


@dataclass(frozen=True)
class Fig8Setup:
    """The §VI experiment; defaults as in ``lqg-experiment``."""

    Jm: float = 2.5  # kg m², motor reduced to the output (§I)
    Jl: float = 0.7  # kg m², link (§III)
    k: float = 6300.0  # Nm/rad (§I)
    c: float = 11.8  # Nms/rad (§II)
    gear_ratio: float = 100.0
    q1: float = 500.0
    q2: float = 0.1
    W: float = 0.12  # Nm, the sensor noise's standard deviation per sample
    V: float = 1e4
    Ts: float = 1e-3
    duration_s: float = 20.0
    skip_s: float = 1.0
    amplitude_Nm: float = 20.0  # tau_s^D = 20 sin(0.4 pi t)
    frequency_Hz: float = 0.2
    coulomb_Nm: float = 13.7  # plant and model
    velocity_scale_radps: float = 2.0  # at the motor shaft
    viscous_Nm_per_motor_radps: float = 0.0  # plant only (unmodelled; 0.15: the viscous reading)
    # a Coulomb friction on the link side of the sensor (output-shaft bearings, Nm,
    # smoothed over link_smoothing_radps of the link): the handle's sensor does not see
    # it, the observer lumps it into tau_lg
    link_coulomb_Nm: float = 3.0
    link_smoothing_radps: float = 0.01
    model: str = "tanh"  # the firmware's reading of Eq. 5: "tanh" or "fade-in"
    plant_model: str = "tanh"  # the plant's Coulomb friction, the same two forms
    fade_in_offset: float = 4.0
    tacho_noise_radps: float = 0.05
    current_lag_s: float = 4e-4
    link_amplitude_deg: float = 60.0
    motion_seed: int = 1
    motion_horizon_s: float = 20.0  # the 60 deg peak falls within this span
    max_link_speed_radps: float = 1000.0 * 2.0 * math.pi / 60.0 / 100.0
    noise_seed: int = 12345
    substeps: int = 10


@dataclass(frozen=True)
class Fig8Result:
    """Time series (paper's convention, from t = 0) and the §VI figures (from skip_s)."""

    t: np.ndarray
    tau_s: np.ndarray
    tau_s_meas: np.ndarray
    tau_sD: np.ndarray
    tau_l: np.ndarray
    tau_l_hat: np.ndarray
    tau_m: np.ndarray
    max_abs_tau_m: float
    within_true: float  # fraction of |tau_s - tau_sD| <= 0.5 Nm
    within_measured: float  # fraction of |tau_s^m - tau_sD| <= 0.5 Nm
    max_abs_tau_l_err: float
    k: tuple[float, float, float, float]
    L: tuple[float, float, float]


def lq_gains(s: Fig8Setup) -> tuple[float, float, float, float]:
    """k1..k4 of Eq. 4 minimising Eq. 6 for Eq. 3."""
    J = s.Jm * s.Jl / (s.Jm + s.Jl)
    A = np.array([[0.0, 1.0], [-s.k / J, -s.c / J]])
    B = np.array([[0.0], [-s.k / s.Jm]])
    E = np.array([[0.0, 0.0], [s.k / s.Jl, -s.k / J]])
    P = solve_continuous_are(A, B, np.diag([s.q1, s.q2]), np.eye(1))
    K = B.T @ P
    K0 = -B.T @ np.linalg.solve((A - B @ K).T, P @ E)
    return float(K[0, 0]), float(K[0, 1]), float(K0[0, 0]), float(K0[0, 1])


def kalman_gain(s: Fig8Setup) -> np.ndarray:
    """L of Eq. 8 for the meta-system of Eq. 7."""
    J = s.Jm * s.Jl / (s.Jm + s.Jl)
    A = np.array([[0.0, 1.0, 0.0], [-s.k / J, -s.c / J, s.k / s.Jl], [0.0, 0.0, 0.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    G = np.array([[0.0], [0.0], [1.0]])
    P = solve_continuous_are(A.T, C.T, G @ G.T * s.V * s.Ts, np.eye(1) * s.W * s.Ts)
    return (P @ C.T / (s.W * s.Ts)).ravel()


def friction_model(s: Fig8Setup, w: float, form: str | None = None) -> float:
    """The firmware's tau_d_hat (or, with ``form``, that form) at the motor-shaft speed
    w (rad/s)."""
    form = s.model if form is None else form
    x = w / s.velocity_scale_radps
    if form == "tanh":
        return -s.coulomb_Nm * math.tanh(x)
    if form == "fade-in":
        if x == 0.0:
            return 0.0
        return -math.copysign(s.coulomb_Nm * 0.5 * (1.0 + math.tanh(abs(x) - s.fade_in_offset)), x)
    raise ValueError(f"friction form must be 'tanh' or 'fade-in', got {form!r}")


def person(s: Fig8Setup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(amplitude rad, omega rad/s, phase rad) of the person's five sinusoids."""
    rng = np.random.default_rng(s.motion_seed)
    f = rng.uniform(0.05, 0.25, 5)
    phase = rng.uniform(0.0, 2.0 * math.pi, 5)
    w, a = 2.0 * math.pi * f, 1.0 / f
    t = np.arange(0.0, s.motion_horizon_s, 0.01)
    shape = (a[:, None] * np.sin(w[:, None] * t + phase[:, None])).sum(axis=0)
    speed = (a[:, None] * w[:, None] * np.cos(w[:, None] * t + phase[:, None])).sum(axis=0)
    scale = math.radians(s.link_amplitude_deg) / float(np.max(np.abs(shape)))
    scale = min(scale, s.max_link_speed_radps / float(np.max(np.abs(speed))))
    return scale * a, w, phase


def simulate(s: Fig8Setup = Fig8Setup()) -> Fig8Result:
    """Run the experiment; see the module docstring."""
    J = s.Jm * s.Jl / (s.Jm + s.Jl)
    k1, k2, k3, k4 = lq_gains(s)
    L = kalman_gain(s)
    A = np.array([[0.0, 1.0, 0.0], [-s.k / J, -s.c / J, s.k / s.Jl], [0.0, 0.0, 0.0]])
    Bu = np.array([0.0, -s.k / s.Jm, 0.0])
    C = np.array([1.0, 0.0, 0.0])
    # observer x' = (A - L C) x + Bu u + L y, inputs held over a sample
    aug = np.zeros((5, 5))
    aug[:3, :3] = A - np.outer(L, C)
    aug[:3, 3] = Bu
    aug[:3, 4] = L
    e = expm(aug * s.Ts)
    Ad, Bd = e[:3, :3], e[:3, 3:]

    amp, om, ph = person(s)
    n = round(s.duration_s / s.Ts)
    rng = np.random.default_rng(s.noise_seed)
    noise = rng.normal(0.0, s.W, n)
    tacho = rng.normal(0.0, s.tacho_noise_radps, n)
    h = s.Ts / s.substeps
    lag = math.exp(-h / s.current_lag_s) if s.current_lag_s > 0 else 0.0
    N, C0, vs = s.gear_ratio, s.coulomb_Nm, s.velocity_scale_radps
    b_out = s.viscous_Nm_per_motor_radps * N  # Nm per output rad/s
    Jm, k, c = s.Jm, s.k, s.c

    def link(t: float) -> tuple[float, float]:
        x = om * t + ph
        return float(np.dot(amp * om, np.cos(x))), float(-np.dot(amp * om * om, np.sin(x)))

    fade = s.plant_model != "tanh"
    if fade:
        friction_model(s, 1.0, s.plant_model)  # checks the name

    def motor_accel(d: float, wm: float, wl: float, tau: float) -> float:
        if fade:
            fr = friction_model(s, wm * N, s.plant_model) - b_out * wm
        else:
            fr = -C0 * math.tanh(wm * N / vs) - b_out * wm
        return (tau + fr + k * d + c * (wl - wm)) / Jm

    # start as a rigid joint moving with the link
    wl0, _ = link(0.0)
    d, wm, tau_act = 0.0, wl0, 0.0
    xh = np.zeros(3)
    cmd = 0.0  # the command acting during the current sample
    out = np.empty((n, 7))
    desired = lambda i: s.amplitude_Nm * math.sin(2.0 * math.pi * s.frequency_Hz * i * s.Ts)  # noqa: E731
    for i in range(n):
        t = i * s.Ts
        wl, al = link(t)
        tau_s = k * d
        y = tau_s + noise[i]
        w_meas = wm * N + tacho[i]
        td_hat = friction_model(s, w_meas)
        # the handle's torque: what moves the link against the joint and the bearings
        tau_l = (
            s.Jl * al
            + tau_s
            + c * (wl - wm)
            + s.link_coulomb_Nm * math.tanh(wl / s.link_smoothing_radps)
        )
        out[i] = (t, tau_s, y, desired(i), tau_l, xh[2], cmd)
        # observer over this sample, fed the command acting now plus the model (§V)
        xh = Ad @ xh + Bd @ np.array([cmd + td_hat, y])
        # Eq. 5 on the estimate for the next sample, acting from then on
        sD = desired(i + 1)
        nxt = -(k1 * (xh[0] - sD) + k2 * xh[1] + k3 * xh[2] + k4 * sD) - td_hat
        # the plant over this sample (Heun sub-steps), the current lagging the command
        for j in range(s.substeps):
            tj = t + j * h
            wl_a, _ = link(tj)
            wl_b, _ = link(tj + h)
            tau_next = cmd + (tau_act - cmd) * lag
            a1 = motor_accel(d, wm, wl_a, tau_act)
            d1, wm1 = d + h * (wl_a - wm), wm + h * a1
            a2 = motor_accel(d1, wm1, wl_b, tau_next)
            d += 0.5 * h * ((wl_a - wm) + (wl_b - wm1))
            wm += 0.5 * h * (a1 + a2)
            tau_act = tau_next
        cmd = nxt
    t, ts, ym, sd, tl, tlh, tm = out.T
    m = t >= s.skip_s
    return Fig8Result(
        t=t,
        tau_s=ts,
        tau_s_meas=ym,
        tau_sD=sd,
        tau_l=tl,
        tau_l_hat=tlh,
        tau_m=tm,
        max_abs_tau_m=float(np.max(np.abs(tm[m]))),
        within_true=float(np.mean(np.abs(ts[m] - sd[m]) <= 0.5)),
        within_measured=float(np.mean(np.abs(ym[m] - sd[m]) <= 0.5)),
        max_abs_tau_l_err=float(np.max(np.abs(tlh[m] - tl[m]))),
        k=(k1, k2, k3, k4),
        L=(float(L[0]), float(L[1]), float(L[2])),
    )


def main() -> None:
    r = simulate()
    print(f"k1..k4 {', '.join(f'{g:.4g}' for g in r.k)}; L {', '.join(f'{g:.5g}' for g in r.L)}")
    print(
        f"max |tau_m| {r.max_abs_tau_m:.1f} Nm; |e| <= 0.5 Nm: true {100 * r.within_true:.1f} %, "
        f"measured {100 * r.within_measured:.1f} %; max |tau_l_hat - tau_l| "
        f"{r.max_abs_tau_l_err:.2f} Nm"
    )


if __name__ == "__main__":
    main()
