"""The wiring of a run: its python-can buses, its nodes and the host tap's listeners.

:class:`RigBuses` opens one handle per node and per tap on the control bus (the run's
interface) and on the truth channel (always the simulated bus), with the run's injected
faults, and closes every one it opened. :func:`build_nodes` builds the controller and
one drive per slot of the layout through their factories (:mod:`hdhil.rig.factories`);
:func:`build_listeners` sets up what listens on the tap (frame counter, scorers, the
recording, the trace writer). Kept apart from the phases (:mod:`hdhil.rig.phases`) and
from the run that plans and scores (:mod:`hdhil.rig.runner`).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from hdhil.can.faults import ChannelFaults, FaultyTransmitBus, check_node_transmit_faults
from hdhil.can.groups import GroupChannel
from hdhil.can.simbus import SimClock
from hdhil.can.traces.tap import FrameCounter
from hdhil.can.traces.writer import WriterProcess
from hdhil.core.dataconf import ConfigError
from hdhil.dbc import CHANNEL_NUMBER
from hdhil.firmware.config import Law
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveNode
from hdhil.rig.evaluate import LiveEvaluationFactory, RecordingListener
from hdhil.rig.factories import ControllerFactory, DriveFactory, NodeSite, layout_joints
from hdhil.rig.faults import FaultInjector
from hdhil.rig.score import TorqueScorer, TrackingScorer
from hdhil.rig.sidecar import utc_text

if TYPE_CHECKING:
    from hdhil.rig.runner import RunPlan

_run_ids = itertools.count(1)


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
        #: The truth channel as frame groups (:meth:`truth`), once opened.
        self._groups: GroupChannel | None = None

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

    def truth(self, node_id: int | None = None) -> can.BusABC | GroupChannel:
        """A new handle on the truth channel for drive ``node_id`` (None: the tap).

        Without truth faults the channel is the run's one :class:`GroupChannel`: each
        drive's three truth frames of a cycle go to the tap as one group (nothing else
        listens, nothing shares a wire with them). Faults act on single frames: with
        them, the channel is a simulated bus."""
        if self._truth_faults is None:
            if self._groups is None:
                self._groups = GroupChannel(self.clock, CHANNEL_NUMBER["truth"],
                                            f"hdhil-{self.run_id}-truth")  # fmt: skip
                self.opened.append(self._groups)  # type: ignore[arg-type]
            return self._groups
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
    truth_bus: can.BusABC | GroupChannel  # one drive's handle on the truth channel (frame counts)
    tap_buses: dict[int, can.BusABC | GroupChannel]


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
        joint_configs=layout_joints(plan.request.scenario, layout),
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
    #: The run's result keeps the recorder's recording (every cycle).
    keep_recording: bool = True
    #: The trace writer whose process runs the evaluation in place of ``recorder``
    #: (its result: :func:`hdhil.rig.runner.collect_evaluation`).
    evaluating_writer: WriterProcess | None = None
    #: The trace writer (renames the trace, its sidecar and the companions into place).
    writer: WriterProcess | None = None


def build_listeners(
    plan: RunPlan,
    trace: Path | None,
    evaluate: bool,
    evaluate_skip_s: float,
    extra: Sequence[can.Listener],
    start_time: float = 0.0,
    metadata: dict[str, Any] | None = None,
    keep_recording: bool = True,
    companions: Sequence[tuple[Path, Path, str]] = (),
) -> RunListeners:
    """The tap's listeners, the trace writer first (it sees every frame as it came).

    In lockstep (on any interface) and on the simulated bus the trace's times are the
    run's clock plus ``start_time`` (:attr:`hdhil.rig.runner.RunPlan.clock_time`); the
    trace's sidecar JSON gets the run's settings and ``metadata``.

    With ``evaluate`` the recorder scores a run in lockstep as it goes (its memory flat
    without ``keep_recording``); in real time it records every cycle and the scoring
    waits for the end, so that it takes no time from the loop's deadlines.  A run in
    lockstep that writes a trace and keeps no recording is scored in the trace writer's
    process instead (:class:`LiveEvaluationFactory`), unless the writer cannot take it
    (``spawn`` start method and a configuration that cannot be pickled).

    ``companions`` (``(temporary, target, label)``: the run's fault log) are renamed into
    place by the trace writer together with the trace and its sidecar."""
    layout = plan.layout
    drive_id, controller_id = layout.drives[0].node_id, layout.controller_node_id
    counter, scorer = FrameCounter(), TorqueScorer(controller_node_id=controller_id)
    listeners: list[can.Listener] = [counter, scorer]
    tracking = recorder = None
    control = plan.firmware.control
    if control.law != Law.NONE:
        tracking = TrackingScorer(
            control.joint.Jl / control.joint.Jm,
            evaluate_skip_s,
            control.friction.active,
            plan.sample_period_s,
            plan.scenario.plant.link,
            controller_node_id=controller_id,
        )
        listeners.append(tracking)
    scored = evaluate and "ripple" in plan.scenario.scored
    live = scored and not plan.realtime
    drive_pdos = (metadata or {}).get("drive_pdos")
    writer = None
    if trace is not None:
        offset = start_time if plan.clock_time else 0.0
        sidecar = {
            "scenario": plan.scenario.name, "seed": plan.seed,
            "duration_s": plan.cycles * plan.sample_period_s,
            "sample_period_s": plan.sample_period_s,
            "start_time": start_time if plan.clock_time else None,
            "start_time_utc": utc_text(start_time) if plan.clock_time else None,
            "time_offset_s": offset, "interface": plan.interface or "python-can configuration",
            "bitrate": plan.bitrate, "actuation": plan.actuation,
            "channels": dict(CHANNEL_NUMBER), "control_law": control.law.name.lower(),
            **(metadata or {}),
        }  # fmt: skip
        # A live evaluation that keeps no rows runs in the writer's process, on the frames
        # it writes (the same frames, in the same order), off the loop's core.
        offload = (
            LiveEvaluationFactory(
                plan.sample_period_s,
                drive_pdos,
                plan.firmware,
                evaluate_skip_s,
                drive_id,
                controller_id,
            )
            if live and not keep_recording
            else None
        )
        # the sidecar is written with the finished trace (both renamed into place)
        writer = WriterProcess(trace, time_offset=offset, metadata=sidecar,
                               child_listener=offload, companions=tuple(companions))  # fmt: skip
        listeners.insert(0, writer)
    evaluating = writer if writer is not None and writer.child_listening else None
    if evaluate and (scored or keep_recording) and evaluating is None:
        recorder = RecordingListener(
            plan.sample_period_s,
            drive_pdos,
            firmware=plan.firmware if live else None,
            skip_s=evaluate_skip_s,
            keep=keep_recording or not live,
            drive_node_id=drive_id,
            controller_node_id=controller_id,
        )
        listeners.append(recorder)
    listeners += extra
    return RunListeners(counter, scorer, tracking, recorder, listeners, keep_recording, evaluating,
                        writer)  # fmt: skip
