"""Which plants the stepper integrates at a given step, and what happens when one fails.

:class:`~hdhil.hostsim.plant.model.Plant` advances in sub-steps of ``h = dt / substeps``
(``dt`` the run's sample period): the linear part (current lag, both inertias, the
flexspline's spring and damper, viscous friction; a prescribed link's exosystem) by its
exact zero-order-hold map ``expm([[A, B], [0, 0]] h)`` (:func:`.linear.zoh`), the
non-linear terms (Coulomb friction, gravity, the load profile) held over the sub-step at
their values at its start.  The limits follow from that integrator, not from a generic
rule such as ``omega h < 2`` (an explicit scheme's):

* **The exact map is stable for any stiffness.**  Every eigenvalue ``lambda`` of the
  mechanical ``A`` has ``Re(lambda) <= 0`` (springs, dampers and inertias are passive),
  so ``|exp(lambda h)| <= 1`` at any ``h``: no natural frequency ``omega_n =
  sqrt(k (1/J_m + 1/J_l))`` is too high for the step in exact arithmetic.  What limits
  it is the floating-point computation of the exponential: scaling and squaring (Al-Mohy
  and Higham 2009, :mod:`hdhil.core.expm`) evaluates a Padé approximant of ``A h / 2^s``
  with ``2^s ≈ ||A h|| / 5.4`` and squares it ``s`` times; each squaring adds a rounding
  error of the order of the unit roundoff ``u = 1.1e-16`` times the map's size, so the
  computed map is off by about ``u ||A h||``.  A mode of the exact map on the unit circle
  (a joint without viscous friction turning freely) then grows by up to
  ``1 + u ||A h|| / 5.4`` per sub-step.  :data:`MAX_RATE_STEP` bounds every rate of
  ``A`` times ``h`` at ``1e5``: an error of at most 2e-12 per sub-step, a growth below
  a factor 1.3 over the 1.3e11 sub-steps of the longest run hdhil accepts (a year of
  1 ms periods, 4 sub-steps each).  Far beyond the bound the computed map does lose its
  stability: ``k_flex = 3e38`` with the default inertias at 0.25 ms (a rate times step
  near 3e16) gives a map of spectral radius 1.7, whose state overflows within a few
  hundred sub-steps.  The rates:
  the undamped joint mode ``omega_n`` (key ``k_flex``), the damper and viscous
  friction ``c (1/J_m + 1/J_l)``, ``b_motor / J_motor``, ``b_load / J_load`` (keys
  ``c_flex``, ``b_motor``, ``b_load``), the current loop ``1 / current_lag_s`` and a
  prescribed sine's ``2 pi frequency_Hz``; the input columns of the augmented matrix
  scale its argument too, which bounds the inertias from below (``1 / J`` per Nm of
  torque, ``N Kt / J_motor`` per A of current).
* **The held Coulomb friction has an explicit scheme's bound.**  Near standstill
  ``-C tanh(w / eps)`` is a viscous friction of slope ``C / eps``; held over a sub-step
  it acts like an explicit Euler step, ``w+ = (1 - h C / (eps J)) w`` on the side it
  brakes (``J`` that side's inertia; viscous friction and the spring only help, see
  :func:`check_step`), stable only for ``h C / (eps J) <= 2``.  Beyond it standstill is
  no longer a rest point: the friction flips sign every sub-step and the velocity
  chatters around zero.  Hence ``friction_smoothing >= h C / (2 J)``, for the motor
  (``coulomb_motor`` on ``J_motor``) and the load (``coulomb_load`` on ``J_load``); more
  sub-steps (``plant.substeps``) lower the bound.  Gravity and the load profile are
  bounded torques held over a sub-step: they cannot make the state overflow.

A state that still becomes non-finite (a load torque past what the inertias can take in
a float, say) is :class:`NonFiniteStateError`, raised by :meth:`Plant.advance` with the
state left at its last finite value; the drive node turns it into a fault and the run
stops with a verdict.
"""

from __future__ import annotations

import math

from hdhil.hostsim.plant.config import TWO_PI, PlantConfig

__all__ = [
    "MAX_HELD_SLOPE_STEP",
    "MAX_RATE_STEP",
    "NonFiniteStateError",
    "check_step",
    "step_problems",
]

#: Largest rate of the plant's linear model (1/s) times the sub-step (s) whose exact map
#: is computed (module docstring: rounding of the scaling and squaring).
MAX_RATE_STEP = 1e5
#: Largest ``h C / (eps J)`` of a Coulomb friction held over a sub-step (module
#: docstring: an explicit Euler step of the friction's slope is stable up to 2).
MAX_HELD_SLOPE_STEP = 2.0


class NonFiniteStateError(ArithmeticError):
    """The plant's state became non-finite during a step: ``time_s`` the end of the
    step, ``states`` the names of the state variables that did."""

    def __init__(self, time_s: float, states: tuple[str, ...]) -> None:
        self.time_s = time_s
        self.states = states
        super().__init__(
            f"the plant's state went non-finite at t = {time_s:.6g} s "
            f"({', '.join(states)}): its dynamics could not be integrated"
        )


def _g(x: float) -> str:
    return f"{x:.3g}"


def step_problems(cfg: PlantConfig, dt: float) -> list[str]:
    """Every reason the stepper cannot integrate ``cfg`` in steps of ``dt`` seconds
    (sub-steps of ``dt / cfg.substeps``), each naming its key and its limit; empty when
    it can.  The limits and their reasons: the module docstring."""
    h = dt / cfg.substeps
    where = f"at a sub-step of {_g(h)} s (sample period / plant.substeps {cfg.substeps})"
    rate_max = MAX_RATE_STEP / h
    d = cfg.drivetrain
    inv_j = 1.0 / d.J_motor + 1.0 / d.J_load
    out: list[str] = []
    omega = math.sqrt(d.k_flex * inv_j)
    if omega > rate_max:
        out.append(
            f"plant.drivetrain.k_flex = {_g(d.k_flex)} puts the joint mode at {_g(omega)} "
            f"rad/s, above the {_g(rate_max)} rad/s the step map is computed for {where}: "
            f"k_flex must be <= {_g(rate_max**2 / inv_j)} with these inertias"
        )
    for key, value, rate, limit in (
        ("c_flex", d.c_flex, d.c_flex * inv_j, rate_max / inv_j),
        ("b_motor", d.b_motor, d.b_motor / d.J_motor, rate_max * d.J_motor),
        ("b_load", d.b_load, d.b_load / d.J_load, rate_max * d.J_load),
    ):
        if rate > rate_max:
            out.append(
                f"plant.drivetrain.{key} = {_g(value)} damps at {_g(rate)} 1/s, above the "
                f"{_g(rate_max)} 1/s the step map is computed for {where}: {key} must be "
                f"<= {_g(limit)} with these inertias"
            )
    # the inputs' columns of the augmented matrix: h / J per Nm (and N Kt h / J_motor
    # per A of current) scale the exponential's argument like the rates do
    kt_out = d.gear_ratio * cfg.amplifier.torque_constant_Nm_per_A
    for key, inertia, gain in (("J_motor", d.J_motor, max(1.0, kt_out)), ("J_load", d.J_load, 1.0)):
        if gain / inertia > rate_max:
            out.append(
                f"plant.drivetrain.{key} = {_g(inertia)} kg m² is below the "
                f"{_g(gain / rate_max)} kg m² the step map is computed for {where}"
            )
    lag = cfg.amplifier.current_lag_s
    if 0.0 < lag < 1.0 / rate_max:
        out.append(
            f"plant.amplifier.current_lag_s = {_g(lag)} is faster than the step map is "
            f"computed for {where}: it must be 0 (an ideal amplifier) or >= {_g(1.0 / rate_max)}"
        )
    link = cfg.link
    if link.kind == "sine" and TWO_PI * link.frequency_Hz > rate_max:
        out.append(
            f"plant.link.frequency_Hz = {_g(link.frequency_Hz)} is above the "
            f"{_g(rate_max / TWO_PI)} Hz the step map is computed for {where}"
        )
    eps = d.friction_smoothing
    for side, coulomb, inertia in (
        ("motor", d.coulomb_motor, d.J_motor),
        ("load", d.coulomb_load, d.J_load),
    ):
        if side == "load" and link.active:
            continue  # the prescribed link's friction does not enter its motion
        slope_step = h * coulomb / (eps * inertia)
        if slope_step > MAX_HELD_SLOPE_STEP:
            eps_min = h * coulomb / (MAX_HELD_SLOPE_STEP * inertia)
            need = math.ceil(cfg.substeps * slope_step / MAX_HELD_SLOPE_STEP)
            out.append(
                f"plant.drivetrain.friction_smoothing = {_g(eps)} makes coulomb_{side} "
                f"{_g(coulomb)} Nm on J_{side} {_g(inertia)} kg m² chatter {where}: "
                f"friction_smoothing must be >= {_g(eps_min)}"
                + (f" (or plant.substeps >= {need})" if need <= 10_000 else "")
            )
    return out


def check_step(cfg: PlantConfig, dt: float) -> None:
    """Raise ``ValueError`` with the first of :func:`step_problems`, one line, if the
    stepper cannot integrate ``cfg`` in steps of ``dt`` seconds.

    The held-friction bound is checked per side with that side's own inertia: the
    spring can only add the other side's inertia to the braked one (a stiff joint
    moves as one body, ``J_motor + J_load``), and viscous friction only shrinks the
    velocity change, so the bound is sufficient for the coupled joint too."""
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
        raise ValueError(f"the step must be a finite number of seconds > 0, got {dt!r}")
    problems = step_problems(cfg, dt)
    if problems:
        raise ValueError(problems[0])
