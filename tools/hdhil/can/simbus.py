"""A deterministic, simulated-time CAN bus that plugs into python-can as interface ``simbus``.

python-can's own ``virtual`` interface stamps frames with wall-clock time and deep-copies
every frame for every receiver.  Lockstep runs need the opposite: simulated timestamps,
bit-identical delivery order, and a bus that behaves like a real 1 Mbit/s wire.
``SimBus`` is an ordinary :class:`can.BusABC`, so nodes written against python-can run on
it unchanged, and on SocketCAN, PCAN, ``virtual`` or ``udp_multicast`` just the same.

Timing: a node requests a frame at the clock's time (or when it received the frame it
answers); when the wire is free every frame requested by then competes and the lowest
identifier wins; the frame is delivered, timestamped, at the end of its exact bit time
(:mod:`hdhil.can.bittiming`; ``timing="worst-case"`` for docs/design.md's budget,
``bitrate=0`` for untimed delivery, as on the truth channel).  With a fault hook
(``faults``, :mod:`hdhil.can.faults`) a frame is receivable only once the simulated
clock reaches its delivery time, so a frame delayed past the next SYNC arrives in the
next cycle; without one the channel keeps its fault-free path.  ``node_id`` names the
node that owns a handle, so a silence or bus-off of that node stops all it sends.

Delivery: one :class:`can.Message` per sent frame is queued for every other bus on the
channel (and for the sender with ``receive_own_messages``); receivers must not mutate it.
"""

from __future__ import annotations

import heapq
import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import can

from hdhil.can.bittiming import frame_bits, frame_seconds
from hdhil.dbc import worst_case_frame_bits

if TYPE_CHECKING:
    from hdhil.can.faults import ChannelFaults


class SimClock:
    """Simulated time in seconds, advanced by whoever paces the run (the lockstep runner).

    ``now`` is the start of the current step (a lockstep cycle starts at ``k * Ts``);
    ``horizon`` is where the step ends (``(k + 1) * Ts``): a channel with a fault hook
    holds back every delivery due at or after it (a frame delayed past the next SYNC)
    until a later step reaches its time.  ``inf`` (the default): nothing is held, every
    delivery is handed out at the next poll.
    """

    __slots__ = ("horizon", "now")

    def __init__(self, now: float = 0.0, horizon: float = math.inf) -> None:
        self.now = now
        self.horizon = horizon


class _Channel:
    __slots__ = ("_held_sender", "bitrate", "buses", "busy_until", "clock", "data_bitrate",
                 "delivered",
                 "faults", "frames", "inflight", "label", "latest_request", "lock", "name",
                 "pending", "receivers", "seq", "timing", "waiting")  # fmt: skip

    def __init__(self, name: str, clock: SimClock, bitrate: int, label: str | int,
                 timing: str, data_bitrate: int | None = None) -> None:  # fmt: skip
        self.name = name
        self.label = label
        self.clock = clock
        self.bitrate = bitrate
        #: The data phase's bit rate of FD frames with bit-rate switching (None: the
        #: nominal one).
        self.data_bitrate = data_bitrate
        self.timing = timing if bitrate else "none"
        self.busy_until = 0.0
        self.buses: list[SimBus] = []
        #: For each sender, the buses its frames are delivered to (see :meth:`attach`).
        self.receivers: dict[SimBus, tuple[SimBus, ...]] = {}
        #: Buses blocked in ``recv`` with a timeout (they wait on the channel's lock).
        self.waiting = 0
        self.frames = 0
        self.lock = threading.Lock()
        # Frames requested but not yet on the wire: (arbitration key, sequence, request
        # time, sender, msg); the key orders frames as arbitration does, the sequence
        # number keeps requests of equal identifiers in order.
        self.pending: list[_Pending] = []
        self.seq = 0
        #: The latest request time among the frames requested so far (only ever grows).
        self.latest_request = 0.0
        #: Fault injection hook (:class:`hdhil.can.faults.ChannelFaults`); None = a clean link.
        self.faults: ChannelFaults | None = None
        #: With a fault hook: deliveries off the wire, not yet handed to the receivers, as a
        #: heap of (delivery time, order, sender, frame); due ones go out at the next poll,
        #: the others when the clock's horizon has passed their time.  Always empty
        #: without a hook.
        self.inflight: list[tuple[float, int, SimBus, can.Message]] = []
        #: The sender of the frame the fault hook holds back for reordering.
        self._held_sender: SimBus | None = None
        #: Deliveries made so far (the order of equal delivery times).
        self.delivered = 0

    def attach(self, bus: SimBus) -> None:
        self.buses.append(bus)
        self._route()

    def detach(self, bus: SimBus) -> None:
        if bus in self.buses:
            self.buses.remove(bus)
        self._route()

    def _route(self) -> None:
        """Every other bus receives a sender's frames; the sender too with
        ``receive_own_messages``."""
        self.receivers = {
            sender: tuple(b for b in self.buses if b is not sender or b._receive_own)
            for sender in self.buses
        }

    def notify_waiting(self) -> None:
        """Wake the buses blocked in ``recv`` (caller holds the lock)."""
        for bus in self.buses:
            if bus._waiting:
                bus._ready.notify()

    def bits(self, msg: can.Message) -> int:
        length = 0 if msg.is_remote_frame else len(msg.data)
        if self.timing == "exact" and not msg.is_error_frame:
            return frame_bits(msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                              bytes(msg.data))  # fmt: skip
        return worst_case_frame_bits(length, msg.is_extended_id)

    def flush(self) -> None:
        """Put every requested frame on the wire, in bus order (caller holds the lock).

        When the wire becomes free, every frame requested by then competes and the lowest
        identifier wins arbitration (an extended frame loses to a base frame with the same
        11 leading bits); if none is waiting, the frames of the earliest request time
        start together and arbitrate the same way.
        """
        if self.faults is not None:
            self._flush_faulty(self.faults)
            return
        pending = self.pending
        timing = self.timing
        exact = timing == "exact"
        while pending:
            free = self.busy_until
            if len(pending) == 1:  # the common case: nothing to arbitrate
                item = pending.pop()
                start = free if item[2] <= free else item[2]
            elif self.latest_request <= free:
                # Every frame was requested before the wire frees up: they go in
                # arbitration order, which is what _next would pick one by one.
                pending.sort(reverse=True)
                item = pending.pop()
                start = free
            else:
                start, item = self._next()
            msg = item[4]
            if exact and not msg.is_error_frame:  # the snapshot's data is bytes (hashable)
                if msg.is_fd:
                    end = start + frame_seconds(msg, self.bitrate, self.data_bitrate)
                else:
                    bits = frame_bits(msg.arbitration_id, msg.is_extended_id,
                                      msg.is_remote_frame, msg.data)  # fmt: skip
                    end = start + bits / self.bitrate
            elif timing != "none":
                end = start + self.bits(msg) / self.bitrate
            else:
                end = start
            self.busy_until = msg.timestamp = end  # the sender's snapshot is the received frame
            self.frames += 1
            for bus in self.receivers[item[3]]:
                bus._queue.append(msg)
                bus._last_rx = end
        if self.waiting:
            self.notify_waiting()

    def deliver_now(
        self, frame: can.Message, requested: float, receivers: tuple[SimBus, ...]
    ) -> None:
        """Deliver ``frame`` at once (a channel with no wire to share: ``timing`` "none"
        and no fault hook), after whatever it delivered before, in the order sent
        (caller holds the lock)."""
        end = requested if requested > self.busy_until else self.busy_until
        self.busy_until = frame.timestamp = end
        self.frames += 1
        for bus in receivers:
            bus._queue.append(frame)
            bus._last_rx = end

    def _next(self) -> tuple[float, _Pending]:
        """Take the frame that goes on the wire next, and when it starts: when the wire
        frees up, the lowest identifier among the frames requested by then wins
        arbitration; if none is waiting, the frames of the earliest request time start
        together when it comes, and the lowest identifier among them wins."""
        pending = self.pending
        free = self.busy_until
        ready = [p for p in pending if p[2] <= free]
        if ready:
            item = min(ready)  # (arbitration key, sequence): unique, never compares further
            start = free
        else:
            start = min(pending, key=_request_key)[2]
            item = min(p for p in pending if p[2] == start)
        pending.remove(item)
        return start, item

    def _flush_faulty(self, faults: ChannelFaults) -> None:
        """:meth:`flush` through the fault hook: frames of a silent/bus-off sender never
        reach the wire; the others may be lost, delayed, duplicated, reordered,
        corrupted, resized or followed by an error frame.

        Every delivery goes in flight with its delivery time; those due before the
        clock's horizon are handed out now, in delivery-time order; later ones wait for
        the step that contains their time (:meth:`release`), so a frame delayed past the
        next SYNC reaches its receivers after that SYNC, as on a real bus."""
        inflight = self.inflight
        while self.pending:
            start, (_, _, _, sender, msg) = self._next()
            if faults.blocked(msg, start, sender.node_id):
                continue
            frame_s = self.bits(msg) / self.bitrate if self.timing != "none" else 0.0
            end = start + frame_s
            self.frames += 1
            held = faults.held  # a frame held back for reordering, sent by _held_sender
            delivered, self.busy_until = faults.transmit(msg, end, frame_s)
            for m in delivered:
                self.delivered += 1
                # A reordered frame comes out after another sender's frame: it is still
                # its own sender's, which every other node receives (that sender included
                # only with receive_own_messages), not the frame that released it.
                origin = self._held_sender if held is not None and m is held else sender
                heapq.heappush(inflight, (m.timestamp, self.delivered, origin, m))
            if faults.held is not None and faults.held is not held:
                self._held_sender = sender
        self.release()

    def release(self) -> None:
        """Hand out the in-flight deliveries due before the clock's horizon, in
        delivery-time order (caller holds the lock)."""
        inflight = self.inflight
        horizon = self.clock.horizon
        receivers = self.receivers
        released = False
        while inflight and inflight[0][0] < horizon:
            _, _, sender, msg = heapq.heappop(inflight)
            released = True
            # A receiver's answer time moves when it takes the frame (recv/dispatch), not
            # now: a node answering the first of several frames released together answers
            # at that frame's time, not at the last one's.
            for bus in receivers.get(sender, ()):
                bus._queue.append(msg)
        if released and self.waiting:
            self.notify_waiting()


_Pending = tuple[int, int, float, "SimBus", can.Message]


def arbitration_key(arbitration_id: int, extended: bool) -> int:
    """Orders identifiers as bitwise arbitration does (lower wins): the identifier bits on
    the wire, the 11 base bits first, then (extended frames) SRR/IDE recessive, then the
    18 extension bits; so an extended frame loses to a base frame with the same 11 bits."""
    if extended:
        return ((arbitration_id >> 18) << 1 | 1) << 18 | (arbitration_id & 0x3FFFF)
    return (arbitration_id << 1) << 18


def _request_key(item: _Pending) -> tuple[float, int]:
    return item[2], item[1]


#: The fields of a :class:`can.Message`; :func:`received_copy` fills every one of them.
_MESSAGE_FIELDS = frozenset(
    ("arbitration_id", "bitrate_switch", "channel", "data", "dlc", "error_state_indicator",
     "is_error_frame", "is_extended_id", "is_fd", "is_remote_frame", "is_rx", "timestamp")
)  # fmt: skip
_new_message = object.__new__


def _snapshot_fast(msg: can.Message, channel: Any) -> can.Message:
    """The received copy of a sent frame, built field by field: a quarter of the cost of
    :class:`can.Message`'s constructor, which re-validates what the sender already built."""
    frame = _new_message(can.Message)
    frame.timestamp = 0.0
    frame.arbitration_id = msg.arbitration_id
    frame.is_extended_id = msg.is_extended_id
    frame.is_remote_frame = msg.is_remote_frame
    frame.is_error_frame = msg.is_error_frame
    frame.channel = channel
    frame.dlc = msg.dlc
    frame.data = bytes(msg.data)
    frame.is_fd = msg.is_fd
    frame.is_rx = True
    frame.bitrate_switch = msg.bitrate_switch
    frame.error_state_indicator = msg.error_state_indicator
    return frame


def _snapshot_checked(msg: can.Message, channel: Any) -> can.Message:
    return can.Message(
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame,
        dlc=msg.dlc,
        data=bytes(msg.data),
        channel=channel,
        is_fd=msg.is_fd,
        is_rx=True,
        bitrate_switch=msg.bitrate_switch,
        error_state_indicator=msg.error_state_indicator,
        check=False,
    )


#: The field-by-field copy only while python-can's Message has exactly these fields; a
#: python-can that adds one gets the constructor (slower, always complete).  The copy is
#: a received frame (``is_rx``) on ``channel``, timestamp 0 until it is delivered.
received_copy = (
    _snapshot_fast
    if set(getattr(can.Message, "__slots__", ())) - {"__weakref__"} == _MESSAGE_FIELDS
    else _snapshot_checked
)

#: Whether :meth:`SimBus.send` copies a frame field by field (as :func:`_snapshot_fast`).
_FAST_COPY = received_copy is _snapshot_fast

_channels: dict[str, _Channel] = {}
_channels_lock = threading.Lock()


class SimBus(can.BusABC):
    """One node's connection to a simulated CAN channel (python-can interface ``simbus``)."""

    def __init__(
        self,
        channel: Any = "control",
        bitrate: int = 1_000_000,
        receive_own_messages: bool = False,
        clock: SimClock | None = None,
        trace_channel: int | None = None,
        timing: str = "exact",
        faults: ChannelFaults | None = None,
        node_id: int | None = None,
        data_bitrate: int | None = None,
        **kwargs: Any,
    ) -> None:
        name = str(channel)
        if bitrate < 0:
            raise ValueError(f"simbus bitrate must be >= 0, got {bitrate}")
        with _channels_lock:
            ch = _channels.get(name)
            if ch is None:
                label = name if trace_channel is None else trace_channel
                if timing not in ("exact", "worst-case"):
                    raise ValueError(
                        f"simbus timing must be 'exact' or 'worst-case', got {timing!r}"
                    )
                ch = _Channel(name, clock or SimClock(), bitrate, label, timing, data_bitrate)
                _channels[name] = ch
            elif clock is not None and clock is not ch.clock:
                raise ValueError(f"simbus channel {name!r} already runs on another clock")
            if faults is not None:
                if ch.faults is not None and ch.faults is not faults:
                    raise ValueError(f"simbus channel {name!r} already has other faults")
                if ch.faults is None:
                    ch.faults = faults
                    for bus in ch.buses:
                        bus._use_fault_path()
            self._ch = ch
            self._queue: deque[can.Message] = deque()
            self._ready = threading.Condition(ch.lock)
            self._receive_own = receive_own_messages
            self._waiting = False
            self._last_rx = 0.0
            #: The CANopen node-ID of the node that sends through this handle (None: not
            #: known); silence and bus-off windows of that node stop all its frames.
            self.node_id = node_id
            if ch.faults is not None:
                self._use_fault_path()
            with ch.lock:  # a frame in flight is routed to the old set or the new one
                ch.attach(self)
        self.channel_info = f"simbus channel {name!r} at {ch.bitrate} bit/s"
        super().__init__(channel=name, **kwargs)

    @property
    def clock(self) -> SimClock:
        return self._ch.clock

    @property
    def trace_channel(self) -> str | int:
        """The channel received frames carry (``msg.channel``)."""
        return self._ch.label

    @property
    def frames_requested(self) -> int:
        """Frames requested (``send``) on the whole channel since it was created."""
        return self._ch.seq

    @property
    def frames_sent(self) -> int:
        """Frames sent on the whole channel since it was created."""
        return self._ch.frames

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Request transmission.  The request time is the clock's time, or later if this
        node has received a frame since (it cannot answer a frame before receiving it)."""
        ch = self._ch
        # A private snapshot: callers may reuse their Message object for the next frame
        # (received_copy; field by field here, as _snapshot_fast does, where it applies).
        if _FAST_COPY:
            frame = _new_message(can.Message)
            frame.timestamp = 0.0
            frame.arbitration_id = msg.arbitration_id
            frame.is_extended_id = msg.is_extended_id
            frame.is_remote_frame = msg.is_remote_frame
            frame.is_error_frame = msg.is_error_frame
            frame.channel = ch.label
            frame.dlc = msg.dlc
            frame.data = bytes(msg.data)
            frame.is_fd = msg.is_fd
            frame.is_rx = True
            frame.bitrate_switch = msg.bitrate_switch
            frame.error_state_indicator = msg.error_state_indicator
        else:
            frame = received_copy(msg, ch.label)
        with ch.lock:
            now = ch.clock.now
            requested = self._last_rx if self._last_rx > now else now
            seq = ch.seq = ch.seq + 1
            if ch.timing == "none" and ch.faults is None:
                ch.deliver_now(frame, requested, ch.receivers[self])
                if ch.waiting:
                    ch.notify_waiting()
                return
            if requested > ch.latest_request:
                ch.latest_request = requested
            key = (
                arbitration_key(frame.arbitration_id, True)
                if frame.is_extended_id
                else frame.arbitration_id << 19  # arbitration_key of a base frame
            )
            ch.pending.append((key, seq, requested, self, frame))
            if ch.waiting:
                ch.notify_waiting()

    def send_frames(self, msgs: Sequence[can.Message]) -> None:
        """Request transmission of ``msgs``, in order: what :meth:`send` does for each, in
        one call (the drive's three truth frames of a cycle)."""
        ch = self._ch
        if ch.timing != "none" or ch.faults is not None:
            for msg in msgs:
                self.send(msg)
            return
        label = ch.label
        with ch.lock:  # no wire to share: each is delivered at once, in the order sent
            now = ch.clock.now
            requested = self._last_rx if self._last_rx > now else now
            receivers = ch.receivers[self]
            deliver = ch.deliver_now
            for msg in msgs:
                ch.seq += 1
                deliver(received_copy(msg, label), requested, receivers)
            if ch.waiting:
                ch.notify_waiting()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Next received frame; without receive filters this skips python-can's generic
        filter loop (the 1 kHz path polls with ``timeout=0`` several times a cycle)."""
        ch = self._ch
        if ch.pending:
            with ch.lock:
                ch.flush()
        if self._filters is None and self._queue:
            return self._queue.popleft()
        if timeout == 0 and self._filters is None:
            return None
        return super().recv(timeout)

    def _recv_faulty(self, timeout: float | None = None) -> can.Message | None:
        """:meth:`recv` on a channel with a fault hook: in-flight deliveries that have
        come due are released too, and the answer time moves to the frame taken."""
        ch = self._ch
        if ch.pending or ch.inflight:
            with ch.lock:
                ch.flush()
        if self._filters is None and self._queue:
            msg = self._queue.popleft()
        elif timeout == 0 and self._filters is None:
            return None
        else:
            msg = super().recv(timeout)
        if msg is not None and msg.timestamp > self._last_rx:
            self._last_rx = msg.timestamp
        return msg

    def dispatch(self, handler: Callable[[can.Message], object]) -> int:
        """Hand every frame waiting for this bus (and passing its receive filters) to
        ``handler``, in order; returns how many.

        What calling ``recv(0)`` until the queue is empty and handling each frame does
        (frames requested meanwhile go on the wire before the next one is taken, so a
        handler's answers arbitrate as they would), without a method call per frame.
        """
        ch = self._ch
        queue = self._queue
        matches = None if self._filters is None else self._matches_filters
        n = 0
        while True:
            if ch.pending:
                with ch.lock:
                    ch.flush()
            if not queue:
                return n
            msg = queue.popleft()
            if matches is None or matches(msg):
                handler(msg)
                n += 1

    def _dispatch_faulty(self, handler: Callable[[can.Message], object]) -> int:
        """:meth:`dispatch` on a channel with a fault hook (see :meth:`_recv_faulty`)."""
        ch = self._ch
        queue = self._queue
        matches = None if self._filters is None else self._matches_filters
        n = 0
        while True:
            if ch.pending or ch.inflight:
                with ch.lock:
                    ch.flush()
            if not queue:
                return n
            msg = queue.popleft()
            if msg.timestamp > self._last_rx:
                self._last_rx = msg.timestamp
            if matches is None or matches(msg):
                handler(msg)
                n += 1

    def drain_into(self, frames: list[can.Message]) -> int:
        """Move every frame waiting for this bus (and passing its receive filters) to the
        end of ``frames``, in order; returns how many.

        What ``dispatch(frames.append)`` does, in one step: for a listen-only handle (the
        run's tap), whose handler requests no frame between two."""
        ch = self._ch
        if self._filters is not None or ch.faults is not None:
            return self.dispatch(frames.append)
        queue = self._queue
        with ch.lock:
            if ch.pending:
                ch.flush()
            n = len(queue)
            frames += queue
            queue.clear()
        return n

    def _use_fault_path(self) -> None:
        """Receive through the fault-aware ``recv``/``dispatch`` (the channel got a fault
        hook); the plain ones stay free of its checks."""
        self.recv = self._recv_faulty  # type: ignore[method-assign]
        self.dispatch = self._dispatch_faulty  # type: ignore[method-assign]

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        queue = self._queue
        if queue:
            return queue.popleft(), False
        if timeout == 0:
            return None, False
        ch = self._ch
        with self._ready:
            self._waiting = True
            ch.waiting += 1
            try:

                def arrived() -> bool:
                    if ch.pending or ch.inflight:
                        ch.flush()
                    return bool(queue)

                self._ready.wait_for(arrived, timeout)
            finally:
                self._waiting = False
                ch.waiting -= 1
            return (queue.popleft() if queue else None), False

    def idle(self) -> bool:
        """Whether a poll would find nothing: no frame waits for this bus and none is
        requested or in flight on the channel (cheap: no lock, nothing scheduled)."""
        ch = self._ch
        return not (self._queue or ch.pending or ch.inflight)

    def pending(self) -> int:
        """Frames waiting in this bus's receive queue (after scheduling requested frames)."""
        with self._ch.lock:
            self._ch.flush()
        return len(self._queue)

    def shutdown(self) -> None:
        with _channels_lock:
            ch = self._ch
            with ch.lock:
                ch.detach(self)
            if not ch.buses and _channels.get(ch.name) is ch:
                del _channels[ch.name]
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        return [{"interface": "simbus", "channel": "control"}]
