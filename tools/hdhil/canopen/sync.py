"""SYNC producer and consumer checks (CiA 301 §7.2.5).

The producer is driven by the caller (one ``send`` per cycle), the consumer is fed the
received SYNC frames with their time; neither keeps a timer of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import can

from hdhil.canopen.clock import TIME_EPSILON
from hdhil.dbc import SYNC_COB_ID

__all__ = ["SYNC_COB_ID", "SyncMonitor", "SyncProducer"]


class SyncProducer:
    """SYNC producer (CiA 301 §7.2.5): counter 1..overflow then 1 again; 0 = no counter.

    ``overflow`` is object 0x1019: 0 sends SYNC with DLC 0, 2..240 adds the counter byte.
    """

    def __init__(self, bus: can.BusABC, overflow: int = 0, cob_id: int = SYNC_COB_ID) -> None:
        self.bus = bus
        self.sent = 0
        self.counter = 0  # last counter sent (0 before the first SYNC / after a reset)
        self._payloads = [bytes((i,)) for i in range(256)]
        self.configure(overflow=overflow, cob_id=cob_id)

    def configure(self, *, overflow: int, cob_id: int = SYNC_COB_ID) -> None:
        """Set 0x1019 / COB-ID; the counter restarts at 1 (CiA 301 §7.5.2.22)."""
        if overflow == 1 or not 0 <= overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 0 or 2..240 (CiA 301), got {overflow}")
        self.overflow = overflow
        self.cob_id = cob_id
        self._msg = can.Message(
            arbitration_id=cob_id,
            is_extended_id=False,
            data=bytes(1 if overflow else 0),
            check=False,
        )
        self.reset()

    def reset(self) -> None:
        """The next SYNC carries counter 1."""
        self.counter = 0

    def send(self) -> int | None:
        """Send one SYNC; returns the counter it carried (None without a counter)."""
        msg = self._msg
        if self.overflow:
            self.counter = self.counter % self.overflow + 1
            msg.data = self._payloads[self.counter]
        self.bus.send(msg)
        self.sent += 1
        return self.counter if self.overflow else None


@dataclass
class SyncMonitor:
    """SYNC consumer checks: missed SYNCs, late or missing cyclic commands (counters only).

    ``period_s`` is the SYNC period (0x1006), ``overflow`` the producer's counter overflow
    (0x1019 of the producer; 0 = SYNC without counter).  Missed SYNCs come from the
    counter when there is one; with a period too, the number of whole periods elapsed
    settles how many counter wraps were missed.  A command (the synchronous RPDO) is late
    when it arrives more than ``command_deadline_s`` after the SYNC that started its cycle
    (default ``period_s``: it must arrive before the next SYNC is due).  A cycle without
    any command counts in ``missing_commands`` once commands have started to arrive.
    The node decides the reaction (e.g. EMCY 0x8250, quick stop).
    """

    period_s: float | None = None
    overflow: int = 0
    command_deadline_s: float | None = None
    syncs: int = 0
    missed_syncs: int = 0
    #: SYNCs whose DLC/counter did not match ``overflow`` (EMCY 0x8240 material).
    length_errors: int = 0
    late_commands: int = 0
    missing_commands: int = 0
    last_counter: int | None = None
    last_sync_time: float | None = None
    #: SYNCs whose counter repeated the previous one (a duplicated frame).
    duplicates: int = 0
    #: SYNCs whose counter lay just behind the previous one (a frame overtaken on the bus).
    stale: int = 0
    #: SYNCs taken as the producer restarting its counter at 1.
    restarts: int = 0
    _commands_in_cycle: int = field(default=0, init=False, repr=False)
    _commands_started: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.overflow == 1 or not 0 <= self.overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 0 or 2..240, got {self.overflow}")
        if self.period_s is not None and self.period_s <= 0:
            raise ValueError(f"SYNC period must be > 0, got {self.period_s}")
        if self.command_deadline_s is None:
            self.command_deadline_s = self.period_s

    def on_sync_frame(self, msg: can.Message, now: float) -> int:
        """``on_sync`` for a received SYNC frame (DLC 0: no counter, DLC 1: counter)."""
        data = msg.data
        if len(data) > 1:
            self.length_errors += 1
            return self._register(None, now)
        return self.on_sync(data[0] if data else None, now)

    def on_sync(self, counter: int | None, now: float) -> int:
        """Register a SYNC; returns how many SYNCs were missed just before it."""
        if (counter is None) != (self.overflow == 0) or (
            counter is not None and not 1 <= counter <= self.overflow
        ):
            self.length_errors += 1
            counter = None
        return self._register(counter, now)

    def _register(self, counter: int | None, now: float) -> int:
        missed = 0
        if self.last_sync_time is not None:
            elapsed = None
            if self.period_s is not None:
                periods = (now - self.last_sync_time) / self.period_s
                # below 1.5 periods round() - 1 is at most 0 (1.5 itself rounds to 2):
                # the on-time SYNC of every cycle skips the round
                elapsed = 0 if periods < 1.5 else max(0, round(periods) - 1)
            if counter is not None and self.last_counter is not None:
                missed = (counter - (self.last_counter % self.overflow + 1)) % self.overflow
                if elapsed is not None and elapsed > missed:
                    missed += self.overflow * round((elapsed - missed) / self.overflow)
            elif elapsed is not None:
                missed = elapsed
            if self._commands_started and self._commands_in_cycle == 0:
                self.missing_commands += 1
        self.missed_syncs += missed
        self.syncs += 1
        self.last_counter = counter
        self.last_sync_time = now
        self._commands_in_cycle = 0
        return missed

    #: A counter at most this many steps behind the previous one is a late (reordered)
    #: SYNC; further behind, counter 1 means the producer restarted, anything else that
    #: SYNCs were lost and the counter wrapped.
    STALE_WINDOW = 8

    def accept(self, msg: can.Message, now: float) -> int | None:
        """Register a SYNC frame robustly; None for a SYNC to ignore, else the number of
        SYNCs missed just before it.

        With a counter (CiA 301 §7.2.5), a repeated counter is a duplicate and a counter
        up to ``STALE_WINDOW`` steps behind the previous one is a reordered SYNC: both
        are counted and ignored, so they never advance the consumer's time.  Counter 1
        further behind is a producer restart (not a jump), unless it is at most
        ``STALE_WINDOW`` steps ahead: the counter wrapped while SYNCs were lost.  Without
        a counter every SYNC is accepted (nothing tells a duplicate apart).
        """
        data = msg.data
        counter = data[0] if len(data) == 1 else None
        overflow = self.overflow
        if counter is None or not overflow or not 1 <= counter <= overflow:
            return self.on_sync_frame(msg, now)
        last = self.last_counter
        if last is not None:
            behind = (last - counter) % overflow
            if behind == 0:
                self.duplicates += 1
                return None
            if behind <= self.STALE_WINDOW:
                self.stale += 1
                return None
            # Counter 1 a few steps after the last one is the wrap with the SYNCs in
            # between lost (240 lost after 239, say), not a restart.
            ahead = (counter - last) % overflow
            if counter == 1 and ahead > self.STALE_WINDOW:
                self.restarts += 1
                self.last_counter = None
        # A one-byte frame with a counter in range: what on_sync_frame and on_sync would
        # check has passed, so straight to the registration (every SYNC takes this path).
        return self._register(counter, now)

    def on_command(self, now: float) -> bool:
        """Register a cyclic command; True if on time (before the deadline after its SYNC)."""
        self._commands_started = True
        self._commands_in_cycle += 1
        if self.last_sync_time is None or self.command_deadline_s is None:
            return True
        if now - self.last_sync_time > self.command_deadline_s + TIME_EPSILON:
            self.late_commands += 1
            return False
        return True

    @property
    def next_sync_due(self) -> float | None:
        if self.last_sync_time is None or self.period_s is None:
            return None
        return self.last_sync_time + self.period_s
