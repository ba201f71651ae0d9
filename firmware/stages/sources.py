"""Sensor sources: the first stage of the handler, one sensor frame to calibrated values.

``AdcSource`` is the raw mapping, the listing's ``DT1401Read`` and calibration lines
([Taghirad97], listing A.1, ``c_int10``) on the counts of the drive's sensor frame.
``CstSource`` is the CiA 402 cyclic synchronous torque mapping (not in the papers): the
drive's torque and position actual values, the velocity through the listing's
differentiator.  Both return the same tuple, so the stages after them do not know which
mapping runs.
"""

from __future__ import annotations

import math

from hdhil.core.converter import Converter
from hdhil.firmware.config import Calibration
from hdhil.firmware.stages.conversion import adc_read, calibrate
from hdhil.firmware.stages.motion import Differentiator

__all__ = [
    "AdcSource",
    "CstSource",
]


class AdcSource:
    """Sensor source of the raw mapping: the listing's ``DT1401Read`` and the
    calibration lines ([Taghirad97], listing A.1, ``c_int10``: ``Tacho = a2dsamples[CH4];
    MotorCurrOut = a2dsamples[CH5]; Torque = a2dsamples[CH6]; vel = Tacho *
    volt2radps; T_meas = Torque * volt2Nm``), on the counts of the drive's sensor frame
    (:class:`firmware.interrupt.AdcSample`).

    Returns ``(T_meas, vel, current, encoder, torque_V, tacho_V)``: the calibrated
    torque (Nm), motor velocity (rad/s) and current (A), the 16-bit encoder count
    ``pcsample``, and the two channels in volts for the stuck-channel check.
    """

    name = "adc"

    __slots__ = ("adc", "cal")

    def __init__(self, adc: Converter, cal: Calibration) -> None:
        self.adc = adc
        self.cal = cal

    def __call__(self, sample: object) -> tuple[float, float, float, int, float, float]:
        s = sample  # AdcSample
        Torque, Tacho, MotorCurrOut = adc_read(s.torque, s.tacho, s.current, self.adc)  # type: ignore[attr-defined]
        T_meas, vel, current = calibrate(Torque, Tacho, MotorCurrOut, self.cal)
        return T_meas, vel, current, s.encoder, Torque, Tacho  # type: ignore[attr-defined]


class CstSource:
    """Sensor source of the CiA 402 cyclic synchronous torque mapping, in place of the
    ADC read and calibration: the drive's torque actual value 0x6077 and position actual
    value 0x6064 (:class:`firmware.interrupt.CstSample`).  Not in the papers.

    - ``T_meas = 0x6077 * 1e-3 * rated_torque_Nm``: CiA 402 scales 0x6077 in per mille
      of 0x6076 motor rated torque, which the controller reads from the drive by SDO at
      boot (:attr:`rated_torque_Nm`).  It is the torque the amplifier produces (from its
      current), not the strain-gauge bridge: the torque ripple and misalignment the
      gauges see are not in it, and neither is the motor's own inertia and friction
      torque, which the gauges on the flexspline do not see either.
    - motor angle ``phi = 0x6064 * 2 pi / encoder_counts_per_rev``; there is no tacho,
      so ``vel`` is the angle through the firmware's own band-limited differentiator
      (:class:`Differentiator`, listing ``Diff_filter``, ``diff_tau_s``), primed with
      the first angle so the first sample gives no velocity step.
    - the encoder count handed to the ripple filter's phase is ``0x6064 & 0xFFFF``, the
      16 bits the raw mapping carries (``EncoderUnwrap`` unwraps it again).
    - there is no current channel: ``current`` is 0.

    Returns the tuple :class:`AdcSource` returns, with ``T_meas`` and ``vel`` in place
    of the channels in volts.
    """

    name = "cst"

    __slots__ = ("_rad_per_count", "differentiator", "primed", "rated_torque_Nm")

    def __init__(
        self,
        rated_torque_Nm: float,
        counts_per_rev: int,
        diff_tau_s: float,
        sample_period_s: float,
    ) -> None:
        if not (math.isfinite(rated_torque_Nm) and rated_torque_Nm > 0):
            raise ValueError(f"rated torque must be > 0 Nm, got {rated_torque_Nm!r}")
        self.rated_torque_Nm = rated_torque_Nm
        self._rad_per_count = 2.0 * math.pi / counts_per_rev
        self.differentiator = Differentiator(diff_tau_s, sample_period_s)
        self.primed = False

    def __call__(self, sample: object) -> tuple[float, float, float, int, float, float]:
        s = sample  # CstSample
        T_meas = s.torque_actual * 1e-3 * self.rated_torque_Nm  # type: ignore[attr-defined]
        angle = s.position * self._rad_per_count  # type: ignore[attr-defined]
        if not self.primed:
            self.differentiator.reseed(angle)
            self.primed = True
        vel = self.differentiator.step(angle)
        return T_meas, vel, 0.0, s.position & 0xFFFF, T_meas, vel  # type: ignore[attr-defined]

    def reset(self) -> None:
        self.differentiator.reset()
        self.primed = False
