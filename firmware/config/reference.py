"""Configuration of the reference generator: the wave types and the host mailboxes of
[Taghirad97], listing A.1 ``main()`` (``Nbias``, ``Namplitude``, ``wavetype``, ``freq``,
``duty``).

The generator itself is :class:`firmware.stages.ReferenceGenerator`; the same waves give
[Vertechy]'s desired torque (:class:`firmware.config.DesiredTorqueConfig`).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from hdhil.core.dataconf import check_fields

__all__ = [
    "ReferenceConfig",
    "SpeedLoopConfig",
    "Wave",
]


class Wave(enum.IntEnum):
    """Reference wave types ([Taghirad97], listing A.1: ``int wavetype = 0; /* no wave
    generation by default */`` and ``ref_fl = reference_generation(wavetype)``).

    The listing includes ``servo_refgen.h`` but does not print ``reference_generation``;
    only ``0`` = "no wave" is given.  The numbering of the other types is ours;
    their definitions are in :class:`firmware.stages.ReferenceGenerator`.
    """

    NONE = 0  # constant output: bias only (the listing's default)
    SINE = 1
    SQUARE = 2
    TRIANGLE = 3
    STEP = 4
    SAWTOOTH = 5
    CHIRP = 6  # linear frequency sweep ([Vertechy] Fig. 5: identification by a chirp)


@dataclass(frozen=True)
class ReferenceConfig:
    """The reference generator's host mailboxes ([Taghirad97], listing A.1 ``main()``:
    ``copy(parm_ptr, &Nbias ...)``, ``Namplitude``, ``wavetype``, ``freq``, ``duty``).

    The listing receives ``Nbias`` / ``Namplitude`` as host numbers and converts them
    with ``PC2V_linear_conv``; here they are given directly in volts at the DAC.  Any
    finite value is accepted: the 12-bit, +/-10 V DAC saturates what lies outside.
    The listing's global default ``duty = 1.0`` makes a square wave constant; we use
    0.5 (a symmetric square wave) as default.  The listing's ``freq = 0`` default is
    replaced by 1 Hz because the frequency must be > 0 here.

    Units: ``frequency_Hz`` is in hertz (cycles per second).  The listing declares
    ``float theta = 0, freq = 0; /* Angle and angular frequency of function */``, so its
    ``freq`` mailbox (``parm_ptr+6``) held an angular frequency; its unit is not printed
    (rad/s or rad per sample).  A value ω in rad/s from such a host is ``frequency_Hz =
    ω / 2π``.

    Left out, with the reason: the listing's globals ``theta``, ``rise`` and ``fall``
    (listing A.1, ``float theta = 0 ...; float rise = 0.0; float fall = 0.0;``).  They
    belong to ``reference_generation`` (``servo_refgen.h``), whose body [Taghirad97] does
    not print, and ``main()`` never writes them from the host (it copies ``Nbias``,
    ``sample_period``, ``numsamples``, ``Namplitude``, ``wavetype``, ``freq``, ``duty``
    only), so they keep their initial 0 for every run the listing makes.  ``theta`` is
    the generator's running angle: here the phase ``2π f k Ts`` computed from the sample
    index (no accumulated state to drift).  ``rise = fall = 0`` are zero edge times:
    here every edge (square, step) is instantaneous, which is what those zeros give.

    ``chirp_end_Hz`` and ``chirp_duration_s`` (not in the papers) are for ``wave =
    "chirp"`` only: a linear sweep from ``frequency_Hz`` to ``chirp_end_Hz`` over
    ``chirp_duration_s``, repeated ([Vertechy] Fig. 5: "obtained experimentally by
    commanding tau_m with a chirp function").
    """

    wave: Wave = Wave.NONE
    bias_V: float = 0.0
    amplitude_V: float = 0.0
    frequency_Hz: float = 1.0
    duty: float = 0.5
    step_time_s: float = 0.0
    chirp_end_Hz: float = 10.0
    chirp_duration_s: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.wave, Wave):
            raise ValueError(f"reference.wave must be one of {[w.name.lower() for w in Wave]}")
        check_fields(self, {"bias_V": "finite", "amplitude_V": "finite", "frequency_Hz": ">0"})
        check_fields(self, {"chirp_end_Hz": ">0", "chirp_duration_s": ">0"})
        if not (math.isfinite(self.duty) and 0.0 <= self.duty <= 1.0):
            raise ValueError(f"reference.duty must be within [0, 1], got {self.duty!r}")
        if not (math.isfinite(self.step_time_s) and self.step_time_s >= 0.0):
            raise ValueError(
                f"reference.step_time_s must be a finite number >= 0, got {self.step_time_s!r}"
            )


@dataclass(frozen=True)
class SpeedLoopConfig:
    """A PI loop on the motor speed, added to the reference voltage (not in the papers).

    [Taghirad97]'s free-motion experiment drives the amplifier with a constant voltage
    and the motor settles where its friction balances the torque; on a joint of an arm
    under gravity the same voltage gives no steady speed (a gravity torque change of
    1 Nm moves the balance by 0.59 rad/s at the output, 59 rad/s at the motor, with the
    default drivetrain's 1.7 Nm s/rad), and the arm falls.  The loop holds the motor
    speed the ripple filter needs, from the firmware's own tachometer velocity::

        V(k) = reference(k) + kp (w_ref(k) - vel(k)) + I(k),
        I(k+1) = clip(I(k) + ki Ts (w_ref(k) - vel(k)), -full scale, +full scale)

    with ``w_ref`` 0 before ``start_s`` (the loop holds the joint at rest), rising to
    ``setpoint_radps`` over ``ramp_s`` along a raised cosine, ``w_ref = setpoint (1 -
    cos(pi t / ramp_s)) / 2`` (an acceleration that rises and falls smoothly instead of
    a torque step), and held from then on.  ``kp`` sets the loop's bandwidth, about
    ``kp N² Kt g / J`` rad/s on a joint of inertia ``J`` (output-referred, motor and
    link; ``N`` the gear ratio, ``Kt`` the torque constant, ``g`` the amplifier's A/V),
    which must stay far below the ripple's 2x motor velocity so the loop does not feed
    the ripple back into the torque.  Off (the listing) while ``kp`` and ``ki``
    are 0.
    """

    #: Motor speed set point from ``start_s`` on (rad/s, at the motor, the tachometer's).
    setpoint_radps: float = 0.0
    #: When the set point starts to rise from 0 to ``setpoint_radps`` (s).
    start_s: float = 0.0
    #: How long the set point takes to rise from 0 to ``setpoint_radps`` (s; 0: a step).
    ramp_s: float = 0.0
    #: Proportional gain (V per rad/s of motor speed error).
    kp_V_per_radps: float = 0.0
    #: Integral gain (V per rad of integrated motor speed error).
    ki_V_per_rad: float = 0.0

    def __post_init__(self) -> None:
        check_fields(
            self,
            {"setpoint_radps": "finite", "start_s": ">=0", "ramp_s": ">=0", "kp_V_per_radps": ">=0",
             "ki_V_per_rad": ">=0"},
        )  # fmt: skip

    @property
    def active(self) -> bool:
        """Whether the loop runs (a gain above 0)."""
        return self.kp_V_per_radps > 0.0 or self.ki_V_per_rad > 0.0
