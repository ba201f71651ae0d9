"""A deterministic, simulated-time CAN bus that plugs into python-can as interface ``simbus``.

python-can's own ``virtual`` interface stamps frames with wall-clock time and deep-copies
every frame for every receiver (about 4 us a copy).  For lockstep runs we want the
opposite: simulated timestamps, bit-identical delivery order, and a bus that behaves like a
real 1 Mbit/s wire.  ``SimBus`` is an ordinary :class:`can.BusABC`, so nodes written against
python-can run on it unchanged and run on SocketCAN, PCAN, ``virtual`` or ``udp_multicast``
just the same::

    clock = SimClock()
    a = can.Bus(interface="simbus", channel="control", clock=clock)
    b = can.Bus(interface="simbus", channel="control", clock=clock)

Timing model: frames are serialised on the channel.  A frame sent at simulated time ``t``
starts when the wire is free (``max(t, busy_until)``) and is delivered, timestamped, at the
end of its transmission, which lasts its worst-case bit count (DESIGN.md frame budget, with
the maximum number of stuff bits) at the channel's bit rate.  ``bitrate=0`` turns the timing
off (frames are stamped with the clock's time), used for the ground-truth side channel.

``trace_channel``: the channel number received frames carry (``msg.channel``), e.g. the
trace channel of the bus; by default the channel name.

Delivery: one immutable-by-convention :class:`can.Message` per sent frame is queued for
every other bus on the channel (and for the sender when ``receive_own_messages``).
Receivers must not mutate received messages.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

import can

from hdhil.dbc import worst_case_frame_bits


class SimClock:
    """Simulated time in seconds, advanced by whoever paces the run (the lockstep runner)."""

    __slots__ = ("now",)

    def __init__(self, now: float = 0.0) -> None:
        self.now = now


class _Channel:
    __slots__ = ("bitrate", "buses", "busy_until", "clock", "frames", "label", "lock", "name")

    def __init__(self, name: str, clock: SimClock, bitrate: int, label: str | int) -> None:
        self.name = name
        self.label = label
        self.clock = clock
        self.bitrate = bitrate
        self.busy_until = 0.0
        self.buses: list[SimBus] = []
        self.frames = 0
        self.lock = threading.Lock()


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
        **kwargs: Any,
    ) -> None:
        name = str(channel)
        if bitrate < 0:
            raise ValueError(f"simbus bitrate must be >= 0, got {bitrate}")
        with _channels_lock:
            ch = _channels.get(name)
            if ch is None:
                label = name if trace_channel is None else trace_channel
                ch = _Channel(name, clock or SimClock(), bitrate, label)
                _channels[name] = ch
            elif clock is not None and clock is not ch.clock:
                raise ValueError(f"simbus channel {name!r} already runs on another clock")
            ch.buses.append(self)
        self._ch = ch
        self._queue: deque[can.Message] = deque()
        self._ready = threading.Condition(ch.lock)
        self._receive_own = receive_own_messages
        self._waiting = False
        self._bits_cache: dict[tuple[int, bool], float] = {}
        self.channel_info = f"simbus channel {name!r} at {ch.bitrate} bit/s"
        super().__init__(channel=name, **kwargs)

    @property
    def clock(self) -> SimClock:
        return self._ch.clock

    @property
    def frames_sent(self) -> int:
        """Frames sent on the whole channel since it was created."""
        return self._ch.frames

    def frame_time(self, msg: can.Message) -> float:
        """Seconds the frame occupies the wire (worst-case stuffing), 0 without timing."""
        length = 0 if msg.is_remote_frame else len(msg.data)
        key = (length, msg.is_extended_id)
        seconds = self._bits_cache.get(key)
        if seconds is None:
            bitrate = self._ch.bitrate
            seconds = worst_case_frame_bits(*key) / bitrate if bitrate else 0.0
            self._bits_cache[key] = seconds
        return seconds

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        ch = self._ch
        with ch.lock:
            start = ch.clock.now if ch.clock.now > ch.busy_until else ch.busy_until
            end = start + self.frame_time(msg)
            ch.busy_until = end
            ch.frames += 1
            delivered = can.Message(
                timestamp=end,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                dlc=msg.dlc,
                data=bytes(msg.data),
                channel=ch.label,
                is_rx=True,
                check=False,
            )
            for bus in ch.buses:
                if bus is not self or self._receive_own:
                    bus._queue.append(delivered)
                    if bus._waiting:
                        bus._ready.notify()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Next received frame; without receive filters this skips python-can's generic
        filter loop (the 1 kHz path polls with ``timeout=0`` several times a cycle)."""
        if self._filters is None and self._queue:
            return self._queue.popleft()
        if timeout == 0 and self._filters is None:
            return None
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        queue = self._queue
        if queue:
            return queue.popleft(), False
        if timeout == 0:
            return None, False
        with self._ready:
            self._waiting = True
            try:
                self._ready.wait_for(lambda: bool(queue), timeout)
            finally:
                self._waiting = False
            return (queue.popleft() if queue else None), False

    def pending(self) -> int:
        """Frames waiting in this bus's receive queue."""
        return len(self._queue)

    def shutdown(self) -> None:
        with _channels_lock:
            ch = self._ch
            if self in ch.buses:
                ch.buses.remove(self)
            if not ch.buses and _channels.get(ch.name) is ch:
                del _channels[ch.name]
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        return [{"interface": "simbus", "channel": "control"}]
