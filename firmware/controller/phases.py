"""The controller's link phases, their history and the sets the per-cycle code tests.

One enum for the whole node: the boot sequencer, the cyclic I/O and the supervision each
change or read the phase (:class:`hdhil.firmware.controller.ControllerNode`), and the
runner ends a run on its final phases.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

__all__ = ["COMMANDING", "FINAL", "Phase", "PhaseChange", "seconds"]


class Phase(str, enum.Enum):
    """The controller's link phase (a ``str`` enum: ``node.phase == "operational"`` works).

    ============  ==================================================  ======  ============
    phase         what happens                                        SYNC    DRIVE_RPDO1
    ============  ==================================================  ======  ============
    wait-boot     PRE-OPERATIONAL, waiting for the drive's boot-up    yes     no
    starting      drive NMT-started, CiA 402 walk (controlword)       yes     DAC 0 + cw
    operational   the interrupt handler runs on every sensor frame    yes     DAC + 0x000F
    stopping      CiA 402 walk back (0x0007, then 0x0006)             yes     DAC 0 + cw
    stopped       drive sent to PRE-OPERATIONAL, controller too       no      no
    safe          fault: the drive is no longer commanded             no      no
    ============  ==================================================  ======  ============

    "stopped" and "safe" are final: SDO and heartbeat keep running, but **recovery is a
    restart** (a new node and ``boot``).  Heartbeats and the SDO server run in every phase.
    """

    WAIT_BOOT = "wait-boot"
    STARTING = "starting"
    OPERATIONAL = "operational"
    STOPPING = "stopping"
    STOPPED = "stopped"
    SAFE = "safe"

    def __str__(self) -> str:
        return self.value


#: Phases in which the controller commands the drive (sends DRIVE_RPDO1).
COMMANDING = frozenset({Phase.STARTING, Phase.OPERATIONAL, Phase.STOPPING})
#: Final phases: no SYNC, no PDO; only a restart leaves them.
FINAL = frozenset({Phase.STOPPED, Phase.SAFE})


class PhaseChange(NamedTuple):
    """One entry of the phase history: when (the latest ``tick``/``boot`` time, s), the
    new phase and why."""

    time_s: float
    phase: Phase
    reason: str


def seconds(t: float) -> str:
    """2.0 -> "2.0", 0.25 -> "0.25" (as a user would write the timeout)."""
    return f"{t:.1f}" if round(t, 1) == t else f"{t:g}"
