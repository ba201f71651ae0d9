"""Control-bus budget: worst-case load of the cyclic schedule described in the DBC.

docs/design.md, "Frame budget": a classical base frame with n data bytes takes at most
47 + 8n bits (incl. the 3-bit interframe space) plus floor((34 + 8n - 1)/4) stuff bits.
The cyclic schedule is every message with a ``GenMsgCycleTime`` attribute; its worst-case
load is the sum of worst-case frame times over one cycle divided by the cycle.
"""

from __future__ import annotations

from dataclasses import dataclass

from hdhil.dbc import BusName, database, worst_case_frame_bits

#: Above this worst-case load the schedule leaves too little room for SDO, heartbeat,
#: EMCY and retransmissions (docs/design.md: keep it at or below 60 %).
LOAD_LIMIT = 0.60


@dataclass(frozen=True)
class ScheduleLoad:
    bus: str
    bitrate: int
    frames: tuple[tuple[str, int, float], ...]  # (name, worst-case bits, period s)
    worst_case_load: float

    def fits(self) -> bool:
        return self.worst_case_load <= LOAD_LIMIT


def schedule_load(
    bus: BusName = "control", bitrate: int = 1_000_000, sample_period_s: float = 1e-3
) -> ScheduleLoad:
    """Worst-case load of ``bus``'s cyclic frames at ``bitrate``.

    Messages whose cycle time equals the DBC's 1 ms base cycle run every sample period,
    so a slower loop (``sample_period_s`` > 1 ms) scales their period with it.
    """
    if bitrate <= 0:
        raise ValueError(f"bitrate must be > 0, got {bitrate}")
    frames = []
    load = 0.0
    for msg in database(bus).messages:
        cycle_ms = msg.cycle_time
        if not cycle_ms:
            continue
        period = cycle_ms * sample_period_s
        bits = worst_case_frame_bits(msg.length, msg.is_extended_frame)
        frames.append((msg.name, bits, period))
        load += bits / bitrate / period
    return ScheduleLoad(bus, bitrate, tuple(frames), load)
