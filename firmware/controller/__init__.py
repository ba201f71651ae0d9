"""The controller node: the firmware's interrupt handler behind a CANopen link.

:class:`ControllerNode` (:mod:`.node`) is made of small parts, one module each: the link
phases (:mod:`.phases`), the diagnostics (:mod:`.diagnostics`), the PDO codecs
(:mod:`.codecs`), the object dictionary and live parameters (:mod:`.objects`), the boot
and stop sequencer (:mod:`.sequencer`), the cyclic I/O of the 1 kHz path with its probe
seam (:mod:`.cyclic`) and the supervision (:mod:`.supervision`).  This module only moves
frames and sequences the link: every computation is in :mod:`hdhil.firmware.isr` and its
stages.
"""

from hdhil.firmware.controller.cyclic import CycleProbe
from hdhil.firmware.controller.diagnostics import ControllerDiagnostics
from hdhil.firmware.controller.node import ControllerNode
from hdhil.firmware.controller.phases import Phase, PhaseChange
from hdhil.firmware.parameters import PARAMETERS, Parameter
from hdhil.firmware.walk import CONTROLWORD_ENABLE_OPERATION

__all__ = [
    "CONTROLWORD_ENABLE_OPERATION",
    "PARAMETERS",
    "ControllerDiagnostics",
    "ControllerNode",
    "CycleProbe",
    "Parameter",
    "Phase",
    "PhaseChange",
]
