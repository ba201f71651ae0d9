"""Heartbeat producer and consumer (CiA 301 §7.2.8.3.2), driven by the caller's clock.

canopen's ``NmtSlave`` produces its heartbeat on a ``send_periodic`` thread and has no
consumer (canopen issues #286, #558); here both run in the node's own ``tick``, so a
lockstep run stays deterministic.  The reactions to a loss (EMCY 0x8130, the 0x1029
error behaviour, the application's callbacks) are the composing class's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import can

from hdhil.canopen.clock import TIME_EPSILON
from hdhil.canopen.nmt import HEARTBEAT_BASE, NmtMaster, NmtState

__all__ = ["HEARTBEAT_BASE", "HeartbeatConsumer", "HeartbeatProducer", "MonitoredNode"]


@dataclass
class MonitoredNode:
    """Heartbeat consumer state for one monitored node (an entry of 0x1016)."""

    node_id: int
    timeout_s: float
    #: "waiting" until the first heartbeat (CiA 301: monitoring starts there), "active"
    #: while heartbeats arrive in time, "lost" after a timeout until the next heartbeat.
    status: Literal["waiting", "active", "lost"] = "waiting"
    last_heartbeat: float | None = None
    nmt_state: int | None = None
    deadline: float = math.inf
    losses: int = 0
    #: Time the latest loss was detected (the ``now`` of that ``tick``).
    lost_at: float | None = None
    resumed_at: float | None = None


class HeartbeatProducer:
    """Heartbeats at origin + k * period, k = 1, 2, ... (0x1017; period 0 = off).

    The boot-up message (or a new 0x1017 value) restarts the schedule; a late ``tick``
    sends one heartbeat and skips the slots it missed instead of bursting.
    """

    def __init__(self, bus: can.BusABC, node_id: int) -> None:
        self.bus = bus
        self.period_s = 0.0
        self.sent = 0
        self._origin = 0.0
        self._count = 0
        self.next_due = math.inf
        self._msg = can.Message(
            arbitration_id=HEARTBEAT_BASE + node_id,
            is_extended_id=False,
            data=bytes(1),
            check=False,
        )

    def start(self, now: float) -> None:
        self._origin = now
        self._count = 0
        self.next_due = now + self.period_s if self.period_s > 0 else math.inf

    def send(self, now: float, state: int) -> None:
        self._msg.data = bytes((state,))
        self.bus.send(self._msg)
        self.sent += 1
        period, origin = self.period_s, self._origin
        k = max(self._count + 1, math.floor((now - origin) / period))
        while origin + (k + 1) * period <= now + TIME_EPSILON:
            k += 1
        self._count = k
        self.next_due = origin + (k + 1) * period


HeartbeatEvent = Literal["boot", "heartbeat", "resumed"]


class HeartbeatConsumer:
    """Monitors the nodes of 0x1016 ({node_id: timeout}); records boot-ups and remote
    NMT states for the NMT master.  Monitoring of a node starts at its first heartbeat
    (CiA 301) and restarts after its boot-up."""

    def __init__(self, master: NmtMaster) -> None:
        self.master = master
        self.monitored: dict[int, MonitoredNode] = {}
        self.received = 0
        #: The earliest time (s, with the tolerance added) after which :meth:`expired` can
        #: find an overdue node: the nearest active deadline, ``inf`` when none is active.
        #: A per-cycle ``tick`` compares ``now`` with this one float and skips the scan.
        self.next_expiry = math.inf

    def _update_next_expiry(self) -> None:
        self.next_expiry = min(
            (m.deadline + TIME_EPSILON for m in self.monitored.values() if m.status == "active"),
            default=math.inf,
        )

    def configure(self, entries: Mapping[int, int]) -> None:
        """Set the monitored nodes from {node_id: timeout_ms}; unchanged entries keep state."""
        wanted = {n: ms for n, ms in entries.items() if n and ms}
        for node_id in list(self.monitored):
            if node_id not in wanted or self.monitored[node_id].timeout_s != wanted[node_id] / 1e3:
                del self.monitored[node_id]
        for node_id, ms in wanted.items():
            if node_id not in self.monitored:
                self.monitored[node_id] = MonitoredNode(node_id, ms / 1e3)
        self._update_next_expiry()

    def on_frame(
        self, node_id: int, state_byte: int, now: float, monitoring: bool
    ) -> HeartbeatEvent:
        """A heartbeat or boot-up of ``node_id``; ``monitoring`` False (this node not
        booted) only records the remote state."""
        state = state_byte & 0x7F  # bit 7 is the node-guarding toggle bit
        self.received += 1
        monitor = self.monitored.get(node_id)
        master = self.master
        if state == NmtState.INITIALISING:
            # Boot-up: the node restarted.  Monitoring (re)starts at its next heartbeat.
            master.boot_times[node_id] = now
            master.remote_states[node_id] = NmtState.PRE_OPERATIONAL
            if monitor is not None and monitor.status == "active":
                monitor.status = "waiting"
                monitor.deadline = math.inf
                self._update_next_expiry()
            return "boot"
        try:
            master.remote_states[node_id] = NmtState(state)
        except ValueError:
            master.remote_states[node_id] = state
        if monitor is None or not monitoring:
            return "heartbeat"
        monitor.last_heartbeat = now
        monitor.nmt_state = state
        monitor.deadline = now + monitor.timeout_s
        event: HeartbeatEvent = "resumed" if monitor.status == "lost" else "heartbeat"
        if event == "resumed":
            monitor.resumed_at = now
        monitor.status = "active"
        self._update_next_expiry()
        return event

    def expired(self, now: float) -> list[MonitoredNode]:
        """Mark and return the active nodes whose heartbeat is overdue at ``now``."""
        if not now > self.next_expiry:
            return []  # the per-cycle case: no active deadline has passed
        lost = []
        for m in self.monitored.values():
            if m.status == "active" and now > m.deadline + TIME_EPSILON:
                m.status = "lost"
                m.losses += 1
                m.lost_at = now
                m.deadline = math.inf
                lost.append(m)
        self._update_next_expiry()
        return lost
