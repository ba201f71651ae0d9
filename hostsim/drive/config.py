"""What the drive node is set to and what it did: its settings and its diagnostics.

:class:`DriveConfig` is how the drive runs the plant against the bus and its CANopen
settings (node-IDs, heartbeat, command hold, SYNC counter, quick-stop ramp), checked when
built; :class:`DriveDiagnostics` counts what the node did (frames, SYNC errors, faults)
and keeps its latest EMCY events, for summaries, verdicts and tests.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

__all__ = ["DriveConfig", "DriveDiagnostics", "EmcyRecord"]


def _check_int(obj: object, name: str, lo: int, hi: int) -> None:
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(
            f"{type(obj).__name__}.{name} must be an integer {lo}..{hi}, got {value!r}"
        )


@dataclass(frozen=True)
class DriveConfig:
    """How the drive node runs the plant against the bus, and its CANopen settings.

    ``heartbeat_ms`` is the producer time (0x1017, 0 = off); the drive consumes the
    heartbeat of ``controller_node_id`` with ``controller_heartbeat_timeout_ms`` (0x1016,
    0 = not monitored).  ``command_hold_cycles`` SYNC cycles without a command in
    OPERATION ENABLED fault the drive (0 = never).  ``sync_overflow`` is the SYNC
    producer's counter overflow (its 0x1019; 0 = SYNC without counter).
    ``quick_stop_time_s`` is the torque ramp-down time of a quick stop (0x605A 1-8) and
    of a fault reaction (0x605E 1-4); 0 turns the torque off at once.
    ``truth_joint_index``: the joint whose ground truth the drive publishes.
    """

    sample_period_s: float = 1e-3
    actuation: Literal["next-sync", "immediate"] = "next-sync"
    node_id: int = 2
    heartbeat_ms: int = 100
    controller_node_id: int = 1
    controller_heartbeat_timeout_ms: int = 250
    command_hold_cycles: int = 10
    sync_overflow: int = 240
    quick_stop_time_s: float = 0.0
    #: The drive's joint in a rig of several: its truth frames at that joint's
    #: identifiers (:func:`hdhil.dbc.truth_frame_id`; 0: ``truth.dbc``'s).
    truth_joint_index: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.sample_period_s <= 1:
            raise ValueError(f"sample_period_s must be in (0, 1] s, got {self.sample_period_s}")
        if self.actuation not in ("next-sync", "immediate"):
            raise ValueError(
                f"actuation must be 'next-sync' or 'immediate', got {self.actuation!r}"
            )
        _check_int(self, "node_id", 1, 127)
        _check_int(self, "controller_node_id", 1, 127)
        if self.controller_node_id == self.node_id:
            raise ValueError(f"DriveConfig: controller and drive share node-ID {self.node_id}")
        _check_int(self, "heartbeat_ms", 0, 0xFFFF)
        _check_int(self, "controller_heartbeat_timeout_ms", 0, 0xFFFF)
        _check_int(self, "command_hold_cycles", 0, 255)
        _check_int(self, "sync_overflow", 0, 240)
        if self.sync_overflow == 1:
            raise ValueError("DriveConfig.sync_overflow must be 0 or 2..240 (CiA 301 0x1019)")
        q = self.quick_stop_time_s
        if isinstance(q, bool) or not isinstance(q, (int, float)) or not 0 <= q < math.inf:
            raise ValueError(f"DriveConfig.quick_stop_time_s must be >= 0 s, got {q!r}")


@dataclass(frozen=True)
class EmcyRecord:
    """An error this drive signalled (``sent`` is False when NMT did not allow the frame)."""

    time: float
    code: int
    manufacturer: bytes
    sent: bool


@dataclass
class DriveDiagnostics:
    """What the drive node did (cumulative; NMT resets do not clear it)."""

    syncs: int = 0
    #: DRIVE_RPDO1 frames processed (in OPERATIONAL).
    commands: int = 0
    malformed_frames: int = 0
    #: DRIVE_RPDO1 frames received outside OPERATIONAL (CiA 301: not processed).
    pdos_ignored: int = 0
    sensor_frames: int = 0
    statusword_frames: int = 0
    #: SYNCs missing before a received one (counter jumps).
    missed_syncs: int = 0
    #: SYNCs ignored because their counter repeated the previous one, or lay behind it.
    duplicate_syncs: int = 0
    stale_syncs: int = 0
    #: SYNCs whose length or counter did not fit ``sync_overflow``.
    sync_errors: int = 0
    #: Commands that arrived more than one period after their SYNC.
    late_commands: int = 0
    #: Command-hold faults (EMCY 0x8250).
    command_timeouts: int = 0
    #: RPDO event-timer deadlines missed (EMCY 0x8250, manufacturer byte 0 = RPDO number).
    rpdo_timeouts: int = 0
    #: SYNC timeouts (1.5 x 0x1006 without a SYNC; EMCY 0x8100).
    sync_timeouts: int = 0
    heartbeat_losses: int = 0
    adc_saturations: int = 0
    overcurrents: int = 0
    nmt_resets: int = 0
    #: Why the plant could not be advanced (what went non-finite, at which plant time);
    #: None while it advances.
    plant_failure: str | None = None
    #: EMCY error events raised by this drive (not counting the 0x0000 "cleared" frames).
    emcy_sent: int = 0
    emcy_log: deque[EmcyRecord] = field(default_factory=lambda: deque(maxlen=256))
