"""The plant's linear models: state-space matrices, their exact discretisation, the steady state.

The stepper (:mod:`hdhil.hostsim.plant.model`) advances the linear part of the amplifier
and the flexible joint ([Vertechy] Eq. 1) with the matrix exponential of these models,
computed once per step size; the non-linear terms (Coulomb friction, gravity, the load
profile) enter as inputs held over a sub-step. Kept apart from the stepper because the
matrices are also what a controller design or a test checks against.

:func:`steady_state_motor_velocity` and :func:`steady_state_volts` are the closed-form
torque balance at constant input: how a scenario picks its amplifier inputs.
"""

from __future__ import annotations

import math

import numpy as np

from hdhil.core.expm import expm
from hdhil.hostsim.plant.config import PlantConfig

__all__ = [
    "continuous_model",
    "discrete_model",
    "has_ideal_amplifier",
    "person_model",
    "prescribed_model",
    "steady_state_motor_velocity",
    "steady_state_volts",
    "zoh",
]


def steady_state_motor_velocity(cfg: PlantConfig, volts: float, load_Nm: float = 0.0) -> float:
    """Motor velocity (rad/s) the plant settles to at a constant amplifier input.

    Torque balance at the output ([Vertechy] Eq. 1 with all accelerations zero and the
    Coulomb friction as a sign function)::

        N Kt i + tau_l = (b_m + b_l) w_out + (C_m + C_l) sign(w_out),  i = clip(g V)

    0 when the drive cannot break away.  ``load_Nm`` is a constant external torque.
    """
    d, a = cfg.drivetrain, cfg.amplifier
    i = max(-a.current_limit_A, min(a.current_limit_A, a.gain_A_per_V * volts))
    drive = d.gear_ratio * a.torque_constant_Nm_per_A * i + load_Nm
    coulomb = d.coulomb_motor + d.coulomb_load
    if abs(drive) <= coulomb:
        return 0.0
    return d.gear_ratio * (drive - math.copysign(coulomb, drive)) / (d.b_motor + d.b_load)


def steady_state_volts(cfg: PlantConfig, motor_velocity: float, load_Nm: float = 0.0) -> float:
    """The amplifier input that holds ``motor_velocity`` (rad/s) in steady state.

    The inverse of :func:`steady_state_motor_velocity` (ignoring the current limit).
    """
    d, a = cfg.drivetrain, cfg.amplifier
    w_out = motor_velocity / d.gear_ratio
    coulomb = (d.coulomb_motor + d.coulomb_load) * (
        math.copysign(1.0, w_out) if w_out != 0 else 0.0
    )
    torque = (d.b_motor + d.b_load) * w_out + coulomb - load_Nm
    return torque / (d.gear_ratio * a.torque_constant_Nm_per_A * a.gain_A_per_V)


def continuous_model(cfg: PlantConfig) -> tuple[np.ndarray, np.ndarray]:
    """Linear part of amplifier + [Vertechy] Eq. 1 as ``dz/dt = A z + B u``.

    State ``z = [d, w_m, w_l, i, q_l]`` with the flexspline twist ``d = q_m - q_l``
    (output-referred), reduced motor velocity ``w_m = dq_m/dt``, load velocity ``w_l``,
    motor current ``i`` and load angle ``q_l``.  Input ``u = [i_cmd, tau_m_nl, tau_l_nl]``:
    commanded current (A) and the non-linear / external torques on the motor and
    load inertia (Nm at the output).  Viscous friction is in ``A``; Coulomb friction
    and external torques enter through ``tau_*_nl``.  With ``current_lag_s == 0`` the
    current row is zero and ``i_cmd`` drives the motor directly.
    """
    dt_cfg = cfg.drivetrain
    jm, jl = dt_cfg.J_motor, dt_cfg.J_load
    k, c = dt_cfg.k_flex, dt_cfg.c_flex
    a = np.zeros((5, 5))
    b = np.zeros((5, 3))
    # d' = w_m - w_l
    a[0, 1], a[0, 2] = 1.0, -1.0
    # J_m w_m' = N Kt i - b_m w_m - k d - c (w_m - w_l) + tau_m_nl
    a[1, 0] = -k / jm
    a[1, 1] = -(dt_cfg.b_motor + c) / jm
    a[1, 2] = c / jm
    b[1, 1] = 1.0 / jm
    # J_l w_l' = k d + c (w_m - w_l) - b_l w_l + tau_l_nl
    a[2, 0] = k / jl
    a[2, 1] = c / jl
    a[2, 2] = -(dt_cfg.b_load + c) / jl
    b[2, 2] = 1.0 / jl
    # i' = (i_cmd - i) / tau_i
    _current_row(cfg, a, b, row=3)
    # q_l' = w_l
    a[4, 2] = 1.0
    return a, b


def discrete_model(cfg: PlantConfig, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation over ``h`` seconds: ``z+ = Ad z + Bd u``.

    ``expm([[A, B], [0, 0]] h) = [[Ad, Bd], [0, I]]`` (the augmented-matrix trick).
    With an ideal amplifier (no lag) the current after the step is ``i_cmd``.
    """
    return zoh(*continuous_model(cfg), h, current_row=3, ideal_amplifier=has_ideal_amplifier(cfg))


def prescribed_model(cfg: PlantConfig) -> tuple[np.ndarray, np.ndarray]:
    """Motor side of [Vertechy] Eq. 1 against a prescribed link (:class:`LinkMotionConfig`).

    State ``z = [d, w_m, i, s, co]``: twist ``d = q_m - q_l`` (output-referred), reduced
    motor velocity, motor current and the exosystem ``s = sin(w t)``, ``co = cos(w t)``
    that generates the link motion, ``q_l = q_0 + A s``, ``dq_l = A w co``.  Input ``u =
    [i_cmd, tau_m_nl]`` (commanded current, non-linear motor torque at the output)::

        d'   = w_m - A w co
        w_m' = (N Kt i - b_m w_m - k d - c (w_m - A w co) + tau_m_nl) / J_m
        s'   = w co,   co' = -w s

    The exosystem makes the zero-order-hold discretisation exact for the sine (and
    trivially for ``hold``, A = 0).  Current row as in :func:`continuous_model`.
    For ``person`` see :func:`person_model`.
    """
    dt_cfg, link = cfg.drivetrain, cfg.link
    jm, k, c = dt_cfg.J_motor, dt_cfg.k_flex, dt_cfg.c_flex
    a_w = link.amplitude_rad * link.omega_radps  # link velocity amplitude
    a = np.zeros((5, 5))
    b = np.zeros((5, 2))
    a[0, 1], a[0, 4] = 1.0, -a_w
    a[1, 0] = -k / jm
    a[1, 1] = -(dt_cfg.b_motor + c) / jm
    a[1, 4] = c * a_w / jm
    b[1, 1] = 1.0 / jm
    _current_row(cfg, a, b, row=2)
    a[3, 4], a[4, 3] = link.omega_radps, -link.omega_radps
    return a, b


def person_model(cfg: PlantConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`prescribed_model` for a link moved as a sum of sinusoids (``person``).

    State ``z = [d, w_m, i, s_1, c_1, ..., s_n, c_n]`` with ``s_j = sin(w_j t + p_j)``,
    ``c_j = cos(w_j t + p_j)`` and ``dq_l = sum_j a_j w_j c_j``
    (:meth:`LinkMotionConfig.components`); one rotation block per component, so the
    zero-order-hold discretisation is exact for the whole motion.
    """
    dt_cfg = cfg.drivetrain
    jm, k, c = dt_cfg.J_motor, dt_cfg.k_flex, dt_cfg.c_flex
    comps = cfg.link.components()
    n = 3 + 2 * len(comps)
    a = np.zeros((n, n))
    b = np.zeros((n, 2))
    a[0, 1] = 1.0
    a[1, 0] = -k / jm
    a[1, 1] = -(dt_cfg.b_motor + c) / jm
    b[1, 1] = 1.0 / jm
    for j, (amp, w, _p) in enumerate(comps):
        s_j, c_j = 3 + 2 * j, 4 + 2 * j
        a[0, c_j] = -amp * w
        a[1, c_j] = c * amp * w / jm
        a[s_j, c_j], a[c_j, s_j] = w, -w
    _current_row(cfg, a, b, row=2)
    return a, b


def _current_row(cfg: PlantConfig, a: np.ndarray, b: np.ndarray, row: int) -> None:
    """The amplifier in the models above: ``i' = (i_cmd - i) / tau_i`` in state ``row``
    drives the motor velocity (state 1) with ``N Kt / J_m``; with an ideal amplifier
    (``current_lag_s == 0``) that row stays zero and ``i_cmd`` (input 0) drives the motor
    directly."""
    dt_cfg, amp = cfg.drivetrain, cfg.amplifier
    kt_out = dt_cfg.gear_ratio * amp.torque_constant_Nm_per_A  # Nm at the output per A
    if amp.current_lag_s > 0.0:
        a[1, row] = kt_out / dt_cfg.J_motor
        a[row, row] = -1.0 / amp.current_lag_s
        b[row, 0] = 1.0 / amp.current_lag_s
    else:
        b[1, 0] = kt_out / dt_cfg.J_motor


def has_ideal_amplifier(cfg: PlantConfig) -> bool:
    """True without current lag: the current follows its command at once."""
    return cfg.amplifier.current_lag_s == 0.0


def zoh(
    a: np.ndarray, b: np.ndarray, h: float, current_row: int, ideal_amplifier: bool
) -> tuple[np.ndarray, np.ndarray]:
    """``expm([[A, B], [0, 0]] h) = [[Ad, Bd], [0, I]]``; with an ideal amplifier the
    current after the step is ``i_cmd`` (input 0)."""
    n, m = b.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = a
    aug[:n, n:] = b
    e = expm(aug * h)
    ad, bd = e[:n, :n].copy(), e[:n, n:].copy()
    if ideal_amplifier:
        ad[current_row, :] = 0.0
        bd[current_row, :] = 0.0
        bd[current_row, 0] = 1.0
    return ad, bd
