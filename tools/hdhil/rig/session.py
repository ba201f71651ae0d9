"""Sessions that follow each other: the firmware's start-up check and clean end, and the
drive's record of the sessions it served (``hdhil firmware`` against ``hdhil emulate``
or a real drive).

A configuring master ends a session so that its drive does not fault when the master's
heartbeat stops: its own entry of the drive's heartbeat consumer 0x1016 cleared first
(sub-index written 0), then CiA 402 "disable voltage" (controlword 0x0000 by SDO) and
NMT "enter pre-operational"; its heartbeat goes on while these transfers wait for their
answers (a master is alive until it has left), so a drive slow to answer them does not
time the controller out. A transfer without an answer is sent again. At
the next start it puts that entry back (the drive's EDS default) when it finds it
cleared, and a drive it finds in FAULT is reset: CiA 402 fault reset (0x0000, then
0x0080 by SDO), and NMT "reset node" when the drive refuses it.
These steps are blocking SDO transfers on the bus, outside the node loop, so the
in-process ``hdhil run`` never sends them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
import canopen

from hdhil.canopen.cia402 import State, state_from_statusword
from hdhil.canopen.nmt import NmtCommand, nmt_frame
from hdhil.canopen.sdo import SdoClient
from hdhil.dbc import eds_path

__all__ = ["SessionLog", "end_session", "start_session"]

CONTROLWORD = 0x6040
STATUSWORD = 0x6041
CONSUMER_HEARTBEAT = 0x1016
#: How long one SDO transfer of the session steps may wait for its answer (s).
SDO_TIMEOUT_S = 0.2
#: How often a transfer that got no answer is sent again (a lost frame, a busy drive).
SDO_ATTEMPTS = 3
#: How long the drive may take to boot after an NMT reset node (s).
RESET_BOOT_S = 2.0
#: How often a waiting transfer runs the controller's heartbeat producer (s).
KEEPALIVE_SLICE_S = 0.01

#: Runs the controller's heartbeat producer at a time (s): a master that ends its
#: session is alive, and its heartbeat goes on until its 0x1016 entry is cleared.
Keepalive = Callable[[float], None]


class _Master:
    """Blocking SDO transfers to the drive, outside the node loop, with the controller's
    heartbeat kept going (``keepalive``) while each waits for its answer."""

    def __init__(self, bus: can.BusABC, drive: int, keepalive: Keepalive | None) -> None:
        self.bus = bus
        self.client = SdoClient(bus, drive)
        self.keepalive = keepalive

    def _transfer(self, send: Callable[[], None]) -> Any:
        """``send()``, then the result (None: no answer after :data:`SDO_ATTEMPTS`)."""
        client, recv, keepalive = self.client, self.bus.recv, self.keepalive
        for _ in range(SDO_ATTEMPTS):
            send()
            deadline = time.monotonic() + SDO_TIMEOUT_S
            while (now := time.monotonic()) < deadline:
                if keepalive is not None:
                    keepalive(now)
                msg = recv(KEEPALIVE_SLICE_S)
                if msg is not None and msg.arbitration_id == client.response_id:
                    result = client.on_response(msg)
                    if result is not None:
                        return result
        return None

    def read(self, index: int, sub: int = 0) -> int | None:
        client = self.client
        result = self._transfer(lambda: client.upload(index, sub))
        if result is None or not result.ok:
            return None
        return int.from_bytes(bytes(result.data[:4]), "little")

    def write(self, index: int, sub: int, data: bytes) -> bool:
        client = self.client
        result = self._transfer(lambda: client.download(index, sub, data))
        return result is not None and result.ok


def _consumer_default() -> int:
    """The drive's power-on 0x1016:1 (its EDS default: node << 16 | timeout ms)."""
    od = canopen.import_od(str(eds_path("drive")))
    return int(od[CONSUMER_HEARTBEAT][1].default)


def _is_fault(statusword: int | None) -> bool:
    if statusword is None:
        return False
    try:
        return state_from_statusword(statusword) is State.FAULT
    except ValueError:
        return False


def start_session(bus: can.BusABC, drive: int, controller: int) -> str | None:
    """Before booting the controller: a drive found in FAULT is reset, and the
    controller's cleared entry of the drive's 0x1016 is put back. Returns the one line
    for stderr when the drive was reset, else None (also for a drive not up yet)."""
    master = _Master(bus, drive, None)  # not booted: no heartbeat of its own yet
    statusword = _read_once(master, STATUSWORD)
    if statusword is None:
        return None  # not booted yet: the normal boot handles it
    if _is_fault(statusword):
        master.write(CONTROLWORD, 0, bytes(2))
        master.write(CONTROLWORD, 0, (0x0080).to_bytes(2, "little"))
        after = master.read(STATUSWORD)
        what = f"drive (node {drive}) was in FAULT (statusword 0x{statusword:04X})"
        if not _is_fault(after):
            return f"{what}: fault reset"
        bus.send(nmt_frame(NmtCommand.RESET_NODE, drive))
        _wait_boot(bus, drive)
        return f"{what} and refused the fault reset: NMT reset node"  # power-on values again
    entry = master.read(CONSUMER_HEARTBEAT, 1)
    default = _consumer_default()
    if entry == 0 and default >> 16 == controller:
        master.write(CONSUMER_HEARTBEAT, 1, default.to_bytes(4, "little"))
    return None


def _read_once(master: _Master, index: int) -> int | None:
    """One upload without retries: a drive that is not up yet is normal at start."""
    client = master.client
    deadline = time.monotonic() + SDO_TIMEOUT_S
    client.upload(index, 0)
    while time.monotonic() < deadline:
        msg = master.bus.recv(KEEPALIVE_SLICE_S)
        if msg is not None and msg.arbitration_id == client.response_id:
            result = client.on_response(msg)
            if result is not None:
                return int.from_bytes(bytes(result.data[:4]), "little") if result.ok else None
    return None


def _wait_boot(bus: can.BusABC, drive: int) -> None:
    """Wait for the drive's boot-up after a reset (its heartbeat then tells the
    controller it is up)."""
    deadline = time.monotonic() + RESET_BOOT_S
    while time.monotonic() < deadline:
        msg = bus.recv(0.01)
        if msg is not None and msg.arbitration_id == 0x700 + drive and bytes(msg.data) == b"\0":
            return


def end_session(
    bus: can.BusABC, drive: int, controller: int, keepalive: Keepalive | None = None
) -> bool:
    """The clean end: the controller's 0x1016 entry cleared, disable voltage, NMT
    pre-operational. True when the drive confirmed the clearing (or had no entry of the
    controller's to clear). ``keepalive`` runs the controller's heartbeat producer while
    the transfers wait: a drive slow to answer them must not time the controller out
    (250 ms) before its entry is cleared."""
    master = _Master(bus, drive, keepalive)
    entry = master.read(CONSUMER_HEARTBEAT, 1)
    cleared = entry is not None
    if cleared and (entry >> 16) & 0xFF == controller:
        cleared = master.write(CONSUMER_HEARTBEAT, 1, bytes(4))
    master.write(CONTROLWORD, 0, bytes(2))
    bus.send(nmt_frame(NmtCommand.ENTER_PRE_OPERATIONAL, drive))
    return cleared


# ------------------------------------------------------------------ the drive's side
@dataclass
class Session:
    """One controller session the drive served: from the controller's boot-up."""

    started_s: float
    syncs_at_start: int
    nmt_starts: int = 0
    end: str = "running"


class SessionLog:
    """The sessions a drive (:class:`hdhil.hostsim.drive.DriveNode`) served: each begins
    with a boot-up of its controller and ends clean (the controller cleared its 0x1016
    entry), on a heartbeat loss, or on an NMT reset node."""

    def __init__(self, drive: Any) -> None:
        self.drive = drive
        self.controller = drive.config.controller_node_id
        self.sessions: list[Session] = []
        #: The drive's time at power-on (session times count from it).
        self.origin = 0.0
        services = drive.services
        services.on_boot(self._on_boot)
        services.on_state_change(self._on_state)
        services.on_heartbeat_lost(self._on_lost)
        services.on_reset(self._on_reset)
        services.on_write(CONSUMER_HEARTBEAT, 1, self._on_consumer)

    def _open(self) -> Session | None:
        s = self.sessions[-1] if self.sessions else None
        return s if s is not None and s.end == "running" else None

    def _close(self, end: str) -> None:
        s = self._open()
        if s is not None:
            s.end = end

    def _on_boot(self, node_id: int) -> None:
        if node_id == self.controller:
            self._close("controller booted again")
            self.sessions.append(Session(self.drive.now, self.drive.diagnostics.syncs))

    def _on_state(self, old: Any, new: Any) -> None:
        s = self._open()
        if s is not None and new.name == "OPERATIONAL":
            s.nmt_starts += 1

    def _on_lost(self, node_id: int) -> None:
        if node_id == self.controller:
            self._close("heartbeat lost")

    def _on_reset(self, kind: str) -> None:
        if kind == "node":
            self._close("NMT reset node")

    def _on_consumer(self, value: int) -> None:
        if not value:
            self._close("clean")

    def summary(self) -> list[dict[str, Any]]:
        syncs = self.drive.diagnostics.syncs
        out = []
        for i, s in enumerate(self.sessions):
            end = self.sessions[i + 1].syncs_at_start if i + 1 < len(self.sessions) else syncs
            started = round(s.started_s - self.origin, 3)
            out.append({"started_s": started, "nmt_starts": s.nmt_starts,
                        "syncs": end - s.syncs_at_start, "end": s.end})  # fmt: skip
        return out
