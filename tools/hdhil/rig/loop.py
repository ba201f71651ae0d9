"""The one node loop: how every node runs, in one process or one per process.

A cycle: wait for the deadline (only with a pacer, :class:`hdhil.rig.realtime.RealtimeLoop`),
run every node's timers, let the SYNC producer start the cycle, then handle frames
until the cycle is complete. On the simulated bus (``pump``) delivery is immediate: the
nodes are polled until a round in which none sent a frame. On any other python-can bus
the loop handles frames until the producer has answered the cycle's sensor frame or
:data:`CYCLE_TIMEOUT_S` passed, running the nodes' timers (heartbeats) every
:data:`TIMER_SLICE_S` meanwhile; a timed-out cycle is closed and counted, and the
controller's sensor hold decides whether the peer is gone. Without a SYNC producer (a
drive or a logger alone) a cycle is one receive slice (:data:`RECV_SLICE_S`).
Listeners that only read (the host tap) are drained every ``listen_every`` cycles.

Used by ``hdhil run`` (lockstep on ``simbus``, network lockstep on another interface,
``--realtime``), ``hdhil emulate`` / ``hdhil firmware`` and the tests' served drive.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import can

from hdhil.can.node import CanNode
from hdhil.can.simbus import SimBus, SimClock

#: How long a cycle on a real or virtual bus waits for the producer's answer (s).
CYCLE_TIMEOUT_S = 0.5
#: The wait of a cycle that expects no sensor frame (before the drive's first one) (s).
STARTUP_WAIT_S = 0.005
#: How long one node alone blocks in one receive before it runs its timers again (s).
RECV_SLICE_S = 0.002
#: The pause of a loop with several nodes when no frame is waiting (s).
IDLE_SLEEP_S = 50e-6
#: While a cycle waits for its answer on a real bus, the nodes' timers run this often (s):
#: a node's heartbeat goes on while its peer is slow to answer (CiA 301: the producer
#: runs on the node's clock, not on the SYNC cycle).
TIMER_SLICE_S = 0.01


@runtime_checkable
class Pollable(Protocol):
    """Something the loop drains without blocking: a node or a listening tap."""

    def poll(self) -> int:
        """Handle every frame waiting, without blocking; return how many."""
        ...


class LoopNode(Pollable, Protocol):
    """What the loop needs from a CAN node (:class:`hdhil.can.node.CanNode` and its
    subclasses have it): its bus, its timers and its frame handler."""

    bus: can.BusABC

    def boot(self, now: float) -> None:
        """Power-on at time ``now`` (boot-up message, NMT pre-operational)."""
        ...

    def tick(self, now: float) -> None:
        """Run the node's timers at ``now`` (heartbeats, timeouts); once per cycle."""
        ...

    def on_message(self, msg: can.Message) -> None:
        """Handle one received frame."""
        ...


class SyncProducer(Protocol):
    """The node that starts each cycle (the controller, :class:`firmware.controller.
    ControllerNode`)."""

    def send_sync(self) -> bool:
        """Start a cycle: SYNC (the node decides by its state whether it goes out)."""
        ...


class NodeLoop:
    """Runs ``nodes`` cycle by cycle (module docstring).

    ``nodes`` are ticked and polled in this order; ``producer`` (one of them, or None)
    sends the SYNC after the ticks, and ``answers`` counts its answers to sensor frames
    (the loop waits for it to move on a non-simulated bus); ``expects_answer`` says
    whether the producer expects a sensor frame this cycle (long timeout) or not (short;
    :func:`controller_expects_answer` for the firmware's controller).
    ``listeners`` are drained every ``listen_every`` cycles and while waiting.
    ``more_buses``: further simulated buses on the same clock, each with its SYNC
    producer (one process running a rig of several buses in lockstep).

    Time: with a ``pacer`` the cycle waits for its wall-clock deadline; otherwise, with a
    ``sim_clock``, that clock is set to ``k * period_s`` (simulated time) and its
    horizon to ``(k + 1) * period_s`` (frames delayed past it wait for their cycle). Nodes are
    handed ``node_time()`` (default: the monotonic clock; None: the ``sim_clock``'s
    time). ``pump`` is the simulated
    control bus (cycles complete by pumping, no waiting).
    """

    def __init__(
        self,
        nodes: Sequence[LoopNode],
        *,
        producer: SyncProducer | None = None,
        answers: Callable[[], int] | None = None,
        expects_answer: Callable[[], bool] = lambda: True,
        listeners: Sequence[Pollable] = (),
        listen_every: int = 1,
        period_s: float = 1e-3,
        sim_clock: SimClock | None = None,
        node_time: Callable[[], float] | None = time.monotonic,
        pump: SimBus | None = None,
        pacer: Pacer | None = None,
        timeout_s: float | None = None,
        more_buses: Sequence[tuple[SyncProducer, SimBus]] = (),
    ) -> None:
        if producer is not None and answers is None and pump is None:
            raise ValueError("a SYNC producer on a real bus needs its answer counter")
        if node_time is None and sim_clock is None:
            raise ValueError("node_time None reads the sim_clock, and there is none")
        if listen_every < 1:
            raise ValueError(f"listen_every must be >= 1, got {listen_every}")
        if more_buses and (pump is None or producer is None):
            raise ValueError("more simulated buses need the first one's pump and producer")
        self.nodes = tuple(nodes)
        self.producer = producer
        self.answers = answers
        self.expects_answer = expects_answer
        self.listeners = tuple(listeners)
        self.listen_every = listen_every
        self.period_s = period_s
        self.sim_clock = sim_clock
        self.node_time = node_time
        self.pump = pump
        self.pacer = pacer
        #: The cycle timeout (default :data:`CYCLE_TIMEOUT_S`).
        self.timeout_s = CYCLE_TIMEOUT_S if timeout_s is None else timeout_s
        #: Cycles run so far (the next cycle's index).
        self.k = 0
        #: Cycles closed by the timeout before the producer answered.
        self.timeouts = 0
        #: Per node, a test that its poll would find no frame (a plain ``CanNode`` on a
        #: ``simbus``), or None: always poll it.
        self._idle = tuple(_idle_test(node) for node in self.nodes)
        #: Further simulated buses of the same clock, each with its SYNC producer (a rig
        #: of several buses in one process): their SYNCs go out with the first bus's,
        #: and a cycle completes when no bus had a frame requested in a round.
        self.more_buses = tuple(more_buses)

    def now(self) -> float:
        """The time the nodes are handed now."""
        if self.node_time is not None:
            return self.node_time()
        assert self.sim_clock is not None
        return self.sim_clock.now

    def boot(self) -> None:
        """Power every node on, in order, at the current time."""
        for node in self.nodes:
            node.boot(self.now())

    def cycle(self) -> None:
        """One cycle: pace, tick, SYNC, complete, drain the listeners."""
        k = self.k
        pacer = self.pacer
        sim_clock = self.sim_clock
        if pacer is not None:
            pacer.wait(k)  # wall clock: a WallClock reads real time by itself
            if sim_clock is not None:  # its cycles end on the same time base (a cycle
                # that starts late still has a period for its frames)
                sim_clock.horizon = max((k + 1) * self.period_s,
                                        sim_clock.now + self.period_s)  # fmt: skip
        elif sim_clock is not None:
            sim_clock.now = k * self.period_s
            # The step ends at the next SYNC: a delivery due later waits in flight.
            sim_clock.horizon = (k + 1) * self.period_s
        node_time = self.node_time
        now = node_time() if node_time is not None else sim_clock.now  # type: ignore[union-attr]
        nodes = self.nodes
        for node in nodes:
            node.tick(now)
        producer = self.producer
        bus = self.pump
        if producer is None:
            self._serve_slice()
        elif self.more_buses:  # several simulated buses: the same, over all of them
            self._pump_buses(producer, bus)  # type: ignore[arg-type]
        elif bus is not None:  # simulated bus: pump until a round requests no frame
            producer.send_sync()
            idle = self._idle
            while True:
                before = bus.frames_requested
                for node, node_idle in zip(nodes, idle, strict=True):
                    # A poll that would find nothing is skipped (most polls of a round).
                    if node_idle is None or not node_idle():
                        node.poll()
                if bus.frames_requested == before:
                    break
        else:
            answered = self.answers() if self.answers is not None else 0
            producer.send_sync()
            self._await_answer(answered)
        if k % self.listen_every == 0:
            for listener in self.listeners:
                listener.poll()
        if pacer is not None:
            pacer.end_cycle()
        self.k = k + 1

    def run(self, stop: Callable[[], bool], until: Callable[[], bool] = lambda: False) -> None:
        """Cycles until ``stop()`` or ``until()`` (both checked before each cycle)."""
        while not stop() and not until():
            self.cycle()

    def drain(self) -> int:
        """Hand every waiting frame to the listeners; return how many."""
        return sum(listener.poll() for listener in self.listeners)

    # ------------------------------------------------------------------ completion
    def _pump_buses(self, producer: SyncProducer, first: SimBus) -> None:
        """Every bus's SYNC, then rounds of polls until a round in which no bus had a
        frame requested (the simulated buses deliver at once; each bus has its wire)."""
        producer.send_sync()
        buses = [first]
        for more, bus in self.more_buses:
            more.send_sync()
            buses.append(bus)
        nodes, idle = self.nodes, self._idle
        while True:
            before = sum(b.frames_requested for b in buses)
            for node, node_idle in zip(nodes, idle, strict=True):
                if node_idle is None or not node_idle():
                    node.poll()
            if sum(b.frames_requested for b in buses) == before:
                break

    def _poll_all(self) -> int:
        n = 0
        for node in self.nodes:
            n += node.poll()
        for listener in self.listeners:
            n += listener.poll()
        return n

    def _await_answer(self, answered: int) -> None:
        """Handle frames until the producer answered or the cycle timed out."""
        answers = self.answers
        assert answers is not None
        while self._poll_all():
            pass
        expected = self.expects_answer()
        clock = time.perf_counter
        deadline = clock() + (self.timeout_s if expected else STARTUP_WAIT_S)
        if self.pacer is not None:  # paced: never past the next cycle's deadline
            deadline = min(deadline, self.pacer.cycle_end_s())
        alone = self.nodes[0] if len(self.nodes) == 1 and not self.listeners else None
        node_time = self.node_time  # None: simulated time, which does not pass while waiting
        next_timers = clock() + TIMER_SLICE_S
        while answers() <= answered:
            if node_time is not None and clock() >= next_timers:
                now = node_time()
                for node in self.nodes:
                    node.tick(now)
                next_timers = clock() + TIMER_SLICE_S
            if self._poll_all():
                continue
            left = deadline - clock()
            if left <= 0:
                if expected:
                    self.timeouts += 1
                return
            if alone is not None:
                msg = alone.bus.recv(min(left, RECV_SLICE_S))
                if msg is not None:
                    alone.on_message(msg)
            else:
                time.sleep(IDLE_SLEEP_S)

    def _serve_slice(self) -> None:
        """No producer: handle what arrives within one receive slice."""
        if len(self.nodes) == 1:
            node = self.nodes[0]
            recv = node.bus.recv
            msg = recv(RECV_SLICE_S)
            while msg is not None:
                node.on_message(msg)
                msg = recv(0)
            if self.listeners:
                self.drain()
            return
        deadline = time.monotonic() + RECV_SLICE_S
        while time.monotonic() < deadline:
            if not self._poll_all():
                time.sleep(IDLE_SLEEP_S)


def _idle_test(node: LoopNode) -> Callable[[], bool] | None:
    """``node.bus.idle`` when polling ``node`` only drains that bus (the poll of
    :class:`hdhil.can.node.CanNode` on a :class:`SimBus`), else None."""
    bus = getattr(node, "bus", None)
    if isinstance(bus, SimBus) and type(node).poll is CanNode.poll:
        return bus.idle
    return None


class Pacer(Protocol):
    """What the loop needs from a pacer (:class:`hdhil.rig.realtime.RealtimeLoop`, the
    one pacer: sleep, then spin to an absolute deadline)."""

    def wait(self, k: int) -> None:
        """Return at cycle ``k``'s deadline."""
        ...

    def end_cycle(self) -> None:
        """The cycle's frames are handled (statistics, spin-window sizing)."""
        ...

    def cycle_end_s(self) -> float:
        """The next cycle's deadline on :func:`time.perf_counter` (s): how long the
        current cycle may wait for frames."""
        ...


def controller_expects_answer(controller: Any) -> bool:
    """Whether the firmware's controller (:class:`firmware.controller.ControllerNode`)
    waits for a sensor frame this cycle: once the drive has sent one (it is then NMT
    operational and answers every SYNC), in every phase in which the controller
    commands it.  Before that a cycle waits only briefly: the drive is still booting or
    pre-operational and sends nothing to answer."""
    return controller.diagnostics.sensor_frames > 0 and controller.phase in (
        "starting",
        "operational",
        "stopping",
    )


def serve(
    node: LoopNode,
    stop: Callable[[], bool],
    until: Callable[[], bool] = lambda: False,
    node_time: Callable[[], float] = time.monotonic,
) -> NodeLoop:
    """Serve one node on its own bus (no SYNC producer among the nodes served) until
    ``stop()`` or ``until()``: how ``hdhil emulate`` runs the drive and the tests serve
    one. The node is not booted here. Returns the loop (its cycle count)."""
    loop = NodeLoop([node], node_time=node_time)
    loop.run(stop, until)
    return loop
