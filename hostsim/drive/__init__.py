"""The drive node: the plant emulator behind a CiA 301 / CiA 402 CANopen device.

One job per module: :mod:`.node` (:class:`DriveNode`: NMT, heartbeat, EMCY, the CiA 402
objects, and the wiring of the parts below), :mod:`.cyclic` (PDOs, commands in, sensors
out, the plant stepped once per SYNC), :mod:`.cst` (the CiA 402 cyclic synchronous torque
objects), :mod:`.emulator` (objects 0x2300 and 0x2310: retuning and faulting the
emulated plant at run time), :mod:`.truth_channel` (ground truth on the truth bus) and
:mod:`.config` (settings and diagnostics). Every public name is importable from here,
as ``from hdhil.hostsim.drive import DriveNode``.
"""

from hdhil.hostsim.drive.config import DriveConfig, DriveDiagnostics, EmcyRecord
from hdhil.hostsim.drive.cyclic import (
    ADC_CHANNELS,
    OD_ADC_COUNTS,
    OD_DAC_COMMAND,
    OD_ENCODER,
    OD_SYNC_PERIOD,
    OD_SYNC_WINDOW,
)
from hdhil.hostsim.drive.emulator import (
    EMULATOR_KNOBS,
    FAULT_FIELDS,
    FAULT_MASKS,
    FAULT_SILENCE_MS,
    MASK_CHANNELS,
    OD_EMULATOR,
    OD_FAULTS,
)
from hdhil.hostsim.drive.node import (
    OD_ABORT_CONNECTION,
    OD_ERROR_CODE,
    OD_FAULT_REACTION_OPTION,
    OD_MODES_DISPLAY,
    OD_MODES_OF_OPERATION,
    OD_QUICK_STOP_OPTION,
    DriveNode,
)

__all__ = [
    "ADC_CHANNELS",
    "EMULATOR_KNOBS",
    "FAULT_FIELDS",
    "FAULT_MASKS",
    "FAULT_SILENCE_MS",
    "MASK_CHANNELS",
    "OD_ABORT_CONNECTION",
    "OD_ADC_COUNTS",
    "OD_DAC_COMMAND",
    "OD_EMULATOR",
    "OD_ENCODER",
    "OD_ERROR_CODE",
    "OD_FAULTS",
    "OD_FAULT_REACTION_OPTION",
    "OD_MODES_DISPLAY",
    "OD_MODES_OF_OPERATION",
    "OD_QUICK_STOP_OPTION",
    "OD_SYNC_PERIOD",
    "OD_SYNC_WINDOW",
    "DriveConfig",
    "DriveDiagnostics",
    "DriveNode",
    "EmcyRecord",
]
