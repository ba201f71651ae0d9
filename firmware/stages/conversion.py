"""The stages at the ends of ``c_int10`` ([Taghirad97], listing A.1): ADC read, calibration,
DAC write, and the CiA 402 torque command that replaces the DAC write.

``adc_read`` and ``calibrate`` turn the drive's counts into volts and physical units
(``DT1401Read``, ``vel = Tacho * volt2radps``, ``T_meas = Torque * volt2Nm``);
``dac_write`` quantises the amplifier voltage (``write_dac0``); in the cyclic
synchronous torque mapping ``torque_command_per_mille`` turns that voltage into target
torque 0x6071.  All are pure functions of their arguments.
"""

from __future__ import annotations

import math

from hdhil.core.converter import Converter
from hdhil.firmware.config import Calibration

__all__ = [
    "adc_read",
    "calibrate",
    "dac_write",
    "torque_command_per_mille",
]


def adc_read(torque: int, tacho: int, current: int, adc: Converter) -> tuple[float, float, float]:
    """ADC counts to volts: ``(torque_V, tacho_V, current_V)``.

    Ports ``DT1401Read(str_ch, end_ch, a2dsamples)`` and the channel picks
    ``Tacho = a2dsamples[DT140X_CH4]; MotorCurrOut = a2dsamples[DT140X_CH5];
    Torque = a2dsamples[DT140X_CH6]`` ([Taghirad97], listing A.1, ``c_int10``).  On the
    DT1401 the driver returns volts; on our CAN link the drive sends counts, which
    ``adc`` (12 bit, +/-10 V) turns back into volts.
    """
    return adc.to_volts(torque), adc.to_volts(tacho), adc.to_volts(current)


def calibrate(
    torque_V: float, tacho_V: float, current_V: float, cal: Calibration
) -> tuple[float, float, float]:
    """Volts to physical units: ``(T_meas [Nm], vel [rad/s], current [A])``.

    Ports ``vel = Tacho * volt2radps`` and ``T_meas = Torque * volt2Nm`` ([Taghirad97],
    listing A.1, ``c_int10``; gains 56.2565 rad/s/V and 6.6 Nm/V, Table 1).  The
    torque offset is subtracted before scaling (not in the listing).  The listing
    logs ``MotorCurrOut`` in volts; ``cal.volt2amp`` (default 1) scales it to amperes.
    """
    T_meas = (torque_V - cal.torque_offset_V) * cal.volt2Nm
    vel = tacho_V * cal.volt2radps
    current = current_V * cal.volt2amp
    return T_meas, vel, current


def dac_write(volts: float, dac: Converter) -> int:
    """The DAC code for a voltage: quantize (nearest) and saturate.

    Ports ``write_dac0(ref_fl)`` ([Taghirad97], listing A.1, ``c_int10``; "floatV for
    MAX-100 servo").  On our link the code travels in the command frame; NaN gives 0.
    """
    return dac.to_counts(volts)


def torque_command_per_mille(volts: float, torque_per_volt: float, rated_torque_Nm: float) -> int:
    """The command as CiA 402 target torque 0x6071 (INTEGER16, per mille of 0x6076), in
    place of ``write_dac0`` in the standard mapping: the amplifier voltage the handler
    computed times the actuator calibration ``torque_per_volt`` (output-referred Nm per
    V), over the drive's rated torque, rounded and clamped to INTEGER16."""
    if not math.isfinite(volts):
        return 0
    value = round(volts * torque_per_volt / rated_torque_Nm * 1e3)
    return -32768 if value < -32768 else 32767 if value > 32767 else value
