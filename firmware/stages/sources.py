"""Sensor sources: the first stage of the handler, one sensor frame to calibrated values.

``AdcSource`` is the raw mapping, the listing's ``DT1401Read`` and calibration lines
([Taghirad97], listing A.1, ``c_int10``) on the counts of the drive's sensor frame.
``CstSource`` is the CiA 402 cyclic synchronous torque mapping (not in the papers): the
drive's torque and position actual values, the velocity through the listing's
differentiator; with the drive's joint-torque sensor 0x2102 mapped, the torque is the
strain-gauge bridge's, calibrated as the listing calibrates its ADC channel.  Both return
the same tuple, so the stages after them do not know which mapping runs.
"""

from __future__ import annotations

import math
from typing import Any

from hdhil.core.converter import Converter
from hdhil.firmware.config import Calibration
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

    __slots__ = ("_current_gain", "_hi", "_lo", "_lsb", "_offset", "_tacho_gain",
                 "_torque_gain", "adc", "cal")  # fmt: skip

    def __init__(self, adc: Converter, cal: Calibration) -> None:
        self.adc = adc
        self.cal = cal
        # adc_read and calibrate written out in __call__ (five calls fewer per sample,
        # the same arithmetic in the same order, so the same floats; a test compares
        # them over the whole code range): their constants, from the frozen converter
        # and calibration.
        self._lo = adc.code_min
        self._hi = adc.code_max
        self._lsb = adc.lsb_V
        self._offset = cal.torque_offset_V
        self._torque_gain = cal.volt2Nm
        self._tacho_gain = cal.volt2radps
        self._current_gain = cal.volt2amp

    def __call__(self, sample: object) -> tuple[float, float, float, int, float, float]:
        s: Any = sample  # AdcSample
        lo = self._lo
        hi = self._hi
        lsb = self._lsb
        # adc_read: Torque = CH6, Tacho = CH4, MotorCurrOut = CH5, counts to volts
        # (Converter.to_volts: clipped to the code range, times the LSB)
        torque = s.torque
        Torque = (hi if torque > hi else lo if torque < lo else torque) * lsb
        tacho = s.tacho
        Tacho = (hi if tacho > hi else lo if tacho < lo else tacho) * lsb
        current = s.current
        MotorCurrOut = (hi if current > hi else lo if current < lo else current) * lsb
        # calibrate: T_meas = Torque * volt2Nm (offset first); vel = Tacho * volt2radps
        T_meas = (Torque - self._offset) * self._torque_gain
        vel = Tacho * self._tacho_gain
        return T_meas, vel, MotorCurrOut * self._current_gain, s.encoder, Torque, Tacho


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
    - with ``calibration`` (the drive's joint-torque sensor 0x2102 is mapped: the mapping
      "cst-sensor"), ``T_meas`` is the strain-gauge torque instead of 0x6077: the
      sample's ``joint_torque_mV`` in volts, calibrated as :class:`AdcSource` calibrates
      the torque channel (``T_meas = (V - torque_offset_V) * volt2Nm``).  0x6077 is not
      used then.

    Returns the tuple :class:`AdcSource` returns, with ``T_meas`` (without a gauge) or
    the gauge's volts (with one) and ``vel`` in place of the channels in volts.
    """

    name = "cst"  # the same with or without the gauge (``calibration``)

    __slots__ = ("_gauge", "_rad_per_count", "calibration", "differentiator", "primed",
                 "rated_torque_Nm")  # fmt: skip

    def __init__(
        self,
        rated_torque_Nm: float,
        counts_per_rev: int,
        diff_tau_s: float,
        sample_period_s: float,
        calibration: Calibration | None = None,
    ) -> None:
        if not (math.isfinite(rated_torque_Nm) and rated_torque_Nm > 0):
            raise ValueError(f"rated torque must be > 0 Nm, got {rated_torque_Nm!r}")
        self.rated_torque_Nm = rated_torque_Nm
        self._rad_per_count = 2.0 * math.pi / counts_per_rev
        self.differentiator = Differentiator(diff_tau_s, sample_period_s)
        self.primed = False
        #: The torque sensor's calibration when the joint-torque sensor is mapped, else None.
        self.calibration = calibration
        self._gauge = (
            None if calibration is None else (calibration.torque_offset_V, calibration.volt2Nm)
        )

    def __call__(self, sample: object) -> tuple[float, float, float, int, float, float]:
        s: Any = sample  # CstSample
        gauge = self._gauge
        if gauge is None:
            T_meas = Torque = s.torque_actual * 1e-3 * self.rated_torque_Nm
        else:
            Torque = s.joint_torque_mV * 1e-3
            T_meas = (Torque - gauge[0]) * gauge[1]
        angle = s.position * self._rad_per_count
        if not self.primed:
            self.differentiator.reseed(angle)
            self.primed = True
        vel = self.differentiator.step(angle)
        return T_meas, vel, 0.0, s.position & 0xFFFF, Torque, vel

    def reset(self) -> None:
        self.differentiator.reset()
        self.primed = False
