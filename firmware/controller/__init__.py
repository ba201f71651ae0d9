"""The controller node: the firmware's interrupt handlers behind a CANopen link.

:class:`ControllerNode` (:mod:`.node`) is made of small parts, one module each: the link
phases (:mod:`.phases`), the diagnostics (:mod:`.diagnostics`), the PDO codecs
(:mod:`.codecs`), the object dictionary and live parameters (:mod:`.objects`), the boot
and stop sequencer (:mod:`.sequencer`), the cyclic I/O of the 1 kHz path with its probe
seam (:mod:`.cyclic`) and the supervision (:mod:`.supervision`); the sequencer, cyclic
I/O and supervision are one per joint the node serves (:mod:`.joint`), each joint
addressing its drive through its link (:mod:`.link`).  This module only moves
frames and sequences the link: every computation is in :mod:`hdhil.firmware.isr` and its
stages.
"""

from hdhil.firmware.controller.cyclic import CycleProbe
from hdhil.firmware.controller.diagnostics import ControllerDiagnostics
from hdhil.firmware.controller.joint import ControllerJoint, JointSetup
from hdhil.firmware.controller.link import MAX_JOINTS_PER_NODE, DriveLink
from hdhil.firmware.controller.node import ControllerNode
from hdhil.firmware.controller.phases import Phase, PhaseChange
from hdhil.firmware.parameters import PARAMETERS, Parameter
from hdhil.firmware.walk import CONTROLWORD_ENABLE_OPERATION

__all__ = [
    "CONTROLWORD_ENABLE_OPERATION",
    "MAX_JOINTS_PER_NODE",
    "PARAMETERS",
    "ControllerDiagnostics",
    "ControllerJoint",
    "ControllerNode",
    "CycleProbe",
    "DriveLink",
    "JointSetup",
    "Parameter",
    "Phase",
    "PhaseChange",
]
