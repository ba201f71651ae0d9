"""The pure stages of the 1 kHz interrupt handler ``c_int10`` ([Taghirad97], listing A.1).

Source: [Taghirad97], Appendix A.1 ``free_kalman.c``.
Each function or class of this package ports one line (or one helper function) of
``c_int10``; none touches a bus, a clock or any global state.  The torque-ripple Kalman
filter is in :mod:`firmware.ripple`, the sequencing of the stages in :mod:`firmware.isr`.

The modules, in the order the handler runs them: :mod:`.sources` (sensor frame to
calibrated values, on :mod:`.conversion`'s ADC read and calibration),
:mod:`.plausibility` and :mod:`.stuck` (implausible samples, stuck channels),
:mod:`.motion` (differentiator, encoder unwrap), :mod:`.torque` (expected and filtered
torque), :mod:`.reference` (reference generator) and :mod:`.conversion` again (DAC
write).  Import the stages from this package: its names are the public interface.

The listing computes in 32-bit ``float`` on a TMS320C30; the port uses Python floats
(IEEE double), so results agree with the listing to single precision, not bit for bit.
"""

from __future__ import annotations

from hdhil.firmware.stages.conversion import (
    adc_read,
    calibrate,
    dac_write,
    torque_command_per_mille,
)
from hdhil.firmware.stages.motion import (
    Differentiator,
    EncoderUnwrap,
    LowPass,
    VelocityIntegrator,
    tustin_differentiator,
)
from hdhil.firmware.stages.plausibility import SensorPlausibility
from hdhil.firmware.stages.reference import ReferenceGenerator, SpeedLoop
from hdhil.firmware.stages.sources import AdcSource, CstSource
from hdhil.firmware.stages.stuck import StuckChannels
from hdhil.firmware.stages.torque import expected_torque, filtered_torque, torque_error

__all__ = [
    "AdcSource",
    "CstSource",
    "Differentiator",
    "EncoderUnwrap",
    "LowPass",
    "ReferenceGenerator",
    "SensorPlausibility",
    "SpeedLoop",
    "StuckChannels",
    "VelocityIntegrator",
    "adc_read",
    "calibrate",
    "dac_write",
    "expected_torque",
    "filtered_torque",
    "torque_command_per_mille",
    "torque_error",
    "tustin_differentiator",
]
