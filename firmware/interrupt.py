"""The seam between the controller node and its interrupt handler: what
:class:`firmware.controller.ControllerNode` needs from the 1 kHz interrupt body.

The controller node is the CANopen side (NMT master, the CiA 402 walk, SYNC, PDOs, SDO
parameters, EMCY); the interrupt handler is the algorithm.  On every sensor frame in
operation the node decodes the drive's counts into an :class:`AdcSample` (in the CiA 402
cyclic synchronous torque mapping, a :class:`CstSample`), calls the handler once, and
sends the :class:`IsrOutput`'s DAC code to the drive and its torques and velocity as
telemetry.  Anything with the members of :class:`InterruptHandlerModel` can be that
handler: the port of [Taghirad97] listing A.1 (:class:`firmware.isr.InterruptHandler`)
or a law of your own, handed over with ``ControllerNode(..., isr=handler)`` or through a
controller factory (:mod:`hdhil.rig.factories`).  With another handler the node keeps
its CANopen behaviour but leaves out what belongs to the firmware's own stages (the
plausibility EMCYs, the stage parameters over SDO, which refuse writes with 0x08000022).
The handler never sees ground truth.

:data:`StageHook` is the other seam here: a callable the firmware's handler calls at
each stage boundary of an interrupt, so a host can time the stages (``hdhil run
--realtime``) without touching the handler's code.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable

__all__ = ["AdcSample", "CstSample", "InterruptHandlerModel", "IsrOutput", "StageHook"]


class AdcSample(NamedTuple):
    """Raw counts from the drive's sensor frame (listing ``DT1401Read`` channels
    CH6 torque bridge, CH4 tachometer, CH5 motor current monitor, and the quadrature
    decoder's 16-bit wrapping pulse count ``pcsample``).

    An immutable named tuple (not a dataclass): the controller makes one per sample, and
    from a decoded sensor frame whose signals are in this order it is the decoded tuple
    itself, retyped (``tuple.__new__(AdcSample, values)``)."""

    torque: int
    tacho: int
    current: int
    encoder: int


class CstSample(NamedTuple):
    """The drive's sensor frame in the CiA 402 cyclic synchronous torque mapping:
    torque actual value 0x6077 (per mille of the drive's rated torque 0x6076) and
    position actual value 0x6064 (encoder increments, 32 bits), and when the mapping
    carries it the joint-torque sensor 0x2102 (mV of the strain-gauge bridge's amplified
    output; None when not mapped).  The handler's sensor source
    (:class:`firmware.stages.CstSource`) turns them into torque, angle and velocity.  An
    immutable named tuple, as :class:`AdcSample`."""

    torque_actual: int
    position: int
    joint_torque_mV: int | None = None


@dataclass(slots=True)
class IsrOutput:
    """What one interrupt produced.

    ``samplecount`` is the index k of the sample this output belongs to (the listing's
    ``samplecount`` before its ``++``); ``reference_V`` is the reference at k and
    ``dac_counts`` its DAC code.  ``ripple`` is the ripple subtracted at k, so
    ``T_filtered = T_meas - ripple`` exactly: in paper mode the prediction the Kalman
    filter made at k − 1 (listing ``T_ripple``), in recommended mode the learned ripple
    map at the angle measured at k.  ``encoder`` is the pulse count masked to 16 bits
    (listing ``pcsample &= 0x0000ffff``), so in 0..65535.  Units: Nm, rad/s, A, rad/s².

    Torque control ([Vertechy], only with a control law; 0 otherwise), all in the product
    convention (:mod:`firmware.isr`): ``tau_s_hat`` / ``dtau_s_hat`` the observer's
    sensor torque and its derivative (Nm, Nm/s), ``tau_lgd_hat`` the exogenous torque
    ``τlgd = τl + τg − τd Jl/Jm`` (Nm), ``tau_sD`` / ``dtau_sD`` the desired torque and
    its derivative, ``e_hat = tau_s_hat − tau_sD``, ``tau_m_request`` the law's motor
    torque (Nm, output-referred) and ``tau_m_cmd`` the torque the DAC code stands for
    (after the torque limit, the DAC range and quantisation), ``saturated`` whether
    the two differ by more than half a DAC step.  ``reference_V`` is then the DAC
    voltage before quantisation.  ``tau_d_hat`` is the motor-friction model's torque
    of Eq. 5 (0 without compensation); with it ``tau_lgd_hat`` is ``τ̂lg``.
    """

    samplecount: int = 0
    dac_counts: int = 0
    reference_V: float = 0.0
    T_meas: float = 0.0
    velocity: float = 0.0
    current: float = 0.0
    acceleration: float = 0.0
    T_expected: float = 0.0
    delta_T: float = 0.0
    T_filtered: float = 0.0
    ripple: float = 0.0
    encoder: int = 0
    tau_s_hat: float = 0.0
    dtau_s_hat: float = 0.0
    tau_lgd_hat: float = 0.0
    tau_sD: float = 0.0
    dtau_sD: float = 0.0
    e_hat: float = 0.0
    tau_m_request: float = 0.0
    tau_m_cmd: float = 0.0
    saturated: bool = False
    tau_d_hat: float = 0.0


@runtime_checkable
class InterruptHandlerModel(Protocol):
    """What the controller node needs from its interrupt handler (module docstring)."""

    @property
    def samplecount(self) -> int:
        """Samples handled so far: the index of the next (listing ``samplecount``)."""
        ...

    @property
    def done(self) -> bool:
        """True once the handler wants no more samples (the node then walks the drive
        back); False to run until stopped."""
        ...

    @property
    def shutdown_dac_counts(self) -> int:
        """The DAC code to send outside operation (start-up, stop): zero torque."""
        ...

    def __call__(self, sample: AdcSample | CstSample) -> IsrOutput:
        """One sample period: the drive's sensor counts (or, in the CiA 402 CST mapping,
        its torque actual and position actual values) in, the command and telemetry out.
        The node reads the output before the next call, so it may be one reused object."""
        ...

    def sample_missed(self) -> None:
        """A sample period passed without a sensor frame (it was lost on the bus)."""
        ...


#: Called by the handler with ``i`` at the boundaries of an interrupt's stages: 0 when
#: it starts, then ``i`` when stage ``i`` (1-based, the firmware's
#: :data:`firmware.isr.STAGES` order) ends. The stages are contiguous, so the times
#: between successive calls add up to the whole interrupt.
StageHook = Callable[[int], None]
