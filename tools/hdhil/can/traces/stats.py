"""Timing statistics of a trace, for ``hdhil dump --stats``.

:func:`compute_stats` (or the streaming :class:`StatsAccumulator`) gives, as a JSON-ready
dict (keys on :meth:`StatsAccumulator.result`): per identifier its rate, period and
jitter; per bus its worst-case load against the 60 % budget and its actual load from the
frames' exact bits; and the gaps in the cycle counters (SYNC, the drive command's cycle)
that show lost, reordered or duplicated frames, per channel and sender.
:func:`format_stats` is its text.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import can

from hdhil.can.bittiming import (
    fd_frame_bits,
    frame_bits,
    worst_case_fd_frame_bits,
    worst_case_frame_bits_for,
)
from hdhil.can.busload import LOAD_LIMIT
from hdhil.can.traces.decode import (
    UNKNOWN_BUS,
    DecodedFrame,
    FrameDecoder,
    FrameKind,
    default_decoder,
    format_id,
)
from hdhil.dbc import CHANNEL_NUMBER, codec, worst_case_frame_bits


@dataclass
class _IdStats:
    bus: str
    arbitration_id: int
    is_extended_id: bool
    name: str | None
    count: int = 0
    first: float = 0.0
    last: float = 0.0
    payload: int = 0
    malformed: int = 0
    # Welford accumulation of the periods
    n_periods: int = 0
    mean_period: float = 0.0
    m2_period: float = 0.0
    min_period: float = math.inf
    max_period: float = -math.inf
    #: A CAN FD frame (its data phase at the bus's data bit rate when it has one).
    fd: bool = False

    def add(self, time: float, payload: int, malformed: bool) -> None:
        if self.count:
            period = time - self.last
            self.n_periods += 1
            delta = period - self.mean_period
            self.mean_period += delta / self.n_periods
            self.m2_period += delta * (period - self.mean_period)
            if period < self.min_period:
                self.min_period = period
            if period > self.max_period:
                self.max_period = period
        else:
            self.first = time
        self.count += 1
        self.last = time
        if payload > self.payload:
            self.payload = payload
        self.malformed += malformed


class _CounterTrack:
    """One cycle counter as one sender sends it on one channel: which counts went
    missing for good (lost), which came late (reordered) and which came twice.

    ``last`` is the highest count seen (modulo ``modulus``).  A count one ahead is in
    order; further ahead is a jump whose skipped counts become *pending*; a count behind
    ``last`` that is pending arrived late (reordered, no longer missing), one seen
    recently is a duplicate.  Pending counts older than :data:`REORDER_WINDOW` frames
    are lost for good; at the end every pending count is lost.
    """

    __slots__ = ("frames", "gaps", "last", "lost", "modulus", "pending", "recent",
                 "reordered", "repeats")  # fmt: skip

    def __init__(self, modulus: int) -> None:
        self.modulus = modulus
        self.last: int | None = None
        self.pending: dict[int, int] = {}  # count -> frame number when it went missing
        self.recent: dict[int, int] = {}  # count -> frame number last seen
        self.frames = self.gaps = self.lost = self.reordered = self.repeats = 0

    def add(self, value: int) -> None:
        self.frames += 1
        n = self.frames
        value %= self.modulus  # SYNC counts 1..240: 240 is 0 here, so steps wrap right
        last = self.last
        if last is None:
            self.last = value
            self.recent[value] = n
            return
        step = (value - last) % self.modulus
        if step == 0:
            self.repeats += 1  # the newest count again: a duplicate
        elif step <= self.modulus // 2:
            if step > 1:  # a jump: the skipped counts are missing (for now)
                self.gaps += 1
                for i in range(1, step):
                    self.pending[(last + i) % self.modulus] = n
            self.last = value
        elif value in self.pending:
            del self.pending[value]  # a count given up as missing arrived late
            self.reordered += 1
        elif n - self.recent.get(value, -REORDER_WINDOW - 1) <= REORDER_WINDOW:
            self.repeats += 1  # an older count seen again: a duplicate
        else:
            self.last = value  # far behind, never missed: the sender restarted its count
        self.recent[value] = n
        if len(self.recent) > 2 * REORDER_WINDOW:
            self.recent = {k: v for k, v in self.recent.items() if n - v <= REORDER_WINDOW}
        if self.pending and n - min(self.pending.values()) > REORDER_WINDOW:
            expired = [k for k, v in self.pending.items() if n - v > REORDER_WINDOW]
            for k in expired:
                del self.pending[k]
            self.lost += len(expired)

    def result(self) -> dict[str, int]:
        return {"gaps": self.gaps, "missing": self.lost + len(self.pending),
                "reordered": self.reordered, "repeats": self.repeats}  # fmt: skip


#: Frames of one counter after which a count still missing is lost for good (a
#: reordered frame arrives at most a few frames late).
REORDER_WINDOW = 32
#: Distinct identifiers listed (all buses together; hdhil's buses carry 15, a vehicle bus
#: a few hundred): frames of further identifiers count in their bus's frame totals and
#: actual load only, so a trace of random identifiers cannot fill the memory.
MAX_IDS = 4096
#: Distinct buses (channels) listed; frames of further channels count under OTHER_BUS.
MAX_BUSES = 64
OTHER_BUS = "other"


@dataclass
class _BusStats:
    frames: int = 0
    first: float = math.inf
    last: float = -math.inf
    actual_bits: int = 0
    unknown_frames: int = 0
    unknown_ids: set[tuple[bool, int]] = field(default_factory=set)
    #: Time on the wire of its CAN FD frames (s; its classical frames: ``actual_bits``).
    actual_fd_s: float = 0.0
    malformed: int = 0
    errors: int = 0
    remote: int = 0


_BUS_ORDER = {name: i for i, name in enumerate(CHANNEL_NUMBER)}


def _bus_share(
    load: float | None, count: int, span: float, frame_percent: float, bus_span: float
) -> float:
    """One identifier's share of its bus's worst-case load (``load_percent`` of a bus).

    A cyclic identifier, seen over at least half the bus's duration, counts with its own
    rate.  A sporadic one (an SDO exchange, a burst of configuration writes at boot, a
    single EMCY) would count with the rate inside its burst, which can exceed the whole
    bus; it counts with its frames spread over the bus's duration instead.
    """
    if load is not None and span >= 0.5 * bus_span:
        return load
    if bus_span <= 0.0:
        return 0.0
    return count * frame_percent / bus_span


def _bus_sort_key(bus: str) -> tuple[int, str]:
    return (_BUS_ORDER.get(bus, len(_BUS_ORDER) + (bus == UNKNOWN_BUS)), bus)


class StatsAccumulator:
    """Streaming per-(bus, ID) timing statistics and per-bus worst-case load."""

    def __init__(self, bitrate: int = 1_000_000, decoder: FrameDecoder | None = None) -> None:
        if bitrate <= 0:
            raise ValueError(f"bitrate must be > 0, got {bitrate}")
        self.bitrate = bitrate
        self.decoder = decoder or default_decoder()
        #: Per bus label, the data phase's bit rate of its FD frames (its database's FD
        #: bit rate, bit-rate switching); a bus without one times them at ``bitrate``.
        self._data_rates: dict[str, int] = {}
        for name, db in getattr(self.decoder, "databases", {}).items():
            rate = db.buses[0].fd_baudrate if getattr(db, "buses", None) else None
            if rate:
                self._data_rates[name] = int(rate)
        self._ids: dict[tuple[str, bool, int], _IdStats] = {}
        self._buses: dict[str, _BusStats] = {}
        self.counts = {kind: 0 for kind in FrameKind}
        self.unlisted = 0  # frames of identifiers beyond MAX_IDS
        self.first = math.inf
        self.last = -math.inf
        # Cycle counters whose gaps show lost frames: (name, signal index, modulus).
        # The command's identifier as the decoder has it (a drive at another node-ID).
        by_name = self.decoder.by_name
        command = by_name["DRIVE_RPDO1"][1].frame_id if "DRIVE_RPDO1" in by_name else None
        command_codec = codec("control", "DRIVE_RPDO1")
        command_codec = command_codec.at(command if command is not None else command_codec.frame_id)
        self._counters = {
            (codec("control", "SYNC").frame_id, False): ("SYNC.sync_counter", 0, 240),
            (command_codec.frame_id, False): ("DRIVE_RPDO1.cycle", 2, 256),
        }
        sync = codec("control", "SYNC")
        self._counter_codecs = {(sync.frame_id, False): sync,
                                (command_codec.frame_id, False): command_codec}  # fmt: skip
        # One track per (channel, sender's identifier, counter): frames logged on two
        # channels, or two senders of one counter, are never mixed into one sequence.
        self._tracks: dict[tuple[str, int, str], _CounterTrack] = {}

    def _count(self, frame: DecodedFrame, bus: str) -> None:
        key = (frame.arbitration_id, frame.is_extended_id)
        name, index, modulus = self._counters[key]
        try:
            value = int(self._counter_codecs[key].decode(frame.data)[index])
        except ValueError:
            return
        # Works for both counters: SYNC runs 1..240 and wraps to 1, so (value - last) mod
        # 240 is 1 across the wrap as well; the command's cycle counter runs mod 256.
        track_key = (bus, frame.arbitration_id, name)
        track = self._tracks.get(track_key)
        if track is None:
            track = self._tracks[track_key] = _CounterTrack(modulus)
        track.add(value)

    @property
    def gaps(self) -> dict[str, dict[str, int]]:
        """Per counter, summed over channels and senders: ``gaps`` (jumps forward),
        ``missing`` (counts never seen: lost frames), ``reordered`` (counts that came
        late), ``repeats`` (duplicates)."""
        out = {name: dict.fromkeys(("gaps", "missing", "reordered", "repeats"), 0)
               for name, *_rest in self._counters.values()}  # fmt: skip
        for (_, _, name), track in self._tracks.items():
            for k, v in track.result().items():
                out[name][k] += v
        return out

    @property
    def gaps_by_channel(self) -> list[dict[str, Any]]:
        """One entry per channel, sender and counter (see :attr:`gaps`)."""
        return [
            {"bus": bus, "sender": format_id(frame_id, False), "counter": name, "frames": t.frames,
             **t.result()}
            for (bus, frame_id, name), t in sorted(
                self._tracks.items(), key=lambda kv: (_bus_sort_key(kv[0][0]), kv[0][1:])
            )
        ]  # fmt: skip

    def add(self, frame: DecodedFrame | can.Message) -> None:
        if isinstance(frame, can.Message):
            frame = self.decoder.classify(frame, decode=False)
        self.counts[frame.kind] += 1
        t = frame.time
        if t < self.first:
            self.first = t
        if t > self.last:
            self.last = t
        label = frame.bus
        bus = self._buses.get(label)
        if bus is None:
            if len(self._buses) >= MAX_BUSES:
                label = OTHER_BUS
                bus = self._buses.get(label)
            if bus is None:
                bus = self._buses[label] = _BusStats()
        bus.frames += 1
        if t < bus.first:
            bus.first = t
        if t > bus.last:
            bus.last = t
        if frame.kind is FrameKind.ERROR:
            bus.errors += 1
            return  # error frames have no identifier and no schedule
        if frame.kind is FrameKind.UNKNOWN:
            bus.unknown_frames += 1
            if len(bus.unknown_ids) < MAX_IDS:
                bus.unknown_ids.add((frame.is_extended_id, frame.arbitration_id))
        elif frame.kind is FrameKind.MALFORMED:
            bus.malformed += 1
        elif frame.kind is FrameKind.REMOTE:
            bus.remote += 1
        key = (label, frame.is_extended_id, frame.arbitration_id)
        stats = self._ids.get(key)
        if stats is None and len(self._ids) < MAX_IDS:
            stats = self._ids[key] = _IdStats(
                label, frame.arbitration_id, frame.is_extended_id, frame.message
            )
        definition = frame.definition
        fd = len(frame.data) > 8 or (definition is not None and bool(definition.is_fd))
        if stats is not None:
            payload = 0 if frame.kind is FrameKind.REMOTE else len(frame.data)
            stats.add(t, payload, frame.kind is FrameKind.MALFORMED)
            stats.fd = stats.fd or fd
        else:
            self.unlisted += 1
        remote = frame.kind is FrameKind.REMOTE
        ident = (frame.arbitration_id, frame.is_extended_id)
        if fd and not remote and len(frame.data) <= 64:
            rate = self._data_rates.get(label)
            bits = fd_frame_bits(*ident, bytes(frame.data), brs=rate is not None)
            bus.actual_fd_s += bits.seconds(self.bitrate, rate or self.bitrate)
        else:
            bus.actual_bits += frame_bits(*ident, remote, bytes(frame.data[:8]))
        if frame.kind is FrameKind.DECODED and ident in self._counters:
            self._count(frame, label)

    def result(self) -> dict[str, Any]:
        """The statistics as a JSON-ready dict.

        Top level: ``bitrate`` (bit/s), ``load_limit_percent`` (the 60 % budget),
        ``frames``, ``decoded``, ``unknown``, ``malformed``, ``error``, ``remote`` (frame
        counts), ``start``/``end``/``duration`` (s; ``None`` without frames), ``ids`` and
        ``buses``.

        ``ids``: one entry per (bus, identifier), ordered by bus then identifier, with
        ``bus``, ``id`` (int), ``id_hex``, ``extended``, ``name`` (``None`` if unknown),
        ``count``, ``malformed`` (count), ``rate_hz`` ((count - 1) / time span),
        ``period_ms`` (mean period), ``jitter_std_us`` (population std of the periods),
        ``jitter_max_us`` (max |period - mean period|), ``payload_bytes`` (largest seen),
        ``worst_case_bits`` and ``frame_time_us`` (worst case incl. stuffing and
        interframe space, for the identifier:
        :func:`hdhil.can.bittiming.worst_case_frame_bits_for`), ``load_percent``
        (rate x worst-case bits / bitrate).  Rate, period, jitter and load are ``None``
        for an identifier seen once (or with no time span).

        ``buses``: per bus label: ``duration`` (s, first to last frame of that bus),
        ``frames``, ``load_percent`` (worst-case load, sum over its identifiers; an
        identifier seen over less than half the bus's duration, such as a burst of SDO
        frames at boot, counts with its frames spread over the bus's duration rather
        than with the rate inside its burst),
        ``actual_load_percent`` (the frames' exact bits incl. real stuff bits,
        :mod:`hdhil.can.bittiming`, over the duration),
        ``over_limit`` (load above ``load_limit_percent``; never the truth channel, which
        exists only in simulation), ``unknown_ids`` (distinct,
        counted up to :data:`MAX_IDS`), ``unknown_frames``, ``malformed``,
        ``error_frames``, ``remote_frames``.  At most :data:`MAX_BUSES` buses are listed
        (frames of further channels under :data:`OTHER_BUS`).

        ``unlisted_frames``: frames of identifiers beyond the first :data:`MAX_IDS`, in
        their bus's ``frames`` and ``actual_load_percent`` but in no ``ids`` entry (nor in
        the worst-case ``load_percent``).
        """
        ids = []
        loads: dict[str, float] = {}
        bus_spans = {name: b.last - b.first for name, b in self._buses.items()}
        for key in sorted(self._ids, key=lambda k: (_bus_sort_key(k[0]), k[1], k[2])):
            s = self._ids[key]
            # the worst case for this identifier (as hdhil run and hdhil plan count it);
            # a payload longer than a classical frame's, or an identifier out of its
            # range (a damaged trace): the bound for any identifier
            valid = key[2] < (1 << (29 if s.is_extended_id else 11))
            seconds = None
            if s.fd and valid and s.payload <= 64:  # FD: its phases at their bit rates
                rate = self._data_rates.get(s.bus)
                fd_bits = worst_case_fd_frame_bits(
                    s.payload, s.is_extended_id, brs=rate is not None, arbitration_id=key[2]
                )
                bits = fd_bits.total
                seconds = fd_bits.seconds(self.bitrate, rate or self.bitrate)
            elif s.payload <= 8 and valid:
                bits = worst_case_frame_bits_for(key[2], s.is_extended_id, s.payload)
            else:
                bits = worst_case_frame_bits(s.payload, s.is_extended_id)
            if seconds is None:
                seconds = bits / self.bitrate
            span = s.last - s.first
            if s.count >= 2 and span > 0:
                rate = (s.count - 1) / span
                mean = s.mean_period
                std = math.sqrt(max(s.m2_period, 0.0) / s.n_periods)
                jmax = max(s.max_period - mean, mean - s.min_period)
                load = rate * seconds * 100.0
                period_ms, std_us, jmax_us = mean * 1e3, std * 1e6, jmax * 1e6
            else:
                rate = period_ms = std_us = jmax_us = load = None
            loads[s.bus] = loads.get(s.bus, 0.0) + _bus_share(
                load, s.count, span, seconds * 100.0, bus_spans.get(s.bus, 0.0)
            )
            ids.append(
                {
                    "bus": s.bus,
                    "id": s.arbitration_id,
                    "id_hex": format_id(s.arbitration_id, s.is_extended_id),
                    "extended": s.is_extended_id,
                    "name": s.name,
                    "count": s.count,
                    "malformed": s.malformed,
                    "rate_hz": rate,
                    "period_ms": period_ms,
                    "jitter_std_us": std_us,
                    "jitter_max_us": jmax_us,
                    "payload_bytes": s.payload,
                    "worst_case_bits": bits,
                    "frame_time_us": seconds * 1e6,
                    "load_percent": load,
                }
            )
        buses = {}
        for name in sorted(self._buses, key=_bus_sort_key):
            b = self._buses[name]
            load = loads.get(name, 0.0)
            span = b.last - b.first
            buses[name] = {
                "duration": span,
                "frames": b.frames,
                "load_percent": load,
                "actual_load_percent": (
                    (b.actual_bits / self.bitrate + b.actual_fd_s) / span * 100.0
                    if span > 0
                    else None
                ),
                # the truth channel exists only in simulation: no bus, no budget
                "over_limit": name != "truth" and load > LOAD_LIMIT * 100.0,
                "unknown_ids": len(b.unknown_ids),
                "unknown_frames": b.unknown_frames,
                "malformed": b.malformed,
                "error_frames": b.errors,
                "remote_frames": b.remote,
            }
        any_frames = self.last >= self.first
        return {
            "bitrate": self.bitrate,
            "load_limit_percent": LOAD_LIMIT * 100.0,
            "frames": sum(self.counts.values()),
            **{kind.value: n for kind, n in self.counts.items()},
            "start": self.first if any_frames else None,
            "end": self.last if any_frames else None,
            "duration": self.last - self.first if any_frames else None,
            "ids": ids,
            "unlisted_frames": self.unlisted,
            "buses": buses,
            # Gaps in the cycle counters (lost frames): per counter, the number of jumps and
            # of counts missing: SYNC.sync_counter (CiA 301, 1..240), DRIVE_RPDO1.cycle.
            "counter_gaps": self.gaps,
            # The same per channel and sender (two channels logging the same frames, or a
            # counter sent by two nodes, each checked on its own).
            "counter_gaps_by_channel": self.gaps_by_channel,
        }


def compute_stats(
    frames: Iterable[can.Message | DecodedFrame], bitrate: int = 1_000_000
) -> dict[str, Any]:
    """Per-ID timing and per-bus worst-case load of ``frames`` (streamed); see
    :meth:`StatsAccumulator.result` for the keys."""
    acc = StatsAccumulator(bitrate)
    for frame in frames:
        acc.add(frame)
    return acc.result()


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def format_stats(stats: Mapping[str, Any]) -> str:
    """Human-readable text of a :func:`compute_stats` result."""
    lines = [
        f"{'bus':<7}  {'id':<8}  {'name':<12}  {'count':>8}  {'rate/Hz':>9}  "
        f"{'period/ms':>9}  {'jit.std/us':>10}  {'jit.max/us':>10}  {'bytes':>5}  "
        f"{'frame/us':>8}  {'load/%':>6}"
    ]
    for s in stats["ids"]:
        name = s["name"] or "UNKNOWN"
        if s["malformed"]:
            name += f" ({s['malformed']} malformed)"
        lines.append(
            f"{s['bus']:<7}  {s['id_hex']:<8}  {name:<12}  {s['count']:>8}  "
            f"{_fmt(s['rate_hz'], '9.2f')}  {_fmt(s['period_ms'], '9.4f')}  "
            f"{_fmt(s['jitter_std_us'], '10.2f')}  {_fmt(s['jitter_max_us'], '10.2f')}  "
            f"{s['payload_bytes']:>5}  {s['frame_time_us']:>8.1f}  "
            f"{_fmt(s['load_percent'], '6.2f')}"
        )
    kbit = stats["bitrate"] / 1000
    for bus, b in stats["buses"].items():
        flag = f"  OVER THE {stats['load_limit_percent']:.0f} % BUDGET" if b["over_limit"] else ""
        if bus == "truth":
            flag = "  (the simulation's ground truth, not a bus: no budget)"
        extras = [f"unknown IDs {b['unknown_ids']} ({b['unknown_frames']} frames)"]
        if b["malformed"]:
            extras.append(f"malformed {b['malformed']}")
        if b["error_frames"]:
            extras.append(f"error frames {b['error_frames']}")
        if b["remote_frames"]:
            extras.append(f"remote frames {b['remote_frames']}")
        lines.append(
            f"bus {bus}: {b['duration']:.6f} s, {b['frames']} frames, worst-case load "
            f"{b['load_percent']:.1f} % of {kbit:g} kbit/s{flag}, actual "
            f"{_fmt(b.get('actual_load_percent'), '.1f')} %; {', '.join(extras)}"
        )
    if stats.get("unlisted_frames"):
        lines.append(
            f"{stats['unlisted_frames']} frames of identifiers beyond the first {MAX_IDS} not "
            "listed (counted in their bus's frames and actual load only)"
        )
    for g in stats.get("counter_gaps_by_channel", []):
        lines.append(
            f"cycle counter {g['counter']} on {g['bus']} from {g['sender']}: {g['frames']} "
            f"frames, {g['missing']} lost ({g['gaps']} gaps), {g['reordered']} reordered, "
            f"{g['repeats']} duplicated"
        )
    return "\n".join(lines)
