"""Control-bus budget: worst-case load of the cyclic schedule described in the DBC.

docs/design.md, "Frame budget": a classical frame's worst case for its known identifier
and length (:func:`hdhil.can.bittiming.worst_case_frame_bits_for`: the header stuffed
exactly, the data and CRC bits at their most stuff bits), never above the bound for any
identifier (47 + 8n bits incl. the 3-bit interframe space plus floor((34 + 8n - 1)/4)
stuff bits).  The cyclic schedule is every message with a ``GenMsgCycleTime`` attribute;
its worst-case load is the sum of worst-case frame times over one cycle divided by the
cycle, as the planner of several joints computes it (:mod:`hdhil.can.schedule`).  CAN FD
messages (``is_fd`` in the DBC) count with :func:`hdhil.can.bittiming.worst_case_fd_frame_bits`,
their data phase at ``data_bitrate`` (bit-rate switching) when one is given.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hdhil.can.bittiming import worst_case_fd_frame_bits, worst_case_frame_bits_for
from hdhil.dbc import BusName, database

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
    bus: BusName = "control",
    bitrate: int = 1_000_000,
    sample_period_s: float = 1e-3,
    data_bitrate: int | None = None,
    db: Any = None,
) -> ScheduleLoad:
    """Worst-case load of ``bus``'s cyclic frames at ``bitrate`` (``db``: a cantools
    database of the bus in place of its DBC, e.g. a drive at another node-ID, whose
    identifiers stuff differently).

    Messages whose cycle time equals the DBC's 1 ms base cycle run every sample period,
    so a slower loop (``sample_period_s`` > 1 ms) scales their period with it.
    """
    if bitrate <= 0:
        raise ValueError(f"bitrate must be > 0, got {bitrate}")
    if data_bitrate is not None and data_bitrate <= 0:
        raise ValueError(f"data bitrate must be > 0, got {data_bitrate}")
    frames = []
    load = 0.0
    for msg in (db if db is not None else database(bus)).messages:
        cycle_ms = msg.cycle_time
        if not cycle_ms:
            continue
        period = cycle_ms * sample_period_s
        if msg.is_fd:
            brs = data_bitrate is not None
            fd_bits = worst_case_fd_frame_bits(msg.length, msg.is_extended_frame, brs=brs)
            bits = fd_bits.total
            seconds = fd_bits.seconds(bitrate, data_bitrate or bitrate)
        else:
            bits = worst_case_frame_bits_for(msg.frame_id, msg.is_extended_frame, msg.length)
            seconds = bits / bitrate
        frames.append((msg.name, bits, period))
        load += seconds / period
    return ScheduleLoad(bus, bitrate, tuple(frames), load)
