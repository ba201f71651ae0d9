"""The plant's ground truth: one record of what ideal, noise-free sensors would read.

A plant returns a :class:`Truth` from ``truth()``; the drive publishes its first ten
fields on the truth channel (``truth.dbc``), which the firmware never reads, and the
scorer compares the firmware's estimates with them. One immutable record, read in one
call: the values belong to one instant, a plant of one's own fills in what it models and
leaves the rest at the defaults, and a test sees the whole state at once.
"""

from __future__ import annotations

import math
from typing import NamedTuple

__all__ = ["RippleParts", "Truth"]

_NAN = math.nan


class RippleParts(NamedTuple):
    """The parts of the torque sensor's ripple ``T_ripple_Nm`` (Nm; they sum to it)."""

    mesh: float  #: gear meshing, 2x and 4x motor angle (RippleConfig)
    misalignment: float  #: side load at the output angle (RippleConfig)
    modulation: float  #: wave-generator residual of the bridge at 2 beta (BridgeConfig)
    nonlinearity: float  #: cubic gauge nonlinearity (BridgeConfig)
    hysteresis: float  #: gauge hysteresis (BridgeConfig)


class Truth(NamedTuple):
    """The plant's state at its present time, in SI units at the output unless a name
    says motor.

    Signs: angles, velocities and torques are positive forward on both shafts; positive
    amplifier voltage gives positive current, motor torque and rotation. Torques are
    reduced to the output shaft as in [Vertechy] Eq. 1 (``q_m = theta_motor / N``); the
    flexspline torque ``k (q_m - q_l) + c (dq_m - dq_l)`` is positive when the motor
    drives the load forward, the opposite sign of [Vertechy]'s sensor torque ``tau_s =
    k (theta_l - theta_m)``. External torques keep [Vertechy]'s signs.

    The torque sensor reads ``V = (T_true_Nm + T_ripple_Nm) / volt2Nm_true + offset +
    noise``: ``T_true_Nm + T_ripple_Nm`` is the noise- and offset-free reading of a
    perfectly calibrated firmware, ``T_ripple_Nm`` all the gauges add (mesh ripple,
    misalignment, bridge modulation, gauge nonlinearity and hysteresis; ``ripple``
    splits it up). A firmware with another gain than the sensor's true one
    (``BridgeConfig.volt2Nm``) reads ``(T_true_Nm + T_ripple_Nm)`` times the ratio of
    the gains: that is its calibration error, not ripple.

    The first seven fields are required, the next three default to 0 (a plant without
    ripple, environment or motor friction); the rest is the emulator's own breakdown,
    NaN (or None) where a plant does not model it.
    """

    #: The torque an ideal torque sensor reads (Nm): the flexspline torque, or with
    #: ``SensorConfig.torque_measures = "spring"`` the spring torque (``-tau_s``).
    T_true_Nm: float
    #: Motor (wave generator) angle at the motor shaft, unwrapped (rad); the truth
    #: channel carries it wrapped to [0, 2 pi).
    theta_motor_rad: float
    #: Output (link) angle, unwrapped (rad); wrapped on the truth channel.
    theta_output_rad: float
    #: Motor velocity at the motor shaft (rad/s): what the tachometer sees.
    omega_motor_radps: float
    #: Output velocity (rad/s).
    omega_output_radps: float
    #: Motor torque acting now, ``tau_m`` of [Vertechy] Eq. 1 (Nm): ``N Kt i``, after
    #: the amplifier's current lag and limit.
    tau_m_Nm: float
    #: Motor torque commanded by the amplifier input (Nm): ``N Kt clip(g V)``.
    tau_m_cmd_Nm: float
    #: Everything the torque sensor adds to ``T_true_Nm``, noise and offset aside (Nm).
    T_ripple_Nm: float = 0.0
    #: All torque on the link except the joint's, ``tau_l + tau_g`` of [Vertechy]
    #: (Nm): ``J_l ddtheta_l - T_transmitted``; the output bearings' friction counts in,
    #: so it is the torque the joint's observer estimates, and not the handle torque
    #: (``tau_l_Nm``) when the bearings have friction (``load_friction_Nm``).
    tau_ext_Nm: float = 0.0
    #: Every torque on the motor inertia except ``tau_m`` and the joint's, ``tau_d`` of
    #: [Vertechy] Eq. 1 (Nm): the motor friction.
    tau_d_Nm: float = 0.0
    #: Flexspline torque ``k (q_m - q_l) + c (dq_m - dq_l)`` (Nm).
    T_transmitted_Nm: float = _NAN
    #: Spring torque ``k (q_m - q_l)`` (Nm): ``-tau_s`` of [Vertechy] §II.
    T_spring_Nm: float = _NAN
    #: Motor current (A).
    current_A: float = _NAN
    #: ``tau_l`` (Nm): the torque the environment applies to the link. A free link: the
    #: load torque (held value plus profile); a prescribed motion: what imposing it takes
    #: at the handle, what a sensor in the handle measures ([Vertechy]'s ``τl^m``):
    #: ``tau_ext_Nm - tau_g_Nm - load_friction_Nm``.
    tau_l_Nm: float = _NAN
    #: ``tau_g`` (Nm): gravity on the link (GravityConfig).
    tau_g_Nm: float = _NAN
    #: The output bearings' friction on the link (Nm): the drive train's load friction,
    #: and with a prescribed motion the link's ``bearing_coulomb_Nm``; not in
    #: [Vertechy]; part of ``tau_ext_Nm``, not of ``tau_l_Nm``.
    load_friction_Nm: float = _NAN
    #: Link angular acceleration (rad/s²).
    link_acceleration_radps2: float = _NAN
    #: ``T_ripple_Nm`` by origin.
    ripple: RippleParts | None = None

    @property
    def beta_rad(self) -> float:
        """Angle of the wave generator relative to the gauges (rad, unwrapped).

        ``theta_motor + theta_output``: the gauges sit on the flexspline, which carries
        the output and, in a cup-type harmonic drive with the circular spline fixed
        ([Taghirad97] §1), turns against the wave generator at 1/N of its speed (the
        plant's sign convention hides that reversal). The bridge's residual modulation
        is at ``2 beta`` ([Taghirad97] §2, Eqs. 2-3).
        """
        return self.theta_motor_rad + self.theta_output_rad
