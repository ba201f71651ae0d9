"""``hdhil run``: a full emulated run in one process, lockstep on the simulated bus.

The nodes share python-can channels and nothing else: the controller
(:class:`firmware.controller.ControllerNode`) and the drives
(:class:`hostsim.drive.DriveNode`, publishing ground truth on the truth channel) on the
control bus, and the host tap (:class:`hdhil.can.traces.tap.BusTap`: trace writer, frame
counter, scorers) listening on both. The runner builds no node itself: they come from
factories (:mod:`hdhil.rig.factories`), one per slot of the request's layout, and run in
the one node loop (:mod:`hdhil.rig.loop`). A :class:`~hdhil.rig.request.RunRequest` is
planned (:func:`plan_run`), its buses opened and its nodes built, then it goes through
start-up, operation and stop (:func:`run_phases`) and is scored once (:func:`_result`,
headline first).

Lockstep (``docs/design.md``, "Timing semantics"): SYNC k is sent at simulated time
k·Ts; every node handles what the bus delivers until the cycle is quiet, and SYNC k+1
follows at once: deterministic for a given seed, as fast as the host allows.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
from threadpoolctl import threadpool_limits

from hdhil.can.busload import LOAD_LIMIT, ScheduleLoad, schedule_load
from hdhil.can.faults import (
    ChannelFaults,
    FaultLog,
    FaultyTransmitBus,
    check_node_transmit_faults,
)
from hdhil.can.simbus import SimBus, SimClock
from hdhil.can.traces.tap import BusTap, FrameCounter
from hdhil.can.traces.writer import WriterProcess
from hdhil.canopen.cia402 import State
from hdhil.core.dataconf import ConfigError, merge
from hdhil.core.files import load_toml
from hdhil.core.signals import stop_on_signals as stop_on_signals  # for its callers
from hdhil.dbc import CHANNEL_NUMBER, database
from hdhil.firmware.config import FirmwareConfig, Law
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveNode
from hdhil.rig.evaluate import RecordingListener, format_evaluation
from hdhil.rig.evaluate import evaluate as evaluate_recording
from hdhil.rig.factories import (
    ControllerFactory,
    DriveFactory,
    NodeSite,
    RigLayout,
    dcf_controller,
    scenario_controller,
    scenario_drive,
)
from hdhil.rig.faults import FaultInjector
from hdhil.rig.headline import format_headline, headline
from hdhil.rig.loop import NodeLoop, controller_expects_answer
from hdhil.rig.realtime import RealtimeConfig, RealtimeLoop, WallClock
from hdhil.rig.realtime_stats import format_realtime
from hdhil.rig.request import RunRequest
from hdhil.rig.scenario import Scenario, scenario_data, scenario_from_dict
from hdhil.rig.score import TorqueScorer, TrackingScorer
from hdhil.rig.sidecar import run_metadata
from hdhil.rig.verdict import dcf_refused, format_verdict, startup_verdict, stop_verdict

_run_ids = itertools.count(1)


@dataclass
class RunResult:
    """What a run did, every figure computed from the run itself."""

    scenario: str
    seed: int
    interface: str
    actuation: str
    cycles: int
    sample_period_s: float
    simulated_s: float
    wall_s: float
    interrupted: bool
    frames: dict[str, int]
    frames_total: int
    frames_sent: dict[str, int]
    startup_cycles: int
    stop_cycles: int
    worst_case_load: float
    bitrate: int
    torque: dict[str, float]
    velocity_final: float
    velocity_peak: float
    trace: str | None
    evaluation: dict[str, Any] | None = None
    tracking: dict[str, Any] | None = None
    faults: dict[str, int] | None = None
    controller: dict[str, Any] = field(default_factory=dict)
    drive: dict[str, Any] = field(default_factory=dict)
    realtime: dict[str, Any] | None = None
    #: Unix time of simulated time 0 in the trace (the wall clock at the run's start,
    #: or ``start_time``); ``None`` in real time on another interface than ``simbus``
    #: (:attr:`RunPlan.clock_time`).
    start_time: float | None = None
    #: The per-cycle recording (:class:`hdhil.rig.evaluate.Recording`) when the run
    #: evaluated; not part of :meth:`as_dict`.
    recording: Any = field(default=None, repr=False)
    #: Why the run stopped before its planned end (:func:`hdhil.rig.verdict.stop_verdict`),
    #: ``None`` when it completed or was interrupted.
    verdict: dict[str, Any] | None = None
    #: The run's one figure (:func:`hdhil.rig.headline.headline`), None without one.
    headline: dict[str, Any] | None = None
    #: What the run's scenario scores (:attr:`hdhil.rig.scenario.Scenario.scored`).
    scored: tuple[str, ...] = ("ripple",)

    @property
    def real_time_factor(self) -> float:
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        del d["recording"]
        if d["verdict"] is None:
            del d["verdict"]  # a completed run: the summary keeps its keys
        d["real_time_factor"] = self.real_time_factor
        return d


def _suffixed(trace: Path, label: str) -> Path:
    """``run.blf`` -> ``run-LABEL.blf``; the whole format extension is kept
    (``run.asc.gz`` -> ``run-LABEL.asc.gz``)."""
    from hdhil.can.traces.formats import trace_format

    fmt, compressed = trace_format(trace)
    ext = fmt + (".gz" if compressed else "")
    base = trace.name[: -len(ext)] if ext and trace.name.lower().endswith(ext) else trace.stem
    return trace.with_name(f"{base}-{label}{trace.name[len(base) :]}")


def _utc(unix_s: float) -> str:
    """``unix_s`` as an ISO 8601 UTC date and time, to the millisecond."""
    import datetime

    when = datetime.datetime.fromtimestamp(unix_s, tz=datetime.timezone.utc)
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _frame_names() -> dict[tuple[int, int], str]:
    names = {}
    for bus, channel in CHANNEL_NUMBER.items():
        for msg in database(bus).messages:
            names[(channel, msg.frame_id)] = f"{bus} 0x{msg.frame_id:03X} {msg.name}"
    return names


#: In lockstep on the simulated bus the tap drains its queues every this many cycles
#: (and before a monitor call and at the end): its listeners see the same frames in
#: the same order, with less work per frame.  Every cycle in real-time mode and on
#: other interfaces.
TAP_EVERY_CYCLES = 16
#: The cycle timeout of a run whose nodes fault their own frames on a non-simulated bus
#: (s): every node is in this process, so an answer that has not come by then was dropped.
FAULTY_CYCLE_TIMEOUT_S = 0.02

#: Cycles allowed from power-on to "operation enabled" (NMT start and the CiA 402 walk
#: take a handful) and back to "stopped".
MAX_STARTUP_CYCLES = 500
MAX_STOP_CYCLES = 200


def read_toml(path: Path) -> dict[str, Any]:
    """A TOML override file as nested dicts, with one-line errors naming the file
    (a regular file, size and nesting capped: :func:`hdhil.core.files.load_toml`)."""
    return load_toml(path, "override file")


def _controller_diagnostics(controller: ControllerNode) -> dict[str, Any]:
    """The controller's counters and the health of its filter's covariance (the
    firmware's own interrupt handler; a handler of the user's reports the counters)."""
    d = controller.diagnostics
    counters = {
        "syncs_sent": d.syncs_sent,
        "sensor_frames": d.sensor_frames,
        "malformed_frames": d.malformed_frames,
        "unknown_frames": sum(controller.unknown_frames.values()),
    }
    chain = getattr(controller.isr, "chain", None)
    if chain is None:
        return counters
    kalman = chain.kalman
    P = np.asarray(kalman.P)
    finite = bool(np.all(np.isfinite(P)))
    return {
        **counters,
        "filter_mode": controller.config.ripple.mode,
        "filter_states": int(P.shape[0]),
        "kalman_skipped": kalman.skipped,
        "tacho_rejections": d.tacho_rejections,
        "encoder_rejections": d.encoder_rejections,
        "tacho_reseeds": d.tacho_reseeds,
        "encoder_reseeds": d.encoder_reseeds,
        "plausibility_errors": d.plausibility_errors,
        "stuck_sensor_events": d.stuck_sensor_events,
        "stuck_tacho_events": d.stuck_tacho_events,
        "covariance_resets": getattr(kalman, "covariance_resets", 0),
        "covariance_finite": finite,
        "covariance_min_eigenvalue": (
            float(np.linalg.eigvalsh((P + P.T) / 2).min()) if finite else math.nan
        ),
        "covariance_asymmetry": float(np.abs(P - P.T).max()) if finite else math.nan,
    }


def _drive_diagnostics(drive: DriveNode) -> dict[str, Any]:
    d = drive.diagnostics
    return {
        "syncs": d.syncs,
        "commands": d.commands,
        "malformed_frames": d.malformed_frames,
        "unknown_frames": sum(drive.unknown_frames.values()),
    }


def _frames_sent(control: can.BusABC, truth: can.BusABC) -> dict[str, int]:
    """Frames each channel carried, as counted by the bus itself (simbus only)."""
    return {
        name: bus.frames_sent
        for name, bus in (("control", control), ("truth", truth))
        if hasattr(bus, "frames_sent")
    }


# ---------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class RunPlan:
    """Where and how a :class:`RunRequest` will run, checked before anything is opened
    (every check that can fail without a bus fails here)."""

    request: RunRequest
    interface: str | None
    channel: str | None
    realtime: bool
    load: ScheduleLoad

    @property
    def scenario(self) -> Scenario:
        return self.request.scenario

    @property
    def firmware(self) -> FirmwareConfig:
        return self.request.firmware

    @property
    def seed(self) -> int:
        return self.request.seed

    @property
    def cycles(self) -> int:
        return self.request.cycles

    @property
    def bitrate(self) -> int:
        return self.request.bitrate

    @property
    def actuation(self) -> str:
        return self.request.actuation

    @property
    def layout(self) -> RigLayout:
        return self.request.layout

    @property
    def sample_period_s(self) -> float:
        return self.request.sample_period_s

    @property
    def simulated(self) -> bool:
        """The control bus is the in-process simulated bus (lockstep in simulated time)."""
        return self.interface == "simbus"

    @property
    def clock_time(self) -> bool:
        """Every frame the tap hands on carries the run's clock (the cycle time ``k * Ts``
        in lockstep): always on the simulated bus; on any other interface in lockstep,
        where the tap stamps the control frames itself (:class:`CycleStampedTap`).  Not
        for another interface in real time, whose frames keep the interface's own
        (wall-clock or hardware) timestamps."""
        return self.simulated or not self.realtime


def plan_run(
    request: RunRequest, interface: str | None, channel: str | None, realtime: bool
) -> RunPlan:
    """Check that ``request``'s cyclic schedule fits its bus (one-line :class:`ConfigError`
    otherwise)."""
    if not isinstance(request, RunRequest):
        raise TypeError(
            f"run_lockstep takes a RunRequest (hdhil.rig.request.resolve), got "
            f"{type(request).__name__}"
        )
    Ts = request.sample_period_s
    load = schedule_load("control", request.bitrate, Ts)
    if load.worst_case_load > 1.0:
        raise ConfigError(
            f"the cyclic schedule needs {load.worst_case_load:.0%} of a "
            f"{request.bitrate} bit/s bus at {Ts * 1e3:g} ms: it cannot run"
        )
    return RunPlan(request=request, interface=interface, channel=channel, realtime=realtime,
                   load=load)  # fmt: skip


# ---------------------------------------------------------------------- the buses
class CycleStampedTap:
    """The host tap's handle on a control bus other than ``simbus`` in lockstep: every
    frame it receives is stamped with the run's clock at that moment, the cycle time
    ``k * Ts`` of the cycle in which the frame reached the tap.

    python-can's ``virtual`` bus stamps frames with the wall clock when they are sent and
    ``udp_multicast`` with the kernel's receive time, so a lockstep run (1 s simulated in
    about 0.2 s) would hand the listeners wall-clock control frames next to truth frames
    in simulated time: the evaluation pairs sensor frames with truth and counts missed
    periods by timestamp, and found nothing to pair.  Stamped here, the control frames
    carry the time base of the truth channel and of the firmware's own cycles; what the
    bus really changes stays: a frame the bus (or a fault) holds past its cycle is
    stamped with the cycle in which it arrived, as the firmware received it.  Within one
    cycle the frames share one timestamp and keep their order of arrival; the tap puts the
    truth channel first on a tie (:func:`build_nodes`), as on ``simbus``, where truth is
    stamped at the sample instant and every control frame after its time on the wire.

    Everything else is the wrapped bus.  Received frames are the tap's own copies
    (python-can's buses hand each receiver its own :class:`can.Message`)."""

    def __init__(self, bus: can.BusABC, clock: SimClock) -> None:
        self.bus = bus
        self._clock = clock

    def __getattr__(self, name: str) -> Any:
        if name == "bus":  # not set yet (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.bus, name)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self.bus.recv(timeout)
        if msg is not None:
            msg.timestamp = self._clock.now
        return msg


class RigBuses:
    """Opens the run's python-can buses, one handle per node and per tap, and closes
    every one it opened. The control bus follows the run's interface; the truth
    channel is always the simulated bus (ground truth exists only in simulation)."""

    def __init__(
        self,
        plan: RunPlan,
        clock: SimClock,
        injector: FaultInjector | None,
        open_control: Callable[[], can.BusABC] | None = None,
    ) -> None:
        self.plan = plan
        self._open_control = open_control
        self.clock = clock
        self.run_id = next(_run_ids)
        self._control_faults = injector.channel("control") if injector is not None else None
        self._truth_faults = injector.channel("truth") if injector is not None else None
        self.injector_seed = injector.config.seed if injector is not None else 0
        if self._control_faults is not None and not plan.simulated:
            check_node_transmit_faults(injector.config, "control")  # type: ignore[union-attr]
        self.opened: list[can.BusABC] = []
        #: Some node puts its own frames through the control faults (not the simbus).
        self.faulty_transmit = False

    def control(self, node_id: int | None = None) -> can.BusABC:
        """A new handle on the control bus for node ``node_id`` (None: the tap)."""
        p = self.plan
        if p.simulated:
            bus = can.Bus(
                interface="simbus",
                channel=p.channel or f"hdhil-{self.run_id}-control",
                bitrate=p.bitrate,
                clock=self.clock,
                trace_channel=CHANNEL_NUMBER["control"],
                faults=self._control_faults,
                node_id=node_id,
            )
        elif p.interface == "virtual":
            bus = can.Bus(interface="virtual", channel=p.channel or f"hdhil-{self.run_id}-control")
        elif self._open_control is not None:
            bus = self._open_control()  # python-can's own factory, from the command line
        else:
            try:
                # Any python-can interface; None falls back to python-can's configuration
                # (~/can.conf, CAN_INTERFACE / CAN_CHANNEL environment variables).
                bus = can.Bus(interface=p.interface, channel=p.channel, bitrate=p.bitrate)
            except (can.CanError, ImportError, OSError, ValueError, TypeError) as exc:
                raise ConfigError(
                    f"cannot open the control bus ({p.interface} {p.channel}): {exc}"
                ) from None
        self.opened.append(bus)
        hook = self._control_faults
        if hook is not None and not p.simulated and node_id is not None:
            # No simulated channel between the nodes: each node puts its own frames
            # through the channel's faults, with random draws of its own, timed by the
            # run's clock (the cycle time in network lockstep).
            own = ChannelFaults(hook.cfg, hook.name, self.injector_seed, hook.log,
                                stream=f"node{node_id}")  # fmt: skip
            clock = self.clock
            self.faulty_transmit = True
            return FaultyTransmitBus(bus, own, clock=lambda: clock.now, node_id=node_id)
        return bus

    def truth(self, node_id: int | None = None) -> can.BusABC:
        """A new handle on the truth channel for drive ``node_id`` (None: the tap)."""
        bus = can.Bus(
            interface="simbus",
            channel=f"hdhil-{self.run_id}-truth",
            bitrate=0,
            clock=self.clock,
            trace_channel=CHANNEL_NUMBER["truth"],
            faults=self._truth_faults,
            node_id=node_id,
        )
        self.opened.append(bus)
        return bus

    def shutdown(self) -> None:
        for bus in self.opened:
            bus.shutdown()


@dataclass
class RigNodes:
    """The nodes of a run, each with its own bus handle, and the host tap's handles."""

    controller: ControllerNode
    drives: list[DriveNode]
    controller_bus: can.BusABC
    truth_bus: can.BusABC  # one drive's handle on the truth channel (frame counts)
    tap_buses: dict[int, can.BusABC]


def build_nodes(
    plan: RunPlan,
    buses: RigBuses,
    controller_factory: ControllerFactory,
    drive_factories: Sequence[DriveFactory],
    injector: FaultInjector | None,
) -> RigNodes:
    """Open every node's bus handle and build the nodes through their factories: the
    controller first, then one drive per slot of the layout (its factory is the slot's
    entry of ``drive_factories``, or the only entry for every slot)."""
    layout = plan.layout
    slots = layout.drives
    if len(drive_factories) not in (1, len(slots)):
        raise ConfigError(
            f"{len(drive_factories)} drive factories for {len(slots)} drives in the layout"
        )
    Ts = plan.sample_period_s
    drive_ids = tuple(slot.node_id for slot in slots)
    controller_bus = buses.control(layout.controller_node_id)
    site = NodeSite(
        bus=controller_bus,
        node_id=layout.controller_node_id,
        controller_node_id=layout.controller_node_id,
        sample_period_s=Ts,
        seed=plan.seed,
        actuation=plan.actuation,  # type: ignore[arg-type]
        faults=injector,
        drive_node_ids=drive_ids,
    )
    controller = controller_factory(site, plan.firmware)
    drives = []
    truth_handles = []
    for i, slot in enumerate(slots):
        bus, truth = buses.control(slot.node_id), buses.truth(slot.node_id)
        truth_handles.append(truth)
        make = drive_factories[i if len(drive_factories) > 1 else 0]
        drives.append(
            make(dataclasses.replace(site, bus=bus, node_id=slot.node_id, truth_bus=truth))
        )
    tap_buses = {CHANNEL_NUMBER["control"]: buses.control(),
                 CHANNEL_NUMBER["truth"]: buses.truth()}  # fmt: skip
    if not plan.simulated and plan.clock_time:
        # Control frames in the cycle time, truth first on a tie (CycleStampedTap).
        tap_buses = {CHANNEL_NUMBER["truth"]: tap_buses[CHANNEL_NUMBER["truth"]],
                     CHANNEL_NUMBER["control"]: CycleStampedTap(
                         tap_buses[CHANNEL_NUMBER["control"]], buses.clock)}  # fmt: skip
    return RigNodes(controller, drives, controller_bus, truth_handles[0], tap_buses)


@dataclass
class RunListeners:
    """What listens on the host tap: counts, scores, the recording, the trace."""

    counter: FrameCounter
    scorer: TorqueScorer
    tracking: TrackingScorer | None
    recorder: RecordingListener | None
    all: list[can.Listener]


def build_listeners(
    plan: RunPlan,
    trace: Path | None,
    evaluate: bool,
    evaluate_skip_s: float,
    extra: Sequence[can.Listener],
    start_time: float = 0.0,
    metadata: dict[str, Any] | None = None,
) -> RunListeners:
    """The tap's listeners, the trace writer first (it sees every frame as it came).

    In lockstep (on any interface) and on the simulated bus the trace's times are the
    run's clock plus ``start_time`` (:attr:`RunPlan.clock_time`); the
    trace's sidecar JSON gets the run's settings and ``metadata``."""
    counter, scorer = FrameCounter(), TorqueScorer()
    listeners: list[can.Listener] = [counter, scorer]
    tracking = recorder = None
    control = plan.firmware.control
    if control.law != Law.NONE:
        tracking = TrackingScorer(
            control.joint.Jl / control.joint.Jm,
            evaluate_skip_s,
            control.friction.active,
            plan.sample_period_s,
        )
        listeners.append(tracking)
    if evaluate:
        recorder = RecordingListener(plan.sample_period_s, (metadata or {}).get("drive_pdos"))
        listeners.append(recorder)
    if trace is not None:
        offset = start_time if plan.clock_time else 0.0
        sidecar = {
            "scenario": plan.scenario.name, "seed": plan.seed,
            "duration_s": plan.cycles * plan.sample_period_s,
            "sample_period_s": plan.sample_period_s,
            "start_time": start_time if plan.clock_time else None,
            "start_time_utc": _utc(start_time) if plan.clock_time else None,
            "time_offset_s": offset, "interface": plan.interface or "python-can configuration",
            "bitrate": plan.bitrate, "actuation": plan.actuation,
            "channels": dict(CHANNEL_NUMBER), "control_law": control.law.name.lower(),
            **(metadata or {}),
        }  # fmt: skip
        # the sidecar is written with the finished trace (both renamed into place)
        listeners.insert(0, WriterProcess(trace, time_offset=offset, metadata=sidecar))
    listeners += extra
    return RunListeners(counter, scorer, tracking, recorder, listeners)


# ---------------------------------------------------------------------- the phases
class SilentPeerError(ConfigError):
    """A drive stopped answering SYNC on a non-simulated bus and the controller went
    safe (its sensor hold)."""


@dataclass
class PhaseCounts:
    """Cycles per phase of a run and how it ended."""

    startup: int = 0
    operation: int = 0  # interrupts run in operation
    stop: int = 0
    interrupted: bool = False
    #: Why start-up failed (the drive never reached "operation enabled"), else None.
    startup_failure: str | None = None
    #: The node that failed to start (the first drive not in operation enabled).
    startup_node: int | None = None
    #: Ended by ``KeyboardInterrupt`` (Ctrl-C with no stop request polled, or a second one).
    keyboard: bool = False


def _node_id(drive: DriveNode) -> int | None:
    return getattr(getattr(drive, "config", None), "node_id", None)


def start_up(
    loop: NodeLoop, controller: ControllerNode, drives: Sequence[DriveNode]
) -> tuple[str, int | None] | None:
    """Power-on: every node boots; the controller starts the drives (NMT) and walks them to
    "operation enabled" (CiA 402) over the PDOs.

    Returns None once the controller is operational, else ``(why, node)``: a start-up that
    fails (no boot-up, a drive that never reaches operation enabled, e.g. under heavy
    frame loss) is a stop like any other, reported as the run's verdict (exit code 1).  A
    drive refusing a value of the user's DCF is an input error (:class:`ConfigError`,
    exit code 2): the file has to change, not the bus."""
    loop.boot()
    while controller.phase != "operational":
        if dcf_refused(controller):
            raise ConfigError(controller.boot_error)
        failed = [d for d in drives if d.drive_state != State.OPERATION_ENABLED]
        node = _node_id(failed[0]) if failed else None
        if controller.boot_error:
            return controller.boot_error, node
        if controller.phase == "safe" or loop.k >= MAX_STARTUP_CYCLES:
            states = ", ".join(
                f"node {_node_id(d)} {getattr(d.drive_state, 'name', d.drive_state)}"
                for d in drives
            )
            return (
                f"the drive did not reach operation enabled within {loop.k} start-up cycles "
                f"(controller phase {controller.phase}, drive {states})"
            ), node
        loop.cycle()
    return None


def operate(
    loop: NodeLoop,
    controller: ControllerNode,
    cycles: int,
    stop_requested: Callable[[], bool] | None,
    monitor: Callable[[ControllerNode], None] | None,
    monitor_every: int,
) -> bool:
    """Cycles until the interrupt has handled ``cycles`` samples, the controller leaves
    operation or a stop is requested (polled at every cycle boundary; returns True
    then). ``monitor`` is called every ``monitor_every`` samples, after the tap has
    handed every frame of those samples to its listeners."""
    isr = controller.isr
    next_monitor = monitor_every
    while isr.samplecount < cycles:
        if stop_requested is not None and stop_requested():
            return True
        if controller.phase != "operational":
            break
        loop.cycle()
        if monitor is not None and isr.samplecount >= next_monitor:
            next_monitor += monitor_every
            loop.drain()  # the listeners have seen every frame of those samples
            monitor(controller)
    return False


def shut_down(loop: NodeLoop, controller: ControllerNode) -> None:
    """Walk the drives back (disable operation, shut down) before the buses close."""
    controller.request_stop()
    for _ in range(MAX_STOP_CYCLES):
        if controller.phase in ("stopped", "safe"):
            break
        loop.cycle()


def run_phases(
    loop: NodeLoop,
    nodes: RigNodes,
    cycles: int,
    pacer: RealtimeLoop | None,
    stop_requested: Callable[[], bool] | None,
    monitor: Callable[[ControllerNode], None] | None,
    monitor_every: int,
    lossy: bool = False,
) -> PhaseCounts:
    """Start-up, operation and stop, with the pacer's statistics covering operation.

    ``lossy``: the nodes drop some of their own frames on purpose (faults on a
    non-simulated bus), so cycles that timed out do not make a silent peer: the
    controller's own reason for its safe state is the verdict."""
    counts = PhaseCounts()
    controller = nodes.controller
    try:
        failure = start_up(loop, controller, nodes.drives)
        counts.startup = loop.k
        if failure is not None:
            counts.startup_failure, counts.startup_node = failure
            operation_end = loop.k
            shut_down(loop, controller)  # NMT stop / disable whatever did start
            counts.stop = loop.k - operation_end
            return counts
        if pacer is not None:
            pacer.begin_recording()  # statistics cover the cycles in operation
        counts.interrupted = operate(
            loop, controller, cycles, stop_requested, monitor, monitor_every
        )
        counts.operation = controller.isr.samplecount
        if loop.timeouts and controller.phase == "safe" and not lossy:
            raise SilentPeerError(
                f"the drive went silent: {loop.timeouts} cycles without its sensor frame "
                f"within {loop.timeout_s:g} s of SYNC, the controller went safe"
            )
        operation_end = loop.k
        if pacer is not None:
            pacer.end_recording()
        shut_down(loop, controller)
        counts.stop = loop.k - operation_end
        if pacer is not None and not counts.interrupted:
            pacer.measure_floor()  # the bare loop in the same process state
    except KeyboardInterrupt:
        counts.interrupted = counts.keyboard = True
    return counts


# ---------------------------------------------------------------------- the run
def run_lockstep(
    request: RunRequest,
    *,
    trace: Path | None = None,
    interface: str | None = "simbus",
    channel: str | None = None,
    open_control_bus: Callable[[], can.BusABC] | None = None,
    realtime: bool = False,
    realtime_config: RealtimeConfig | None = None,
    evaluate: bool = True,
    stop_requested: Callable[[], bool] | None = None,
    monitor: Callable[[ControllerNode], None] | None = None,
    monitor_every: int = 1000,
    extra_listeners: Sequence[can.Listener] = (),
    fault_log: Path | None = None,
    controller_factory: ControllerFactory | None = None,
    drive_factories: Sequence[DriveFactory] | None = None,
    start_time: float | None = None,
    metadata: dict[str, Any] | None = None,
) -> RunResult:
    """Run ``request`` (:func:`hdhil.rig.request.resolve`) and return the scored result.

    Where: ``interface`` (``simbus``, the in-process simulated bus, by default; any
    python-can interface, opened by ``open_control_bus`` when given) and ``channel``;
    ``realtime`` paces SYNC by the wall clock instead of lockstep (``realtime_config``:
    spin window, machine-floor reference). ``trace`` writes a trace and its sidecar
    JSON, which carries the request (``start_time``: Unix time of simulated time 0).

    ``evaluate`` records every cycle and scores the run once it ends
    (:mod:`hdhil.rig.evaluate`); without it memory stays flat. ``stop_requested`` is
    polled at every cycle boundary (how Ctrl-C ends a run without losing a frame);
    ``monitor`` gets the controller every ``monitor_every`` samples; ``extra_listeners``
    see every frame of both buses. The nodes come from factories
    (:mod:`hdhil.rig.factories`): by default the firmware's controller (configuring its
    drive from the request's DCF, if any) and one emulated drive per layout slot.
    """
    plan = plan_run(request, interface, channel, realtime)
    if monitor is not None and monitor_every < 1:
        raise ConfigError(f"monitor_every must be >= 1 sample, got {monitor_every}")
    scenario = request.scenario
    Ts = plan.sample_period_s
    pacer = RealtimeLoop(Ts, realtime_config) if realtime else None  # checks its options
    factories = drive_factories or [scenario_drive(scenario)]
    if controller_factory is None:
        dcf = request.mapping.dcf
        controller_factory = dcf_controller(dcf) if dcf is not None else scenario_controller
    metadata = {**run_metadata(request), **(metadata or {})}
    evaluate_skip_s = request.evaluate_from_s
    # Injected faults (the scenario's [faults] table), reproducible by their seed and logged.
    injector = (
        FaultInjector(scenario.faults, FaultLog(fault_log)) if scenario.faults is not None else None
    )
    clock = WallClock() if realtime else SimClock()
    # One BLAS thread for the run: the matrices here are at most 7x7, so BLAS threads
    # only spin and take the core the trace writer runs on; and a thread pool created
    # under SCHED_FIFO on one pinned CPU (OpenBLAS restarts its pool lazily after the
    # writer's fork) starves its own workers and livelocks the real-time loop.
    blas = threadpool_limits(limits=1)
    if start_time is None:
        start_time = round(time.time(), 3)  # whole ms: the resolution of BLF's header date
    buses = RigBuses(plan, clock, injector, open_control_bus)
    listening: RunListeners | None = None
    listeners: list[can.Listener] = []
    wall = 0.0
    frames_sent: dict[str, int] = {}
    try:
        nodes = build_nodes(plan, buses, controller_factory, factories, injector)
        listening = build_listeners(plan, trace, evaluate, evaluate_skip_s, extra_listeners,
                                    start_time, metadata)  # fmt: skip
        listeners = listening.all
        tap = BusTap(nodes.tap_buses, listeners)
        controller = nodes.controller
        pumped = nodes.controller_bus if plan.simulated else None
        in_cycle_time = buses.faulty_transmit and pacer is None
        assert pumped is None or isinstance(pumped, SimBus)
        loop = NodeLoop(
            [*nodes.drives, controller],
            producer=controller,
            answers=lambda: controller.diagnostics.commands_sent,
            expects_answer=lambda: controller_expects_answer(controller),
            listeners=[tap],
            listen_every=TAP_EVERY_CYCLES if plan.simulated and pacer is None else 1,
            period_s=Ts,
            sim_clock=clock,
            # None: the sim clock; also on another interface when the nodes put their own
            # frames through faults (lockstep over a lossy link: a dropped answer closes
            # its cycle after a short wait and costs one cycle of the nodes' time, as on
            # the simulated bus, not half a second of their heartbeat timers).
            node_time=None if plan.simulated or in_cycle_time else time.monotonic,
            pump=pumped,
            pacer=pacer,
            timeout_s=FAULTY_CYCLE_TIMEOUT_S if in_cycle_time else None,
        )
        if pacer is not None:
            pacer.instrument(controller)
            pacer.enter()
        wall0 = time.perf_counter()
        try:
            if pacer is not None:
                assert isinstance(clock, WallClock)
                clock.restart(pacer.start())
            counts = run_phases(loop, nodes, plan.cycles, pacer, stop_requested, monitor,
                                monitor_every, lossy=in_cycle_time)  # fmt: skip
        finally:
            if pacer is not None:
                pacer.exit()
        wall = time.perf_counter() - wall0
        tap.poll()
        frames_sent = _frames_sent(nodes.controller_bus, nodes.truth_bus)
    finally:
        # Close the trace (flush, valid file) and release the buses whatever happened.
        try:
            for listener in listeners:
                listener.stop()
        finally:
            buses.shutdown()
            if injector is not None:
                injector.log.close()  # every injected fault is on disk
            blas.restore_original_limits()
    if counts.keyboard and stop_requested is None:
        # A caller that polls no stop request (bench, tune, a script) gets Ctrl-C as it
        # came, once the trace is closed and the buses released: a loop around runs must
        # end, not start the next run.
        raise KeyboardInterrupt
    result = _result(plan, nodes, listening, counts, wall, frames_sent, trace, injector, pacer,
                     evaluate_skip_s)  # fmt: skip
    result.start_time = start_time if plan.clock_time else None
    return result


def _result(
    plan: RunPlan,
    nodes: RigNodes,
    listening: RunListeners,
    counts: PhaseCounts,
    wall: float,
    frames_sent: dict[str, int],
    trace: Path | None,
    injector: FaultInjector | None,
    pacer: RealtimeLoop | None,
    evaluate_skip_s: float,
) -> RunResult:
    """The scored result of a finished run, every figure from the run itself."""
    recorder, tracking = listening.recorder, listening.tracking
    scored = plan.scenario.scored
    evaluation = (
        evaluate_recording(recorder.recording, plan.firmware, evaluate_skip_s)
        if recorder is not None and not counts.interrupted and "ripple" in scored
        else None
    )
    tracked = (
        {"law": plan.firmware.control.law.name.lower(), **tracking.result().as_dict()}
        if tracking is not None
        else None
    )
    names = _frame_names()
    counter = listening.counter
    frames = {
        names.get(key, f"channel {key[0]} 0x{key[1]:X}"): n
        for key, n in sorted(counter.counts.items())
    }
    drives = nodes.drives
    drive = (
        _drive_diagnostics(drives[0])
        if len(drives) == 1
        else {f"node {d.config.node_id}": _drive_diagnostics(d) for d in drives}
    )
    Ts = plan.sample_period_s
    done = counts.operation
    scorer = listening.scorer
    return RunResult(
        scenario=plan.scenario.name,
        seed=plan.seed,
        interface=plan.interface or "python-can configuration",
        actuation=plan.actuation,
        cycles=done,
        sample_period_s=Ts,
        simulated_s=done * Ts,
        wall_s=wall,
        interrupted=counts.interrupted,
        frames=frames,
        frames_total=counter.total,
        frames_sent=frames_sent,
        startup_cycles=counts.startup,
        stop_cycles=counts.stop,
        worst_case_load=plan.load.worst_case_load,
        bitrate=plan.bitrate,
        torque={**scorer.result().as_dict(), "rms_filtered_per_minute": scorer.block_rms},
        velocity_final=scorer.velocity_final,
        velocity_peak=scorer.velocity_peak,
        trace=str(trace) if trace is not None else None,
        evaluation=evaluation,
        faults=injector.summary() if injector is not None else None,
        tracking=tracked,
        headline=headline(scored, evaluation, tracked, evaluate_skip_s),
        scored=scored,
        controller=_controller_diagnostics(nodes.controller),
        drive=drive,
        realtime=pacer.result() if pacer is not None else None,
        recording=recorder.recording if recorder is not None else None,
        verdict=(
            None
            if counts.interrupted
            else startup_verdict(
                nodes.controller,
                counts.startup_failure,
                counts.startup_node,
                counts.startup,
                plan.cycles,
                Ts,
            )
            if counts.startup_failure is not None
            else stop_verdict(nodes.controller, plan.cycles, done, Ts)
        ),
    )


def format_result(r: RunResult) -> str:
    t = r.torque
    lines = [
        f"hdhil run: scenario {r.scenario}, seed {r.seed}, "
        f"{'real time' if r.realtime is not None else 'lockstep'} on {r.interface}"
        f" ({r.actuation} actuation)" + ("  [INTERRUPTED]" if r.interrupted else ""),
        f"  simulated time     {r.simulated_s:.3f} s ({r.cycles} cycles of "
        f"{r.sample_period_s * 1e3:g} ms in operation; start-up {r.startup_cycles}, "
        f"stop {r.stop_cycles} cycles)",
        f"  wall time          {r.wall_s:.3f} s",
        f"  real-time factor   {r.real_time_factor:.1f}x",
        f"  motor velocity     final {r.velocity_final:.1f} rad/s, peak {r.velocity_peak:.1f} rad/s"
        " (telemetry)",
        format_headline(r.headline),
        "  frames on the buses:",
    ]
    lines += [f"    {name:<34} {n:>8}" for name, n in r.frames.items()]
    lines.append(f"    {'total':<34} {r.frames_total:>8}")
    verdict = "ok" if r.worst_case_load <= LOAD_LIMIT else "OVER the 60 % budget"
    lines.append(
        f"  control bus load   {r.worst_case_load:.1%} worst case at "
        f"{r.bitrate / 1e6:g} Mbit/s ({verdict})"
    )
    if "ripple" not in r.scored:
        pass  # the telemetry's torque is the law's estimate: no filter to score
    elif t["samples"]:
        lines.append(
            f"  whole run          {t['samples']} telemetry samples: RMS true torque "
            f"{t['rms_true']:.4f} Nm; RMS error raw {t['rms_error_raw']:.4f} Nm, filtered "
            f"{t['rms_error_filtered']:.4f} Nm ({t['filtered_to_raw']:.1%} of raw)"
        )
    else:
        lines.append("  whole run          no telemetry/truth pairs were seen")
    if r.faults is not None:
        injected = ", ".join(f"{kind} {n}" for kind, n in r.faults.items()) or "none"
        lines.append(f"  faults injected    {injected}")
    c = r.controller
    if c.get("tacho_rejections") or c.get("encoder_rejections") or c.get("plausibility_errors"):
        lines.append(
            f"  plausibility       replaced {c['tacho_rejections']} tacho samples and "
            f"{c['encoder_rejections']} encoder increments; {c['tacho_reseeds']} / "
            f"{c['encoder_reseeds']} accepted as a new level (tacho / encoder); "
            f"{c['plausibility_errors']} sensor errors (EMCY)"
        )
    if r.tracking is not None:
        lines.append(format_tracking([r.tracking]))
    if r.evaluation is not None:
        lines.append(format_evaluation(r.evaluation))
    if r.realtime is not None:
        lines.append(format_realtime(r.realtime))
    if r.trace:
        lines.append(f"  trace              {r.trace} ({r.frames_total} frames)")
    if r.verdict is not None:
        lines.append(f"  verdict            {format_verdict(r.verdict)}")
    return "\n".join(lines)


#: The laws ``--compare-laws`` runs, as ``(label, trace suffix, [firmware.control]
#: overrides)``: the seed's three ([Vertechy] §IV: JTF1 = Eq. 4 with the LQ design, JTF2
#: k3 = 0, k4 = 1 + Jm/Jl, JTF3 k3 = 0, k4 = 1), JTF2 and JTF3 as [Vertechy] §V says the
#: literature builds them (τ̂s, τ̂s' from a low-pass and a derivative filter of the
#: measurement, ``estimates = "filters"``, cut-offs ``firmware.config.JTF_LOWPASS_HZ``,
#: ``JTF_DERIVATIVE_HZ``), and JTF1 with desired-torque-derivative feedforward tuned for
#: the tracking scenario (:data:`firmware.config.JTF1_FF_TRACKING`: exact feedforward
#: gains, V = 1e7).  A scenario with the Eq. 5 friction compensation keeps it for every
#: law and adds JTF1 without it (:data:`WITHOUT_FRICTION_COMPENSATION`).
COMPARED_LAWS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("JTF1", "jtf1", {"law": "jtf1"}),
    ("JTF2", "jtf2", {"law": "jtf2"}),
    ("JTF3", "jtf3", {"law": "jtf3"}),
    ("JTF2, filters (§V)", "jtf2-filters", {"law": "jtf2", "estimates": "filters"}),
    ("JTF3, filters (§V)", "jtf3-filters", {"law": "jtf3", "estimates": "filters"}),
    ("JTF1 + feedforward", "jtf1_ff",
     {"law": "jtf1_ff", "feedforward": "exact", "weights": {"V": 1e7}}),
)  # fmt: skip
#: The extra row of a scenario that compensates the motor friction (Eq. 5): JTF1 with
#: Eq. 4, no model.
WITHOUT_FRICTION_COMPENSATION = (
    "JTF1 without friction comp. (Eq. 4)",
    "jtf1-eq4",
    {"law": "jtf1", "friction": {"coulomb_Nm": 0.0}},
)


def format_tracking(rows: list[dict[str, Any]]) -> str:
    """The tracking table: e = T_true − T_desired, the observer's exogenous-torque
    estimate against its truth (τlgd, or τlg with Eq. 5) and against the true external
    torque τl + τg (the handle torque of [Vertechy]'s experiment), and the envelope of the
    commanded motor torque (:class:`hdhil.rig.score.TrackingScore`)."""
    lines = [
        "  torque tracking vs truth (e = T_true − T_desired; τ̂: the observer's τlgd, "
        "τlg with Eq. 5)",
        f"    {'law':<30} {'max |e|/Nm':>10} {'RMS e/Nm':>9} {'RMS τ̂ err/Nm':>13} "
        f"{'max |τ̂−τl|/Nm':>14} {'max |τm|/Nm':>11} {'|e|≤0.5':>8} {'samples':>8}",
    ]
    for r in rows:
        lines.append(
            f"    {r['law']:<30} {r['max_abs_error']:10.3f} {r['rms_error']:9.3f} "
            f"{r['rms_disturbance_error']:13.3f} {r.get('max_external_error', math.nan):14.3f} "
            f"{r.get('max_abs_tau_m', math.nan):11.1f} "
            f"{100 * r.get('share_within_goal', math.nan):7.1f}% {r['samples']:8d}"
        )
    return "\n".join(lines)


def compare_laws(request: RunRequest, **kwargs: Any) -> list[dict[str, Any]]:
    """Run ``request`` once per law of :data:`COMPARED_LAWS` (and without friction
    compensation if the scenario has it), each closed over the bus."""
    rows = []
    trace: Path | None = kwargs.pop("trace", None)
    laws = list(COMPARED_LAWS)
    scenario = request.scenario
    if scenario.firmware.control.friction.coulomb_Nm > 0.0:
        laws.insert(1, WITHOUT_FRICTION_COMPENSATION)
        laws[0] = ("JTF1 with friction comp. (Eq. 5)", "jtf1", {"law": "jtf1"})
    base = scenario_data(scenario)
    for label, slug, control in laws:
        variant = scenario_from_dict(merge(base, {"firmware": {"control": control}}), label)
        law_trace = _suffixed(trace, slug) if trace else None
        r = run_lockstep(dataclasses.replace(request, scenario=variant), trace=law_trace,
                         evaluate=False, **kwargs)  # fmt: skip
        if r.tracking is None:
            raise ConfigError(f"{scenario.name}: no tracking telemetry for {label}")
        row = {**r.tracking, "law": label, "trace": str(law_trace) if law_trace else None,
               "real_time_factor": r.real_time_factor}  # fmt: skip
        if r.verdict is not None:
            row["verdict"] = r.verdict
        rows.append(row)
        if r.interrupted:
            break
    return rows
