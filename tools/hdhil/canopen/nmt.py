"""NMT (CiA 301 §7.2.8, §7.3.2): states, commands, the master's boot-up bookkeeping.

State and command codes are canopen's (``canopen.nmt.NMT_STATES`` / ``NMT_COMMANDS``),
given names here.  The slave's state machine (which OD areas a reset restores, which
services each state allows) lives in :class:`hdhil.canopen.services.CanopenServices`,
because it orchestrates every other protocol; the frame layout, the master side and
the boot-up wait are here.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Literal

import can
from canopen.nmt import NMT_COMMANDS, NMT_STATES

from hdhil.canopen.clock import TIME_EPSILON

__all__ = [
    "HEARTBEAT_BASE",
    "NMT_COB_ID",
    "BootTimeoutError",
    "NmtCommand",
    "NmtMaster",
    "NmtState",
    "ResetKind",
    "nmt_frame",
    "state_name",
]

#: NMT node control COB-ID (CiA 301 §7.2.8.3.1).
NMT_COB_ID = 0x000
#: Heartbeat / boot-up COB-ID base (CiA 301 §7.2.8.3.2): 0x700 + node-ID.
HEARTBEAT_BASE = 0x700

_STATE_CODE = {name: code for code, name in NMT_STATES.items()}


class NmtState(IntEnum):
    """NMT states as the heartbeat byte codes them (CiA 301 §7.2.8.3.2.1)."""

    INITIALISING = _STATE_CODE["INITIALISING"]  # only ever seen as the boot-up message
    STOPPED = _STATE_CODE["STOPPED"]
    OPERATIONAL = _STATE_CODE["OPERATIONAL"]
    PRE_OPERATIONAL = _STATE_CODE["PRE-OPERATIONAL"]


class NmtCommand(IntEnum):
    """NMT node control command specifiers (CiA 301 §7.2.8.3.1)."""

    START = NMT_COMMANDS["OPERATIONAL"]
    STOP = NMT_COMMANDS["STOPPED"]
    ENTER_PRE_OPERATIONAL = NMT_COMMANDS["PRE-OPERATIONAL"]
    RESET_NODE = NMT_COMMANDS["RESET"]
    RESET_COMMUNICATION = NMT_COMMANDS["RESET COMMUNICATION"]


#: Command names as a user types them (``hdhil nmt ACTION``).
COMMAND_NAMES: dict[str, NmtCommand] = {
    "start": NmtCommand.START,
    "stop": NmtCommand.STOP,
    "pre-op": NmtCommand.ENTER_PRE_OPERATIONAL,
    "reset": NmtCommand.RESET_NODE,
    "reset-comm": NmtCommand.RESET_COMMUNICATION,
}

ResetKind = Literal["node", "communication"]


def state_name(state: int) -> str:
    """The state's name as CiA 301 and canopen spell it ("OPERATIONAL", "PRE-OPERATIONAL",
    "STOPPED", "INITIALISING"), for summaries a script reads."""
    return NMT_STATES.get(int(state), str(int(state)))


def nmt_frame(cs: int, node_id: int = 0) -> can.Message:
    """The NMT node-control frame: command specifier, addressed node-ID (0 = all)."""
    cs = NmtCommand(cs)
    if not 0 <= node_id <= 127:
        raise ValueError(f"NMT node-ID must be 0..127, got {node_id}")
    return can.Message(
        arbitration_id=NMT_COB_ID, is_extended_id=False, data=bytes((cs, node_id)), check=False
    )


def boot_up_frame(node_id: int) -> can.Message:
    """The boot-up message: the heartbeat COB-ID with state INITIALISING (0x00)."""
    return can.Message(
        arbitration_id=HEARTBEAT_BASE + node_id, is_extended_id=False, data=b"\x00", check=False
    )


class BootTimeoutError(RuntimeError):
    """Expected nodes sent no boot-up message in time (NMT master)."""

    def __init__(self, node_ids: tuple[int, ...], waited_s: float) -> None:
        self.node_ids = node_ids
        names = ", ".join(
            f"node {n} (COB-ID 0x{HEARTBEAT_BASE + n:03X}, data 00)" for n in node_ids
        )
        super().__init__(
            f"no boot-up message from {names} within {waited_s:.3f} s: check that the node "
            "is powered, on the same bus at the same bit rate, and uses that node-ID"
        )


class NmtMaster:
    """The master side: node-control commands and the wait for boot-up messages.

    ``boot_times`` and ``remote_states`` are filled by the heartbeat consumer
    (:class:`hdhil.canopen.heartbeat.HeartbeatConsumer`) from every heartbeat and boot-up.
    """

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.boot_times: dict[int, float] = {}
        self.remote_states: dict[int, NmtState | int] = {}
        self._boot_deadlines: dict[int, tuple[float, float]] = {}  # node -> (deadline, wait)

    def command(self, cs: int, node_id: int = 0) -> None:
        """Send an NMT node-control command (node_id 0 = all nodes).

        A reset command forgets earlier boot-ups of the addressed nodes, so
        :meth:`boot_seen` waits for the new one.
        """
        msg = nmt_frame(cs, node_id)
        self.bus.send(msg)
        if msg.data[0] in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            if node_id == 0:
                self.boot_times.clear()
            else:
                self.boot_times.pop(node_id, None)

    def expect_boot(self, node_id: int, now: float, timeout_s: float) -> None:
        """Start waiting (without blocking) for ``node_id``'s boot-up until now + timeout."""
        self._boot_deadlines[node_id] = (now + timeout_s, timeout_s)

    def boot_seen(self, node_id: int) -> bool:
        """True once a boot-up message from ``node_id`` has been received."""
        return node_id in self.boot_times

    def boot_timed_out(self, now: float) -> tuple[int, ...]:
        """Expected nodes whose boot-up deadline has passed without a boot-up."""
        return tuple(
            n
            for n, (deadline, _) in sorted(self._boot_deadlines.items())
            if n not in self.boot_times and now > deadline + TIME_EPSILON
        )

    def check_boot(self, now: float) -> bool:
        """True when every expected node has booted; raises ``BootTimeoutError`` past a
        deadline; False while still waiting."""
        late = self.boot_timed_out(now)
        if late:
            raise BootTimeoutError(late, max(self._boot_deadlines[n][1] for n in late))
        return all(n in self.boot_times for n in self._boot_deadlines)
