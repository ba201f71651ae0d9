"""Bus faults: a lossy, late, noisy CAN link, reproducibly, every fault recorded.

:class:`BusFaults` (one channel's part of a scenario's ``[faults]`` table, see
:mod:`hdhil.rig.faults`) says what goes wrong on the wire; a :class:`ChannelFaults` hook
makes it happen from the run's fault seed inside the simulated bus
(:meth:`hdhil.can.simbus._Channel.flush`), so every node sees the faults exactly as it
would see a bad link. On any other interface a node puts its own transmissions through
the same hook (:class:`FaultyTransmitBus`), and the drive silences itself through
:class:`TransmitSilence` (its object 0x2310 sub 8). Each fault is one record in the
run's :class:`~hdhil.core.faultbase.FaultLog`.

The sensor faults are the plant's, in :mod:`hdhil.hostsim.sensor_faults`.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import can

from hdhil.core.dataconf import ConfigError
from hdhil.core.faultbase import (
    FaultLog,
    FaultRecord,
    check_nonneg,
    check_rate,
    fault_rng,
)
from hdhil.core.numbers import MAX_SECONDS
from hdhil.dbc import node_function_codes

__all__ = [
    "BusFaults",
    "ChannelFaults",
    "ChannelTables",
    "FaultLog",
    "FaultRecord",
    "FaultyTransmitBus",
    "NodeWindow",
    "TransmitSilence",
    "check_node_transmit_faults",
    "node_ids",
]


#: Tolerance of time comparisons (s): k * Ts and a sum of periods may differ by rounding.
_TIME_EPSILON = 1e-9


def node_ids(node: int) -> frozenset[int]:
    """The COB-IDs CANopen node ``node`` transmits (its default communication objects)."""
    return frozenset(base + node for base in node_function_codes("control"))


#: Largest ``delay_us`` / ``jitter_us`` accepted (1 s).
MAX_DELAY_US = 1e6


@dataclass(frozen=True)
class NodeWindow:
    """A node that stops transmitting: from ``start_s`` for ``duration_s`` (``inf`` =
    for good).  The node is ``node`` (every frame it sends; see the module docstring)
    and/or the ``ids`` listed (whoever sends them)."""

    start_s: float
    duration_s: float = field(default=math.inf, metadata={"allow_inf": True})
    node: int = 0
    ids: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        check_nonneg(self, "start_s", hi=MAX_SECONDS)
        check_nonneg(self, "duration_s", allow_inf=True, hi=MAX_SECONDS)
        if not 0 <= self.node <= 127:
            raise ValueError(
                f"NodeWindow.node must be a node-ID 1..127 (0 = none), got {self.node}"
            )
        if self.node == 0 and not self.ids:
            raise ValueError("NodeWindow needs a node or ids")
        for i in self.ids:
            if not 0 <= i < (1 << 29):
                raise ValueError(f"NodeWindow.ids: not a CAN identifier: {i!r}")

    @property
    def cob_ids(self) -> frozenset[int]:
        return (node_ids(self.node) if self.node else frozenset()) | frozenset(self.ids)

    def active(self, t: float) -> bool:
        return self.start_s <= t < self.start_s + self.duration_s


@dataclass(frozen=True)
class BusFaults:
    """What goes wrong on one CAN channel, in simulated time.

    The simulated bus stamps a frame with the end of its transmission; in lockstep a
    frame is receivable only once the simulated clock has reached its delivery time
    (:class:`hdhil.can.simbus.SimClock`): deliveries due before the end of the current
    cycle (the next SYNC) are handed out in that cycle, in delivery-time order, later
    ones in the cycle that contains their time.  Nodes answer a frame at the time they
    received it.

    - ``loss_rate`` / bursts: the frame goes on the wire (it takes its time) but no node
      receives it.
    - ``silence`` / ``bus_off``: the node's frames never reach the wire (no wire time).
      ``node = n`` is the node by who sends: every frame node n transmits (a master's
      SYNC, RPDOs, NMT and SDO requests included), known from the simulated bus handle
      the frame was sent through (``SimBus(node_id=...)``: every node of ``hdhil run``
      has one, on the control and the truth channel) or from the node process's own bus
      (:class:`FaultyTransmitBus`).  A frame from a handle without a node-ID (a tool) is
      node n's when its identifier is one of node n's own COB-IDs (EMCY/TPDO1/TPDO2/SDO
      response/heartbeat: 0x080+n, 0x180+n, 0x280+n, 0x580+n, 0x700+n;
      :func:`hdhil.dbc.node_function_codes`).  ``ids`` lists identifiers explicitly,
      whoever sends them.
    - ``delay_us`` + uniform ``jitter_us``: added to the delivery time.  A frame that
      stays before the next SYNC is received later in the same cycle (and answered
      later); one pushed past it is received in the next cycle, after that SYNC, as on a
      real bus: the controller then counts a cycle without its sensor frame and a second
      one in the next cycle (the interrupt runs once per SYNC).  The wire is not held up
      by a delay, and the cycles stay ``k * Ts``: timestamps are simulated time whatever
      the delay.
    - ``duplicate_rate``: the frame is sent twice (the copy takes wire time again).
    - ``reorder_rate``: the frame is held back and delivered right after the next frame
      of the channel (the two swap timestamps, so receive times stay monotonic); when
      that next frame is the next cycle's SYNC, the held frame arrives a cycle late.
    - ``corrupt_rate``: one random payload bit flipped (an error the CRC missed);
      ``dlc_rate``: the payload truncated or extended by 1-8 bytes (random bytes);
      ``error_frame_rate``: a python-can error frame follows the frame.

    On any other interface (``hdhil run --interface virtual`` or ``udp_multicast``, and
    ``hdhil emulate``/``firmware`` on any bus) there is no simulated channel between the
    nodes: each node puts its own transmissions through the faults
    (:class:`FaultyTransmitBus`, with its own random draws), timed by the run's clock
    (the cycle time ``k * Ts`` in network lockstep) or the process's monotonic clock;
    error frames are refused there (a node cannot send one).  Truth faults act on the
    truth channel of ``hdhil run`` and ``emulate``; the evaluation then scores only the
    samples whose truth arrived and reports how many had none.
    """

    loss_rate: float = 0.0
    burst_every_s: float = 0.0
    burst_len_frames: int = 0
    delay_us: float = 0.0
    jitter_us: float = 0.0
    duplicate_rate: float = 0.0
    reorder_rate: float = 0.0
    corrupt_rate: float = 0.0
    dlc_rate: float = 0.0
    error_frame_rate: float = 0.0
    silence: tuple[NodeWindow, ...] = ()
    bus_off: tuple[NodeWindow, ...] = ()

    def __post_init__(self) -> None:
        for name in ("loss_rate", "duplicate_rate", "reorder_rate", "corrupt_rate",
                     "dlc_rate", "error_frame_rate"):  # fmt: skip
            check_rate(self, name)
        check_nonneg(self, "burst_every_s", hi=MAX_SECONDS)
        # At most a second late: later than the nodes' supervision times (heartbeat,
        # sensor hold) is a lost frame, which loss_rate/silence describe.
        for name in ("delay_us", "jitter_us"):
            check_nonneg(self, name, hi=MAX_DELAY_US)
        check_nonneg(self, "burst_len_frames")
        if (self.burst_every_s > 0) != (self.burst_len_frames > 0):
            raise ValueError("BusFaults.burst_len_frames and burst_every_s go together "
                             "(both > 0 or both 0)")  # fmt: skip

    @property
    def enabled(self) -> bool:
        return self != BusFaults()


class ChannelFaults:
    """The bus-fault hook of one simbus channel (``SimBus(..., faults=...)``)."""

    def __init__(self, cfg: BusFaults, name: str, seed: int, log: FaultLog,
                 stream: str = "") -> None:  # fmt: skip
        """``stream`` separates the random draws of hooks that share a seed and a channel
        name (the transmissions of two nodes in two processes); "" in lockstep."""
        self.cfg = cfg
        self.name = name
        self.log = log
        where = f"{stream}:{name}" if stream else name
        r = {k: fault_rng(seed, where, k) for k in ("loss", "delay", "duplicate", "reorder",
                                                "corrupt", "dlc", "error_frame")}  # fmt: skip
        self._r = r
        self._next_burst = cfg.burst_every_s if cfg.burst_len_frames else math.inf
        self._burst_left = 0
        self._silence = [(w, w.cob_ids) for w in cfg.silence]
        self._bus_off = [(w, w.cob_ids) for w in cfg.bus_off]
        self._held: can.Message | None = None  # a frame waiting to be reordered

    @property
    def held(self) -> can.Message | None:
        """The frame held back for reordering (delivered after the channel's next one)."""
        return self._held

    def blocked(self, msg: can.Message, t: float, sender: int | None = None) -> bool:
        """True when the sender of ``msg`` is silent or bus-off at ``t`` (frame dropped
        before the wire; logged).

        ``sender`` is the node-ID of the node that sent ``msg`` when it is known (the
        simbus handle's ``node_id``, a node process's own bus): a window of ``node = n``
        then stops every frame node n sends, whatever its identifier.  Without it, the
        frame is node n's when its identifier is one of node n's own COB-IDs
        (:func:`node_ids`).  A window's ``ids`` match by identifier, whoever sends."""
        fid = msg.arbitration_id
        for kind, windows in (("silence", self._silence), ("bus_off", self._bus_off)):
            for w, ids in windows:
                if sender is not None and w.node:
                    hit = sender == w.node or fid in w.ids
                else:
                    hit = fid in ids
                if hit and w.active(t):
                    self.log.record(t, self.name, kind, msg.arbitration_id)
                    return True
        return False

    def transmit(self, msg: can.Message, end: float, frame_s: float
                 ) -> tuple[list[can.Message], float]:  # fmt: skip
        """The frames receivers get for ``msg`` sent on the wire until ``end`` (each
        with its delivery timestamp), and the time the wire is busy until."""
        cfg, r, log, name = self.cfg, self._r, self.log, self.name
        fid = msg.arbitration_id
        busy = end
        if cfg.burst_len_frames:
            if end >= self._next_burst:
                self._burst_left = cfg.burst_len_frames
                while self._next_burst <= end:
                    self._next_burst += cfg.burst_every_s
            if self._burst_left:
                self._burst_left -= 1
                log.record(end, name, "burst_loss", fid)
                return [], busy
        if cfg.loss_rate and r["loss"].random() < cfg.loss_rate:
            log.record(end, name, "loss", fid)
            return [], busy
        if cfg.corrupt_rate and r["corrupt"].random() < cfg.corrupt_rate and msg.data:
            data = bytearray(msg.data)
            bit = r["corrupt"].randrange(8 * len(data))
            data[bit >> 3] ^= 1 << (bit & 7)
            log.record(end, name, "corrupt", fid, bit=bit)
            msg = _copy(msg, bytes(data))
        if cfg.dlc_rate and r["dlc"].random() < cfg.dlc_rate:
            n = len(msg.data)
            choices = [k for k in range(9) if k != n]
            k = r["dlc"].choice(choices)
            data = bytes(msg.data[:k]) + bytes(r["dlc"].randrange(256) for _ in range(k - n))
            log.record(end, name, "wrong_dlc", fid, dlc=n, new_dlc=k)
            msg = _copy(msg, data)
        if cfg.delay_us or cfg.jitter_us:
            extra = (cfg.delay_us + cfg.jitter_us * r["delay"].random()) * 1e-6
            if extra > 0:
                log.record(end, name, "delay", fid, delay_us=extra * 1e6)
                end += extra
        msg.timestamp = end
        out = [msg]
        if cfg.duplicate_rate and r["duplicate"].random() < cfg.duplicate_rate:
            dup = _copy(msg, bytes(msg.data))
            busy += frame_s
            dup.timestamp = end + frame_s
            log.record(end, name, "duplicate", fid)
            out.append(dup)
        if cfg.error_frame_rate and r["error_frame"].random() < cfg.error_frame_rate:
            err = can.Message(is_error_frame=True, arbitration_id=0, dlc=0, channel=msg.channel,
                              is_rx=True, timestamp=out[-1].timestamp, check=False)  # fmt: skip
            log.record(end, name, "error_frame", fid)
            out.append(err)
        if cfg.reorder_rate:
            held = self._held
            if held is not None:
                # The held frame comes after this one: swap their stamps.
                self._held = None
                held.timestamp, out[0].timestamp = out[0].timestamp, held.timestamp
                out.insert(1, held)
            elif r["reorder"].random() < cfg.reorder_rate:
                self._held = out.pop(0)
                log.record(end, name, "reorder", fid)
        return out, busy


def _copy(msg: can.Message, data: bytes) -> can.Message:
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       is_remote_frame=msg.is_remote_frame, dlc=len(data), data=data,
                       channel=msg.channel, is_rx=True, timestamp=msg.timestamp,
                       check=False)  # fmt: skip


# ----------------------------------------------------------------------------- one node
class FaultyTransmitBus:
    """A node's python-can bus whose *own* transmissions go through a channel's faults.

    For a node in a process of its own on a real or networked bus (``hdhil emulate`` /
    ``hdhil firmware``), where no simulated channel sits between the nodes: each frame the
    node sends meets the :class:`ChannelFaults` of its channel as it would on the
    simulated bus, with the time counted from the node's start on ``clock``.  Lost and
    silenced frames are not sent; a corrupted or wrong-DLC frame is sent as modified; a
    duplicate is sent twice; a delayed frame waits in a queue and goes out at its time
    from the next ``send``/``recv`` (the node's loop calls ``recv`` at least every few
    milliseconds; a ``recv`` never blocks past a queued frame's time); a reordered frame
    goes out after the next one.  A node cannot transmit error frames (its CAN controller
    raises them), so ``error_frame_rate`` is refused (:func:`check_node_transmit_faults`).

    ``node_id`` is the node's CANopen node-ID: a ``silence``/``bus_off`` window of that
    node stops every frame it sends (SYNC, RPDOs, NMT and SDO requests of a master
    included); None judges frames by their identifiers (:meth:`ChannelFaults.blocked`).

    Everything else (``recv``, ``shutdown``, ``channel_info``, ...) is the wrapped bus.
    """

    def __init__(self, bus: can.BusABC, hook: ChannelFaults,
                 clock: Callable[[], float] = time.monotonic,
                 node_id: int | None = None) -> None:  # fmt: skip
        self.bus = bus
        self.hook = hook
        self.node_id = node_id
        self._clock = clock
        self._t0 = clock()
        self._due: list[tuple[float, int, can.Message]] = []
        self._seq = itertools.count()

    def __getattr__(self, name: str) -> Any:
        if name == "bus":  # not set yet (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.bus, name)

    def _now(self) -> float:
        return self._clock() - self._t0

    def _release(self, now: float) -> None:
        due = self._due
        while due and due[0][0] <= now:
            self.bus.send(heapq.heappop(due)[2])

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        now = self._now()
        self._release(now)
        if self.hook.blocked(msg, now, self.node_id):
            return
        frame = can.Message(arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                            is_remote_frame=msg.is_remote_frame, dlc=msg.dlc,
                            data=bytes(msg.data), check=False)  # fmt: skip
        out, _ = self.hook.transmit(frame, now, 0.0)
        for m in out:
            m.is_rx = False
            if m.timestamp <= now:
                self.bus.send(m, timeout)
            else:
                heapq.heappush(self._due, (m.timestamp, next(self._seq), m))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self._release(self._now())
        if self._due:
            wait = max(0.0, self._due[0][0] - self._now())
            timeout = wait if timeout is None else min(timeout, wait)
        msg = self.bus.recv(timeout)
        self._release(self._now())
        return msg

    def flush(self) -> None:
        """Send every queued (delayed) frame now, e.g. before the bus shuts down."""
        while self._due:
            self.bus.send(heapq.heappop(self._due)[2])


class ChannelTables(Protocol):
    """The faults of both channels: a run's :class:`hdhil.rig.faults.FaultConfig`."""

    @property
    def control(self) -> BusFaults: ...

    @property
    def truth(self) -> BusFaults: ...


def check_node_transmit_faults(config: ChannelTables, role: Literal["control", "truth"]) -> None:
    """``ConfigError`` if channel ``role`` has faults a single node cannot put on its own
    transmissions (:class:`FaultyTransmitBus`)."""
    cfg: BusFaults = getattr(config, role)
    if cfg.error_frame_rate:
        raise ConfigError(
            f"faults.{role}.error_frame_rate: a node cannot transmit error frames (its CAN "
            "controller raises them): set it to 0 here, and inject them on the simulated "
            "bus with hdhil run"
        )


class TransmitSilence:
    """A node that stops transmitting for a while (the drive's object 0x2310 sub 8).

    While a silence lasts, every frame the node sends on ``bus`` (PDOs, heartbeat, EMCY,
    SDO answers) is dropped before the wire and logged as ``silence`` on ``channel``, as
    a :class:`NodeWindow` of the simulated bus would.  The silence shadows the bus object's
    ``send`` only while it lasts (restored at the first send after its end, or by
    :meth:`stop`), so a node that is not silenced sends exactly as before, at no cost.
    ``clock()`` is the node's time (simulated time in lockstep).
    """

    def __init__(self, bus: Any, log: FaultLog, channel: str, clock: Callable[[], float]) -> None:
        self.bus = bus
        self.log = log
        self.channel = channel
        self._clock = clock
        self.until = -math.inf
        self._shadowed: tuple[bool, Any] | None = None  # (had an own ``send``, that send)
        self._send: Callable[..., None] = bus.send

    @property
    def active(self) -> bool:
        return self._shadowed is not None

    def start(self, duration_s: float) -> None:
        """Silence from now for ``duration_s`` (0 ends a silence at once)."""
        if duration_s <= 0:
            self.stop()
            return
        self.until = self._clock() + duration_s
        if self._shadowed is None:
            own = self.bus.__dict__
            self._shadowed = ("send" in own, own.get("send"))
            self._send = self.bus.send
            self.bus.send = self._silenced

    def stop(self) -> None:
        """End the silence: the bus's own ``send`` is back."""
        if self._shadowed is None:
            return
        had_own, own = self._shadowed
        self._shadowed = None
        if had_own:
            self.bus.send = own
        else:
            del self.bus.send
        self.until = -math.inf

    def _silenced(self, msg: can.Message, timeout: float | None = None) -> None:
        now = self._clock()
        if now >= self.until - _TIME_EPSILON:
            send = self._send
            self.stop()
            send(msg, timeout)
            return
        self.log.record(now, self.channel, "silence", msg.arbitration_id)
