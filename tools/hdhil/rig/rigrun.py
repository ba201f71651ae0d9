"""A rig of several joints in one process, lockstep on the simulated buses: :func:`run_rig`.

The rig is the scenario's layout (:mod:`hdhil.rig.layout`): one simulated CAN channel
per named bus, all on one :class:`~hdhil.can.simbus.SimClock`; on each bus its drives
(:class:`hostsim.drive.DriveNode` at their node-IDs) and its controller nodes
(:class:`firmware.controller.ControllerNode`, one interrupt handler per joint, two joints
a node: the node at the bus's ``controller_node_id`` produces the bus's SYNC, a further
node at a joint's own ``controller_node_id`` follows it). Each drive's plant is its joint
of the arm (:class:`hostsim.plant.arm.ArmPlant`, moved once a cycle by the first drive's
SYNC with every drive's held input) when the scenario names a ``[robot]``, else its own
:class:`hostsim.plant.Plant`. One node loop (:class:`hdhil.rig.loop.NodeLoop`) sends
every bus's SYNC in the same cycle.

A free arm starts at rest under its weight in its joints' ``start_rad`` pose, its
brakes on until every joint's command reaches its drive (:meth:`ArmPlant.rest_under_load`,
:meth:`ArmPlant.apply_brakes`); an arm a person wears starts where they hold it.

Each bus has its own truth channel (frame groups, in-process) on which its drives send
their joint's truth at the joint's identifiers (:func:`hdhil.dbc.truth_frame_id`, the
joint's index in the layout), and its own host tap with a frame counter and, per joint,
the torque scorer (the joint's telemetry at its link's identifiers against its truth)
and, with a control law, the tracking scorer, both from the run's ``evaluate_from_s``,
and unless ``evaluate`` is off the candidate filters of a single joint's evaluation,
scored as the frames come. Frames of two buses share identifiers (the pre-defined
connection set numbers each bus alike), so each bus is scored on its own.

On a CAN FD bus the joints' cyclic PDOs are packed per direction into FD frames
(:mod:`hdhil.rig.fdpack`: the bus's database has the packed layouts, a gateway node
sends them) and the telemetry goes as FD frames, with bit-rate switching when the bus
has a data bit rate.  A bus's ``telemetry_every`` decimates the telemetry
(:func:`hdhil.canopen.rigdb.telemetry_phases`).

The scorers of a joint (:func:`joint_scoring`) are also those that score its trace
(``hdhil evaluate``, :func:`hdhil.rig.trace_score.score_rig_trace`), fed the trace's
frames of the joint's bus and the truth: the same figures as the run's.

What a rig does not take yet (one-line :class:`ConfigError`): real time, an interface
other than ``simbus``, injected faults, a drive DCF or mapping.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import Any

import can
from threadpoolctl import threadpool_limits

from hdhil.can.groups import GroupChannel, expand_groups
from hdhil.can.simbus import SimBus, SimClock
from hdhil.can.traces.tap import BusTap, FrameCounter
from hdhil.core.dataconf import ConfigError
from hdhil.dbc import CHANNEL_NUMBER
from hdhil.firmware.config import FirmwareConfig, Law
from hdhil.firmware.controller import ControllerNode, DriveLink, JointSetup
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.evaluate import RecordingListener
from hdhil.rig.fdpack import FdGateway, PackingBus
from hdhil.rig.layout import BusSpec, JointSpec, rigdb_layout
from hdhil.rig.loop import NodeLoop
from hdhil.rig.request import RunRequest
from hdhil.rig.scenario import Scenario
from hdhil.rig.score import TorqueScorer, TrackingScorer

__all__ = [
    "JointScores",
    "JointScoring",
    "RigJointResult",
    "RigResult",
    "bus_channel",
    "format_joint_table",
    "format_rig_evaluation",
    "format_rig_result",
    "joint_links",
    "joint_scoring",
    "run_rig",
    "worst_joint",
]

#: The tap drains its queues every this many cycles (as the single-joint run's).
TAP_EVERY_CYCLES = 16
#: Start-up and stop give up after this many cycles.
MAX_STARTUP_CYCLES = 3000
MAX_STOP_CYCLES = 200

_rig_ids = itertools.count(1)


def bus_channel(index: int) -> int:
    """The channel number of the rig's ``index``-th bus: 0 for the first, then 2, 3, ...
    The truth keeps channel 1 (``CHANNEL_NUMBER``), so a single-joint trace and the
    first bus of a rig number their frames alike."""
    return CHANNEL_NUMBER["control"] if index == 0 else index + 1


@dataclass
class JointScores:
    """One joint's scores: where it sits, its torque and tracking figures and its
    candidate filters' evaluation (:func:`hdhil.rig.evaluate.evaluate`'s dict, None when
    not evaluated); read back from a trace by :func:`hdhil.rig.trace_score.
    score_rig_trace`."""

    name: str
    bus: str
    node_id: int
    controller_node_id: int
    joint_index: int
    torque: dict[str, float]
    tracking: dict[str, Any] | None = None
    evaluation: dict[str, Any] | None = None


@dataclass
class RigJointResult(JointScores):
    """One joint's figures from a run: its :class:`JointScores` and what only the run
    knows, the drive's state and the interrupts it ran."""

    _: KW_ONLY
    drive_state: str
    samples: int


@dataclass
class RigResult:
    """What a run of a rig did: per joint, the worst joint, frames per bus."""

    scenario: str
    seed: int
    cycles: int
    sample_period_s: float
    simulated_s: float
    wall_s: float
    startup_cycles: int
    stop_cycles: int
    interrupted: bool
    joints: list[RigJointResult]
    frames: dict[str, int]
    buses: dict[str, dict[str, Any]]
    worst_joint: dict[str, Any] = field(default_factory=dict)
    verdict: dict[str, Any] | None = None
    #: Per-cycle wall time of the loop in operation (us).
    us_per_cycle: float = math.nan
    #: Whether the candidate filters were evaluated per joint (:attr:`RigJointResult.evaluation`).
    evaluated: bool = False
    trace: str | None = None
    #: What the scenario scores (:attr:`hdhil.rig.scenario.Scenario.scored`): the torque
    #: columns are the ripple filter's only with ``ripple``.
    scored: tuple[str, ...] = ("ripple",)
    #: The torque and tracking scores start at this time in operation (s): the run's
    #: ``evaluate_from_s``.
    evaluate_from_s: float = 0.0

    @property
    def real_time_factor(self) -> float:
        return self.simulated_s / self.wall_s if self.wall_s > 0 else math.inf

    def as_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "joints"}
        d["joints"] = [dict(j.__dict__) for j in self.joints]
        if d["verdict"] is None:
            del d["verdict"]
        d["real_time_factor"] = self.real_time_factor
        return d


class OnChannels(can.Listener):
    """Hands ``listener`` the frames (and frame groups) of ``channels`` only: the frames of
    one bus and the truth, for a scorer of a joint on that bus (two buses of a rig carry
    the same identifiers)."""

    takes_frame_groups = True

    def __init__(self, listener: can.Listener, channels: frozenset[int]) -> None:
        self.listener = listener
        self.channels = channels
        self._frames = getattr(listener, "on_frames", None)
        self._groups = bool(getattr(listener, "takes_frame_groups", False))

    def on_message_received(self, msg: can.Message) -> None:
        if msg.channel in self.channels:
            self.listener.on_message_received(msg)

    def on_frames(self, frames: list[Any]) -> None:
        channels = self.channels
        mine = [f for f in frames if f.channel in channels]
        if not mine:
            return
        if not self._groups:
            mine = expand_groups(mine)
        if self._frames is not None:
            self._frames(mine)
        else:
            for msg in mine:
                self.listener.on_message_received(msg)


@dataclass(frozen=True)
class RigEvaluationFactory:
    """The candidate filters of every joint, evaluated in the trace writer's process
    (``child_listener`` of :class:`hdhil.can.traces.writer.WriterProcess`) on the frames
    it writes, off the loop's core, as :class:`hdhil.rig.evaluate.LiveEvaluationFactory`
    does for one joint.  Per joint: its firmware, the evaluation start, its drive's
    node-ID, its telemetry identifier, its index and its channels (its bus and the
    truth).  The listener's result: each joint's evaluation, in the layout's order."""

    sample_period_s: float
    joints: tuple[tuple[FirmwareConfig, float, int, int, int, frozenset[int]], ...]

    def __call__(self) -> _RigEvaluation:
        return _RigEvaluation(self)


class _RigEvaluation(can.Listener):
    def __init__(self, factory: RigEvaluationFactory) -> None:
        self.recorders = [
            RecordingListener(
                factory.sample_period_s, firmware=fw, skip_s=skip, keep=False,
                drive_node_id=node_id, telemetry_id=telemetry_id, truth_joint_index=index,
            )
            for fw, skip, node_id, telemetry_id, index, _ in factory.joints
        ]  # fmt: skip
        self._feeds = [
            OnChannels(r, joint[5]) for r, joint in zip(self.recorders, factory.joints, strict=True)
        ]

    def on_message_received(self, msg: can.Message) -> None:
        for feed in self._feeds:
            feed.on_message_received(msg)

    def on_frames(self, frames: list[Any]) -> None:
        for feed in self._feeds:
            feed.on_frames(frames)

    def result(self) -> list[dict[str, Any]]:
        return [r.result() for r in self.recorders]


def scored_channels(bus_index: int) -> frozenset[int]:
    """The channels a joint on the rig's ``bus_index``-th bus is scored from: its bus's
    and the truth's."""
    return frozenset((bus_channel(bus_index), CHANNEL_NUMBER["truth"]))


def joint_links(scenario: Scenario) -> list[DriveLink]:
    """Each joint's link in the layout's order: its drive's PDOs and the telemetry of its
    controller node, the joint's rank at that node its place among the node's joints on
    its bus (as :func:`run_rig` gives them), in CiA 301's pre-defined connection set (a
    rig runs the raw mapping only)."""
    ranks: dict[tuple[str, int], int] = {}
    links = []
    for spec in scenario.joints:
        key = (spec.bus, spec.controller_node_id)
        rank = ranks[key] = ranks.get(key, -1) + 1
        try:
            links.append(DriveLink.predefined(spec.node_id, spec.controller_node_id, rank))
        except ValueError as exc:
            raise ConfigError(f"joint {spec.name}: {exc}") from None
    return links


@dataclass
class JointScoring:
    """One joint's scorers: its torque against its truth and, with a control law, its
    tracking; fed its bus's frames and the truth (:meth:`listeners`)."""

    torque: TorqueScorer
    tracking: TrackingScorer | None
    law: str | None
    #: The candidate filters' evaluation, scored as the frames come (None: not evaluated).
    candidates: RecordingListener | None = None

    def listeners(self, channels: frozenset[int]) -> list[can.Listener]:
        """The scorers, each handed the frames of ``channels`` only (:class:`OnChannels`)."""
        scorers: list[can.Listener] = [self.torque]
        if self.tracking is not None:
            scorers.append(self.tracking)
        if self.candidates is not None:
            scorers.append(self.candidates)
        return [OnChannels(scorer, channels) for scorer in scorers]

    def evaluation(self) -> dict[str, Any] | None:
        """The candidate filters' evaluation (None when not evaluated)."""
        return None if self.candidates is None else self.candidates.result()

    def results(self) -> tuple[dict[str, float], dict[str, Any] | None]:
        """The torque figures and the tracking figures (None without a law)."""
        torque = self.torque.result().as_dict()
        if self.tracking is None:
            return torque, None
        return torque, {"law": self.law, **self.tracking.result().as_dict()}


def joint_scoring(
    request: RunRequest, index: int, link: DriveLink, skip_s: float, *, candidates: bool = False
) -> JointScoring:
    """The scorers of the rig's ``index``-th joint at ``link``'s telemetry identifiers and
    the joint's truth: the run's (:func:`run_rig`) and its trace's
    (:func:`hdhil.rig.trace_score.score_rig_trace`). The tracking counts from ``skip_s``
    (the run's evaluation start), the torque as long after its first telemetry frame.
    With ``candidates``, also the candidate filters of a single joint's evaluation
    (:class:`~hdhil.rig.evaluate.RecordingListener` with the joint's firmware, scoring
    as it goes from ``skip_s``)."""
    plant, fw = request.scenario.joint_configs[index]
    spec = request.scenario.joints[index]
    torque = TorqueScorer(telemetry_id=link.telemetry_cob_id, joint_index=index,
                          skip_from_first_s=skip_s,
                          sample_period_s=request.sample_period_s)  # fmt: skip
    evaluation = (
        RecordingListener(
            request.sample_period_s, firmware=fw, skip_s=skip_s, keep=False,
            drive_node_id=spec.node_id, telemetry_id=link.telemetry_cob_id,
            truth_joint_index=index,
        )
        if candidates
        else None
    )  # fmt: skip
    control = fw.control
    if control.law == Law.NONE:
        return JointScoring(torque, None, None, evaluation)
    tracking = TrackingScorer(
        control.joint.Jl / control.joint.Jm,
        skip_s,
        control.friction.active,
        request.sample_period_s,
        plant.link,
        telemetry_ids=(link.telemetry_cob_id, link.control_cob_id),
        joint_index=index,
    )
    return JointScoring(torque, tracking, control.law.name.lower(), evaluation)


@dataclass
class _Joint:
    spec: JointSpec
    index: int
    plant: PlantConfig
    firmware: FirmwareConfig
    drive: DriveNode | None = None
    controller: ControllerNode | None = None
    rank: int = 0
    scoring: JointScoring | None = None


def check_rig_options(
    request: RunRequest,
    *,
    interface: str | None = "simbus",
    realtime: bool = False,
    compare_laws: bool = False,
    fault_log: Any = None,
) -> None:
    """Refuse, with one line (:class:`ConfigError`), what a rig of several joints does not
    take yet: another interface than ``simbus``, real time, ``--compare-laws``, a fault
    log, injected faults, a drive DCF or mapping."""
    name = request.scenario.name
    what = None
    if interface != "simbus":
        what = f"interface {interface}"
    elif realtime:
        what = "--realtime"
    elif compare_laws:
        what = "--compare-laws"
    elif fault_log is not None:
        what = "--fault-log"
    if what is not None:
        raise ConfigError(
            f"scenario {name} lays out {len(request.scenario.joints)} joints: a rig of several "
            f"joints runs lockstep on simbus without {what} so far"
        )
    _check(request)


def _check(request: RunRequest) -> None:
    s = request.scenario
    if request.mapping.dcf is not None:
        raise ConfigError(f"scenario {s.name}: a rig of several joints runs the raw mapping only")
    if s.faults is not None:
        raise ConfigError(f"scenario {s.name}: a rig of several joints runs without [faults]")


def run_rig(
    request: RunRequest,
    *,
    trace: Path | None = None,
    start_time: float | None = None,
    stop_requested: Callable[[], bool] | None = None,
    evaluate: bool = True,
) -> RigResult:
    """Run the rig of ``request``'s scenario for its duration, lockstep on the simulated
    buses, and score every joint (module docstring). ``trace``: every bus on its channel
    (:func:`bus_channel`) and the truth, with a sidecar that records the layout
    (:func:`rig_metadata`); ``start_time`` the Unix time of simulated time 0 (default
    now, to the millisecond); ``evaluate``: the candidate filters per joint too."""
    s = request.scenario
    if not s.is_rig:
        raise ConfigError(f"scenario {s.name} is a single joint: hdhil.rig.runner runs it")
    _check(request)
    joints = [
        _Joint(spec, j, plant, fw)
        for j, (spec, (plant, fw)) in enumerate(zip(s.joints, s.joint_configs, strict=True))
    ]
    buses: dict[str, BusSpec] = dict(s.buses)
    clock = SimClock()
    rig_id = next(_rig_ids)
    opened: list[Any] = []

    def handle(bus_name: str, index: int, node_id: int | None) -> SimBus:
        spec = buses[bus_name]
        bus = can.Bus(
            interface="simbus",
            channel=f"hdhil-rig{rig_id}-{bus_name}",
            bitrate=spec.bitrate,
            clock=clock,
            trace_channel=bus_channel(index),
            node_id=node_id,
            data_bitrate=(spec.data_bitrate or None) if spec.fd else None,
        )
        opened.append(bus)
        return bus  # type: ignore[no-any-return]

    writer = None
    if trace is not None:
        from hdhil.can.traces.writer import WriterProcess

        if start_time is None:
            start_time = round(time.time(), 3)  # whole ms: the resolution of BLF's date
        writer = WriterProcess(trace, time_offset=start_time,
                               metadata=rig_metadata(request, start_time),
                               child_listener=_offload(request) if evaluate else None,
                               fd=any(spec.fd for spec in buses.values()))  # fmt: skip
    offloaded = writer is not None and writer.child_listening
    blas = threadpool_limits(limits=1)
    completed = False
    try:
        result = _run(request, joints, buses, clock, handle, opened, stop_requested, writer,
                      evaluate and not offloaded)  # fmt: skip
        result.evaluated = evaluate
        if writer is not None:
            writer.stop()  # the trace and its sidecar renamed into place
            result.trace = str(trace)
            if offloaded:
                if result.interrupted:
                    writer.discard_child_result()
                else:
                    for row, ev in zip(result.joints, writer.child_result(), strict=True):
                        row.evaluation = ev
        completed = True
        return result
    finally:
        if writer is not None:
            if not completed:
                writer.abort()  # no trace of a run that failed
            writer.discard_child_result()  # a no-op once the result was taken
        for bus in opened:
            bus.shutdown()
        blas.restore_original_limits()


def candidates_scored(scenario: Scenario) -> bool:
    """Whether a rig's candidate filters are evaluated: it scores the ripple filter and no
    bus packs its joints' sensor frames into FD frames (the evaluation reads each
    joint's own sensor frame)."""
    return "ripple" in scenario.scored and not any(spec.fd for _, spec in scenario.buses)


def _offload(request: RunRequest) -> RigEvaluationFactory | None:
    """The candidate filters of every joint for the trace writer's process (None when
    they are not evaluated: :func:`candidates_scored`)."""
    s = request.scenario
    if not candidates_scored(s):
        return None
    bus_index = {name: i for i, (name, _) in enumerate(s.buses)}
    return RigEvaluationFactory(
        request.sample_period_s,
        tuple(
            (fw, request.evaluate_from_s, spec.node_id, link.telemetry_cob_id, index,
             scored_channels(bus_index[spec.bus]))
            for index, (spec, (_, fw), link) in enumerate(
                zip(s.joints, s.joint_configs, joint_links(s), strict=True))
        ),
    )  # fmt: skip


def rig_metadata(request: RunRequest, start_time: float) -> dict[str, Any]:
    """A rig trace's sidecar: the run's settings, the channel of each bus and of the truth,
    and the layout (``rig``: buses and joints) that :func:`hdhil.canopen.mapping.
    trace_decoder` decodes the trace with."""
    from hdhil.rig.sidecar import run_metadata, utc_text

    s = request.scenario
    channels = {name: bus_channel(i) for i, (name, _) in enumerate(s.buses)}
    return {
        "scenario": s.name, "seed": request.seed,
        "duration_s": request.cycles * request.sample_period_s,
        "sample_period_s": request.sample_period_s, "start_time": start_time,
        "start_time_utc": utc_text(start_time),
        "time_offset_s": start_time, "interface": "simbus", "actuation": request.actuation,
        "channels": {**channels, "truth": CHANNEL_NUMBER["truth"]},
        "rig": {
            "buses": [
                {"name": name, "channel": channels[name], "bitrate": spec.bitrate, "fd": spec.fd,
                 "data_bitrate": spec.data_bitrate,
                 "controller_node_id": spec.controller_node_id}
                for name, spec in s.buses
            ],
            "joints": [
                {"name": j.name, "bus": j.bus, "node_id": j.node_id,
                 "controller_node_id": j.controller_node_id, "joint_index": k}
                for k, j in enumerate(s.joints)
            ],
        },
        **run_metadata(request),
    }  # fmt: skip


def _run(
    request: RunRequest,
    joints: list[_Joint],
    buses: dict[str, BusSpec],
    clock: SimClock,
    handle: Callable[[str, int, int | None], SimBus],
    opened: list[Any],
    stop_requested: Callable[[], bool] | None,
    writer: can.Listener | None,
    evaluate: bool,
) -> RigResult:
    s = request.scenario
    Ts = request.sample_period_s
    seed = request.seed
    # -- the plants: the arm's joints, or one plant per joint
    plants: list[Any]
    arm = None
    if s.robot is not None:
        from hdhil.hostsim.plant.arm import ArmPlant
        from hdhil.hostsim.plant.multibody import LinkDynamics

        try:
            arm = ArmPlant(
                LinkDynamics.from_urdf(s.robot.path),
                [j.plant for j in joints],
                [seed + j.index for j in joints],
                start if any(start := [j.spec.start_rad for j in joints]) else None,
            )
            if not arm.worn:  # a free arm rests under its weight, braked until operation
                arm.rest_under_load()
                arm.apply_brakes()
            arm.prepare(Ts)
        except ValueError as exc:
            raise ConfigError(f"scenario {s.name}: {exc}") from None
        plants = [arm.joint(j.index) for j in joints]
    else:
        plants = [Plant(j.plant, seed + j.index) for j in joints]
    # -- the buses' databases: the cycles of decimated telemetry (as the planner has them)
    from hdhil.canopen.rigdb import is_telemetry, rig_packing, telemetry_phases

    databases, packing = rig_packing(*rigdb_layout(s.joints, s.buses))
    gateways: list[FdGateway] = []
    # -- per bus: truth channel, drives, controller nodes, tap
    truth = GroupChannel(clock, CHANNEL_NUMBER["truth"], f"rig{id(clock)}-truth")
    opened.append(truth)
    tapped: dict[int, Any] = {CHANNEL_NUMBER["truth"]: truth}
    listeners: list[can.Listener] = []
    counters: dict[str, FrameCounter] = {}
    producers: list[tuple[ControllerNode, SimBus]] = []
    controllers: list[ControllerNode] = []
    drives: list[DriveNode] = []
    for index, (name, spec) in enumerate(buses.items()):
        on_bus = [j for j in joints if j.spec.bus == name]
        if not on_bus:
            continue
        gateway: FdGateway | None = None
        if packing.get(name):  # an FD bus: the joints' PDOs packed (hdhil.rig.fdpack)
            fd_ids = [m.frame_id for m in databases[name].messages
                      if m.is_fd and is_telemetry(m.name)]  # fmt: skip
            gateway = FdGateway(handle(name, index, None), packing[name], fd_ids,
                                brs=bool(spec.data_bitrate))  # fmt: skip
            gateways.append(gateway)

        def packed(bus: SimBus, gateway: FdGateway | None = gateway) -> Any:
            return bus if gateway is None else PackingBus(bus, gateway)

        for j in on_bus:
            cfg = DriveConfig(
                sample_period_s=Ts,
                actuation=request.actuation,  # type: ignore[arg-type]
                node_id=j.spec.node_id,
                controller_node_id=j.spec.controller_node_id,
                truth_joint_index=j.index,
            )
            j.drive = DriveNode(packed(handle(name, index, j.spec.node_id)), plants[j.index],
                                cfg, truth_bus=truth)  # type: ignore[arg-type]  # fmt: skip
            drives.append(j.drive)
        ids = sorted({j.spec.controller_node_id for j in on_bus},
                     key=lambda cid: (cid != spec.controller_node_id, cid))  # fmt: skip
        if ids[0] != spec.controller_node_id:
            raise ConfigError(
                f"bus {name}: no joint is served by its controller node {spec.controller_node_id}"
                " (the node that produces the bus's SYNC)"
            )
        producer: ControllerNode | None = None
        every = spec.telemetry_every
        phases = telemetry_phases(databases[name], every) if every > 1 else {}
        for cid in ids:
            served = [j for j in on_bus if j.spec.controller_node_id == cid]
            setups = []
            for rank, j in enumerate(served):
                link = DriveLink.predefined(j.spec.node_id, cid, rank)
                setups.append(JointSetup(
                    j.firmware, j.spec.node_id, j.spec.name, link=link, telemetry_every=every,
                    telemetry_phases=(phases.get(link.telemetry_cob_id, 0),
                                      phases.get(link.control_cob_id, 0)),
                ))  # fmt: skip
            bus = handle(name, index, cid)
            try:
                node = ControllerNode(packed(bus), node_id=cid, joints=setups,
                                      sync_producer=cid == spec.controller_node_id)  # fmt: skip
            except ValueError as exc:
                raise ConfigError(f"bus {name}: {exc}") from None
            controllers.append(node)
            if producer is None:
                producer = node
                producers.append((node, bus))
            for rank, j in enumerate(served):
                j.controller, j.rank = node, rank
        channels = scored_channels(index)
        counters[name] = counter = FrameCounter()
        listeners.append(OnChannels(counter, frozenset((bus_channel(index),))))
        for j in on_bus:
            assert j.controller is not None
            j.scoring = joint_scoring(request, j.index, j.controller.joints[j.rank].link,
                                      request.evaluate_from_s,
                                      candidates=evaluate and candidates_scored(s))  # fmt: skip
            listeners += j.scoring.listeners(channels)
        tapped[bus_channel(index)] = handle(name, index, None)
    if writer is not None:
        listeners.insert(0, writer)  # it sees every frame as it came
    tap = BusTap(dict(sorted(tapped.items())), listeners)
    if arm is not None:
        ordered = [j.drive for j in joints]
        arm.input_source = lambda: [d.io.step_V for d in ordered]  # type: ignore[union-attr]
    (first, first_bus), *more = producers
    loop = NodeLoop(
        [*drives, *controllers, *gateways],  # the gateways after the nodes of each round
        producer=first,
        listeners=[tap],
        listen_every=TAP_EVERY_CYCLES,
        period_s=Ts,
        sim_clock=clock,
        node_time=None,
        pump=first_bus,
        more_buses=more,
    )
    # -- start-up, operation, stop
    cycles = request.cycles
    verdict = None
    interrupted = False
    loop.boot()
    while not all(c.phase == "operational" for c in controllers):
        failed = [c for c in controllers if c.boot_error or c.phase == "safe"]
        if failed or loop.k >= MAX_STARTUP_CYCLES:
            states = ", ".join(f"{j.spec.name} {j.drive.drive_state.name}" for j in joints)  # type: ignore[union-attr]
            verdict = {"phase": "start-up", "reason": f"not every joint reached operation "
                       f"within {loop.k} cycles ({states})"}  # fmt: skip
            break
        loop.cycle()
    startup = loop.k
    isrs = [c.joints[r].isr for c in controllers for r in range(len(c.joints))]
    wall0 = time.perf_counter()
    if verdict is None:
        while min(isr.samplecount for isr in isrs) < cycles:
            if stop_requested is not None and stop_requested():
                interrupted = True
                break
            if arm is not None and arm.braked and min(isr.samplecount for isr in isrs) >= 2:
                # every drive applies its controller's command: the brakes let go
                arm.release_brakes()
            if any(c.phase != "operational" for c in controllers):
                nodes = ", ".join(f"node {c.node_id} {c.phase}" for c in controllers)
                verdict = {"phase": "operation",
                           "reason": f"a controller node left operation: {nodes}"}  # fmt: skip
                break
            loop.cycle()
    wall = time.perf_counter() - wall0
    operation = loop.k - startup
    states = {j.spec.name: j.drive.drive_state.name for j in joints}  # type: ignore[union-attr]
    for c in controllers:
        c.request_stop()
    end = loop.k
    for _ in range(MAX_STOP_CYCLES):
        if all(c.phase in ("stopped", "safe") for c in controllers):
            break
        loop.cycle()
    loop.drain()
    done = min(isr.samplecount for isr in isrs)
    rows = []
    for j in joints:
        assert j.scoring is not None and j.controller is not None
        torque, tracked = j.scoring.results()
        rows.append(
            RigJointResult(
                name=j.spec.name,
                bus=j.spec.bus,
                node_id=j.spec.node_id,
                controller_node_id=j.spec.controller_node_id,
                joint_index=j.index,
                drive_state=states[j.spec.name],
                samples=j.controller.joints[j.rank].isr.samplecount,
                torque=torque,
                tracking=tracked,
                evaluation=j.scoring.evaluation(),
            )
        )
    frames = {name: counter.total for name, counter in counters.items()}
    span = loop.k * Ts
    bus_info = {
        name: {"channel": bus_channel(i), "bitrate": spec.bitrate, "fd": spec.fd,
               "joints": [j.spec.name for j in joints if j.spec.bus == name],
               "worst_case_load": bus_load(counters[name].counts, databases[name], spec, span)}
        for i, (name, spec) in enumerate(buses.items())
        if any(j.spec.bus == name for j in joints)
    }  # fmt: skip
    return RigResult(
        scenario=s.name,
        seed=seed,
        cycles=done,
        sample_period_s=Ts,
        simulated_s=done * Ts,
        wall_s=wall,
        startup_cycles=startup,
        stop_cycles=loop.k - end,
        interrupted=interrupted,
        joints=rows,
        frames=frames,
        buses=bus_info,
        worst_joint=worst_joint(rows, "ripple" in s.scored),
        verdict=verdict,
        us_per_cycle=wall / operation * 1e6 if operation else math.nan,
        scored=tuple(s.scored),
        evaluated=evaluate,
        evaluate_from_s=request.evaluate_from_s,
    )


def bus_load(
    counts: dict[tuple[int, int], int], database: Any, spec: BusSpec, span_s: float
) -> float:
    """The worst-case load of a bus over a run: each frame the run sent on it (``counts``
    by channel and identifier) at its worst-case time for its identifier, length and
    format in the bus's ``database`` (:func:`hdhil.can.schedule.worst_case_seconds`: FD
    phases at their bit rates), summed over the run's ``span_s``.  What ``hdhil dump
    --stats`` gives the bus's trace; the plan's figure plus the service frames (NMT,
    heartbeats, EMCY, SDO, the statusword PDO).  An identifier the database does not
    know counts with the worst case of an 8-byte classical frame."""
    from hdhil.can.schedule import CyclicFrame, worst_case_seconds

    if span_s <= 0:
        return math.nan
    by_id = {m.frame_id: m for m in database.messages if not m.is_extended_frame}
    data_bitrate = (spec.data_bitrate or None) if spec.fd else None
    busy = 0.0
    for (_channel, frame_id), n in counts.items():
        m = by_id.get(frame_id)
        fd = bool(m is not None and m.is_fd)
        frame = CyclicFrame("", frame_id, m.length if m is not None else 8, fd=fd,
                            brs=data_bitrate is not None)  # fmt: skip
        busy += n * worst_case_seconds(frame, spec.bitrate, data_bitrate)
    return busy / span_s


def worst_joint(
    rows: Sequence[RigJointResult | JointScores], filtered: bool = True
) -> dict[str, Any]:
    """The worst joint by each figure: the largest filtered RMS torque error (with the
    ripple filter scored, ``filtered``) and, with a law, the smallest share of
    ``|e| <= 0.5 Nm`` on the measured torque."""
    out: dict[str, Any] = {}
    scored = [r for r in rows if r.torque.get("samples")]
    if scored and filtered:
        w = max(scored, key=lambda r: r.torque["rms_error_filtered"])
        out["rms_error_filtered"] = {"joint": w.name, "value": w.torque["rms_error_filtered"]}
    tracked = [r for r in rows if r.tracking and r.tracking.get("samples")]
    if tracked:
        key = "share_within_goal_measured"
        w = min(tracked, key=lambda r: r.tracking[key])  # type: ignore[index]
        out[key] = {"joint": w.name, "value": w.tracking[key]}  # type: ignore[index]
    return out


def _num(value: float | None, width: int, places: int, scale: float = 1.0) -> str:
    """``value * scale`` in ``width`` columns with ``places`` decimals; ``-`` when there
    is none (no samples, or not scored)."""
    if value is None or math.isnan(value):
        return f"{'-':>{width}}"
    return f"{value * scale:{width}.{places}f}"


def format_joint_table(
    rows: Sequence[RigJointResult | JointScores],
    scored: Sequence[str],
    worst: dict[str, Any],
    since_s: float,
    *,
    state: bool = False,
) -> list[str]:
    """The per-joint table of ``hdhil run`` and ``hdhil evaluate`` of a rig: a row per
    joint (with ``state``, the drive's state and the interrupts it ran, which only a run
    knows) with its scores, then the worst joint (:func:`worst_joint`)."""
    w = max([8, *(len(j.name) for j in rows)])
    ran = f" {'state':<18} {'samples':>7}" if state else ""
    lines = [
        f"  per joint from {since_s:g} s (RMS error of the raw and the filtered torque against "
        "the true torque, with the ripple filter scored; e = T_meas − T_desired with a law)",
        f"    {'joint':<{w}} {'bus':<6} {'node':>4}{ran} "
        f"{'RMS raw/Nm':>10} {'RMS filt/Nm':>11} {'filt/raw':>8} {'law':<6} "
        f"{'RMS e/Nm':>8} {'|e|≤0.5':>8}",
    ]
    filtered = "ripple" in scored
    for j in rows:
        t, k = (j.torque if filtered else {}), j.tracking or {}
        ran = ""
        if state and isinstance(j, RigJointResult):
            ran = f" {j.drive_state:<18} {j.samples:>7}"
        lines.append(
            f"    {j.name:<{w}} {j.bus:<6} {j.node_id:>4}{ran} "
            f"{_num(t.get('rms_error_raw'), 10, 4)} {_num(t.get('rms_error_filtered'), 11, 4)} "
            f"{_num(t.get('filtered_to_raw'), 7, 1, 100)}% {k.get('law', '-'):<6} "
            f"{_num(k.get('rms_error_measured'), 8, 3)} "
            f"{_num(k.get('share_within_goal_measured'), 7, 1, 100)}%"
        )
    for key, wj in worst.items():
        what = "filtered RMS error" if key == "rms_error_filtered" else "|e|≤0.5 Nm share"
        v = wj["value"]
        value = f"{v:.4f} Nm" if key == "rms_error_filtered" else f"{v:.1%}"
        lines.append(f"  worst joint        {wj['joint']} by {what}: {value}")
    return lines


def format_candidates(
    rows: Sequence[RigJointResult | JointScores], evaluated: bool, fd: bool = False
) -> list[str]:
    """The candidate filters per joint, one line each: the firmware's filter and the best
    candidate by RMS error against the joint's true torque, each with its share of raw's
    (every candidate in ``--json``, as :func:`hdhil.rig.evaluate.evaluate` gives them).
    ``fd``: the rig has an FD bus, whose packed sensor frames the evaluation does not read
    (:func:`candidates_scored`)."""
    if not evaluated:
        return ["  evaluation         candidate filters not evaluated (--no-evaluate)"]
    if all(r.evaluation is None for r in rows):
        if fd:
            return ["  evaluation         candidate filters not evaluated: an FD bus packs the "
                    "joints' sensor frames"]  # fmt: skip
        return []  # the rig does not score the ripple filter (a control law's tracking)
    skips = {r.evaluation.get("skip_s") for r in rows if r.evaluation is not None} - {None}
    since = f" from {min(skips):g} s" if skips else ""
    lines = [f"  candidate filters  per joint{since}, each replayed on every sample (the "
             "firmware's own on its telemetry's): RMS error against the true torque (% of "
             "raw's on every sample); every candidate in --json"]  # fmt: skip
    width = max([8, *(len(r.name) for r in rows)])

    def cell(c: dict[str, Any]) -> str:
        return f"{c['name']} {c['rms_error']:.4f} Nm ({100 * c['rms_ratio']:.1f} %)"

    for r in rows:
        ev = r.evaluation or {}
        scored = [c for c in ev.get("candidates") or () if not math.isnan(c["rms_error"])]
        if not ev.get("samples") or not scored:
            lines.append(f"    {r.name:<{width}} no samples with ground truth{since}")
            continue
        firmware = next((c for c in scored if c["name"].startswith("firmware")), None)
        best = min(scored, key=lambda c: c["rms_error"])
        if firmware is None:
            text = f"best: {cell(best)}"
        elif f"{best['rms_error']:.4f}" == f"{firmware['rms_error']:.4f}":
            text = f"{cell(firmware)}, the best"
        else:
            text = f"{cell(firmware)}; best: {cell(best)}"
        lines.append(f"    {r.name:<{width}} {text}")
    return lines


def format_rig_evaluation(ev: dict[str, Any]) -> str:
    """``hdhil evaluate`` of a rig's trace (:func:`hdhil.rig.trace_score.score_rig_trace`):
    the table per joint and the worst joint, as ``hdhil run`` printed them."""
    rows = [JointScores(**j) for j in ev["joints"]]
    tracked = f"; tracking scored from {ev['skip_s']:g} s" if "tracking" in ev["scored"] else ""
    lines = [
        f"hdhil evaluate: scenario {ev['scenario']}, seed {ev['seed']}, {len(rows)} joints on "
        f"{len(ev['buses'])} bus(es){tracked}",
        "  buses              "
        + "; ".join(
            f"{name} (channel {b['channel']}): {', '.join(b['joints'])}"
            for name, b in ev["buses"].items()
        ),
        *format_joint_table(rows, ev["scored"], ev["worst_joint"], ev["skip_s"]),
        *format_candidates(
            rows, bool(ev.get("evaluated", True)), any(b.get("fd") for b in ev["buses"].values())
        ),
    ]
    return "\n".join(lines)


def format_rig_result(r: RigResult) -> str:
    """The text report: the run, a row per joint, the worst joint."""
    lines = [
        f"hdhil run: scenario {r.scenario}, seed {r.seed}, lockstep on simbus, "
        f"{len(r.joints)} joints on {len(r.buses)} bus(es)"
        + ("  [INTERRUPTED]" if r.interrupted else ""),
        f"  simulated time     {r.simulated_s:.3f} s ({r.cycles} cycles of "
        f"{r.sample_period_s * 1e3:g} ms in operation; start-up {r.startup_cycles}, "
        f"stop {r.stop_cycles} cycles)",
        f"  wall time          {r.wall_s:.3f} s ({r.us_per_cycle:.0f} us a cycle in operation)",
        f"  real-time factor   {r.real_time_factor:.1f}x",
        "  buses              "
        + "; ".join(
            f"{name} (channel {b['channel']}{', FD' if b['fd'] else ''}): "
            f"{', '.join(b['joints'])}, {r.frames.get(name, 0)} frames, worst-case load "
            f"{b['worst_case_load'] * 100:.1f} %"
            for name, b in r.buses.items()
        ),
        *format_joint_table(r.joints, r.scored, r.worst_joint, r.evaluate_from_s, state=True),
    ]
    if any(b["fd"] for b in r.buses.values()):
        lines.append(
            "  CAN FD             on an FD bus each direction's cyclic PDOs of its joints go in "
            "one FD frame (FD_DRIVE_TPDO1, FD_DRIVE_RPDO1), the telemetry as FD frames"
        )
    lines += format_candidates(r.joints, r.evaluated, any(b["fd"] for b in r.buses.values()))
    if r.trace:
        lines.append(f"  trace              {r.trace} (bus channels as listed, truth on channel 1)")
    if r.verdict is not None:
        lines.append(f"  verdict            {r.verdict['phase']}: {r.verdict['reason']}")
    return "\n".join(lines)
