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

Each bus has its own truth channel (frame groups, in-process) on which its drives send
their joint's truth at the joint's identifiers (:func:`hdhil.dbc.truth_frame_id`, the
joint's index in the layout), and its own host tap with a frame counter and, per joint,
the torque scorer (the joint's telemetry at its link's identifiers against its truth)
and, with a control law, the tracking scorer. Frames of two buses share identifiers (the
pre-defined connection set numbers each bus alike), so each bus is scored on its own.

On a CAN FD bus the joints' cyclic PDOs are packed per direction into FD frames
(:mod:`hdhil.rig.fdpack`: the bus's database has the packed layouts, a gateway node
sends them) and the telemetry goes as FD frames, with bit-rate switching when the bus
has a data bit rate.  A bus's ``telemetry_every`` decimates the telemetry
(:func:`hdhil.canopen.rigdb.telemetry_phases`).

What a rig does not take yet (one-line :class:`ConfigError`): real time, an interface
other than ``simbus``, injected faults, a drive DCF or mapping, and the evaluation of
candidate filters (the result says so).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
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
from hdhil.rig.fdpack import FdGateway, PackingBus
from hdhil.rig.layout import BusSpec, JointSpec, rigdb_layout
from hdhil.rig.loop import NodeLoop
from hdhil.rig.request import RunRequest
from hdhil.rig.score import TorqueScorer, TrackingScorer

__all__ = ["RigJointResult", "RigResult", "bus_channel", "format_rig_result", "run_rig"]

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
class RigJointResult:
    """One joint's figures: where it sits and its scores."""

    name: str
    bus: str
    node_id: int
    controller_node_id: int
    joint_index: int
    drive_state: str
    samples: int
    torque: dict[str, float]
    tracking: dict[str, Any] | None = None


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
    evaluation: str = "candidate filters are not evaluated for a rig of several joints"
    trace: str | None = None
    #: What the scenario scores (:attr:`hdhil.rig.scenario.Scenario.scored`): the torque
    #: columns are the ripple filter's only with ``ripple``.
    scored: tuple[str, ...] = ("ripple",)

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


@dataclass
class _Joint:
    spec: JointSpec
    index: int
    plant: PlantConfig
    firmware: FirmwareConfig
    drive: DriveNode | None = None
    controller: ControllerNode | None = None
    rank: int = 0
    scorer: TorqueScorer | None = None
    tracking: TrackingScorer | None = None


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
) -> RigResult:
    """Run the rig of ``request``'s scenario for its duration, lockstep on the simulated
    buses, and score every joint (module docstring). ``trace``: every bus on its channel
    (:func:`bus_channel`) and the truth, with a sidecar that records the layout
    (:func:`rig_metadata`); ``start_time`` the Unix time of simulated time 0 (default
    now, to the millisecond)."""
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
                               fd=any(spec.fd for spec in buses.values()))  # fmt: skip
    blas = threadpool_limits(limits=1)
    completed = False
    try:
        result = _run(request, joints, buses, clock, handle, opened, stop_requested, writer)
        if writer is not None:
            writer.stop()  # the trace and its sidecar renamed into place
            result.trace = str(trace)
        completed = True
        return result
    finally:
        if writer is not None and not completed:
            writer.abort()  # no trace of a run that failed
        for bus in opened:
            bus.shutdown()
        blas.restore_original_limits()


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
            )
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
        channels = frozenset((bus_channel(index), CHANNEL_NUMBER["truth"]))
        counters[name] = counter = FrameCounter()
        listeners.append(OnChannels(counter, frozenset((bus_channel(index),))))
        for j in on_bus:
            assert j.controller is not None
            link = j.controller.joints[j.rank].link
            j.scorer = TorqueScorer(telemetry_id=link.telemetry_cob_id, joint_index=j.index)
            listeners.append(OnChannels(j.scorer, channels))
            control = j.firmware.control
            if control.law != Law.NONE:
                j.tracking = TrackingScorer(
                    control.joint.Jl / control.joint.Jm,
                    request.evaluate_from_s,
                    control.friction.active,
                    Ts,
                    j.plant.link,
                    telemetry_ids=(link.telemetry_cob_id, link.control_cob_id),
                    joint_index=j.index,
                )
                listeners.append(OnChannels(j.tracking, channels))
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
        assert j.scorer is not None and j.controller is not None
        torque = j.scorer.result().as_dict()
        tracked = (
            {"law": j.firmware.control.law.name.lower(), **j.tracking.result().as_dict()}
            if j.tracking is not None
            else None
        )
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


def worst_joint(rows: list[RigJointResult], filtered: bool = True) -> dict[str, Any]:
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


def format_rig_result(r: RigResult) -> str:
    """The text report: the run, a row per joint, the worst joint."""
    w = max([8, *(len(j.name) for j in r.joints)])
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
        "  per joint (RMS error of the raw and the filtered torque against the true torque, "
        "with the ripple filter scored; e = T_meas − T_desired with a law)",
        f"    {'joint':<{w}} {'bus':<6} {'node':>4} {'state':<18} {'samples':>7} "
        f"{'RMS raw/Nm':>10} {'RMS filt/Nm':>11} {'filt/raw':>8} {'law':<6} "
        f"{'RMS e/Nm':>8} {'|e|≤0.5':>8}",
    ]
    filtered = "ripple" in r.scored
    for j in r.joints:
        t, k = (j.torque if filtered else {}), j.tracking or {}
        lines.append(
            f"    {j.name:<{w}} {j.bus:<6} {j.node_id:>4} {j.drive_state:<18} {j.samples:>7} "
            f"{_num(t.get('rms_error_raw'), 10, 4)} {_num(t.get('rms_error_filtered'), 11, 4)} "
            f"{_num(t.get('filtered_to_raw'), 7, 1, 100)}% {k.get('law', '-'):<6} "
            f"{_num(k.get('rms_error_measured'), 8, 3)} "
            f"{_num(k.get('share_within_goal_measured'), 7, 1, 100)}%"
        )
    for key, worst in r.worst_joint.items():
        what = "filtered RMS error" if key == "rms_error_filtered" else "|e|≤0.5 Nm share"
        v = worst["value"]
        value = f"{v:.4f} Nm" if key == "rms_error_filtered" else f"{v:.1%}"
        lines.append(f"  worst joint        {worst['joint']} by {what}: {value}")
    if any(b["fd"] for b in r.buses.values()):
        lines.append(
            "  CAN FD             on an FD bus each direction's cyclic PDOs of its joints go in "
            "one FD frame (FD_DRIVE_TPDO1, FD_DRIVE_RPDO1), the telemetry as FD frames"
        )
    lines.append(f"  evaluation         {r.evaluation}")
    if r.trace:
        lines.append(f"  trace              {r.trace} (bus channels as listed, truth on channel 1)")
    if r.verdict is not None:
        lines.append(f"  verdict            {r.verdict['phase']}: {r.verdict['reason']}")
    return "\n".join(lines)
