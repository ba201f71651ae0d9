"""A rig of several joints, one process per bus: the drives and controller nodes of
``hdhil emulate --scenario NAME --bus BUS`` and ``hdhil firmware --scenario NAME --bus
BUS`` on buses the command opened (any python-can interface, one channel per bus:
``udp_multicast`` groups, SocketCAN interfaces).

:class:`RigDrives` serves the drives of the buses it is given (or one joint's drive),
each :class:`~hdhil.hostsim.drive.DriveNode` at its node-ID on a bus handle of its own,
served in turn in one process (:meth:`RigDrives.serve`). Each drive's plant is its
own :class:`~hdhil.hostsim.plant.Plant`, or, for a scenario with a ``[robot]``, its
joint of the one :class:`~hdhil.hostsim.plant.arm.ArmPlant` this process owns. The arm couples every
joint, so it cannot be split between processes: its clock is the first drive served
(:class:`CoupledJoint`): each SYNC that drive receives advances the whole arm by the
period (by the missed periods too) with every joint's held amplifier input, and the
other drives sample the arm as it is at their own SYNC. Serving every bus of the arm in
one process (one bus handle per drive, one channel per bus name) keeps every joint
coupled; a joint whose bus this process does not serve stays in the arm with its
amplifier off (0 V), and :attr:`RigDrives.passive` names it.

:class:`RigController` runs the controller nodes of one bus (the bus's SYNC producer
and a further node at a joint's own ``controller_node_id``), one bus handle each, in
one node loop paced at the sample period (or in network lockstep): a cycle waits until
every joint of the bus answered its SYNC. A listening handle on the same bus scores each
joint from the controller's own telemetry (:class:`JointTelemetry`: ``e = T_meas −
tau_sD`` with a law, no ground truth between processes).

Not taken (one-line :class:`ConfigError`): injected faults, a drive DCF or mapping, a
truth bus.
"""

from __future__ import annotations

import math
import select
import time
from collections.abc import Callable, Sequence
from typing import Any

import can

from hdhil.can.traces.tap import BusTap
from hdhil.canopen.nmt import state_name as nmt_state_name
from hdhil.core.dataconf import ConfigError
from hdhil.dbc import codec
from hdhil.firmware.config import Law
from hdhil.firmware.controller import ControllerNode, JointSetup
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant
from hdhil.hostsim.plant.arm import ArmJoint, ArmPlant
from hdhil.rig.layout import JointSpec
from hdhil.rig.loop import IDLE_SLEEP_S, RECV_SLICE_S, NodeLoop
from hdhil.rig.realtime import RealtimeConfig, RealtimeLoop
from hdhil.rig.request import RunRequest
from hdhil.rig.session import end_session, start_session
from hdhil.rig.verdict import drive_verdict

__all__ = [
    "CoupledJoint",
    "JointTelemetry",
    "RigController",
    "RigDrives",
    "served_joints",
]

#: SYNC cycles allowed for walking the drives back to "stopped" after the run.
MAX_STOP_CYCLES = 2000
#: The goal band of the torque error with a law (Nm), as ``hdhil run`` scores it.
GOAL_NM = 0.5

OpenBus = Callable[[str], can.BusABC]


def check_rig_process(request: RunRequest, command: str) -> None:
    """What a rig's process does not take yet: one-line :class:`ConfigError`."""
    s = request.scenario
    if request.mapping.dcf is not None:
        raise ConfigError(
            f"hdhil {command} --bus: a rig of several joints runs the raw mapping only"
        )
    if s.faults is not None:
        raise ConfigError(f"hdhil {command} --bus: a rig of several joints runs without [faults]")


def served_joints(
    request: RunRequest, buses: Sequence[str], joint: str | None = None
) -> list[JointSpec]:
    """The joints of ``buses`` (or the one named ``joint``), in layout order; an unknown
    bus or joint is a one-line :class:`ConfigError` naming the known ones."""
    s = request.scenario
    known_buses = [name for name, _ in s.buses]
    for name in buses:
        if name not in known_buses:
            raise ConfigError(f"scenario {s.name} has no bus {name!r}: its buses are "
                              f"{', '.join(known_buses)}")  # fmt: skip
    if joint is not None:
        named = [j for j in s.joints if j.name == joint]
        if not named:
            raise ConfigError(f"scenario {s.name} has no joint {joint!r}: its joints are "
                              f"{', '.join(j.name for j in s.joints)}")  # fmt: skip
        if buses and named[0].bus not in buses:
            raise ConfigError(f"joint {joint} is on bus {named[0].bus}, not on "
                              f"{', '.join(buses)}")  # fmt: skip
        return named
    served = [j for j in s.joints if j.bus in buses]
    if not served:
        raise ConfigError(f"scenario {s.name}: no joint on bus(es) {', '.join(buses)}")
    return served


class CoupledJoint(ArmJoint):
    """One joint of an :class:`ArmPlant` shared by drives on buses whose SYNCs are not
    in step (module docstring). The ``clock`` joint's :meth:`advance` moves the whole arm
    by ``dt`` with :attr:`ArmPlant.input_source`'s inputs; the others' only sample it."""

    def __init__(self, arm: ArmPlant, k: int, clock: bool) -> None:
        super().__init__(arm, k)
        self.clock = clock

    @property
    def time(self) -> float:
        return self.arm.time

    def advance(self, volts: float, dt: float) -> None:
        if self.clock:
            source = self.arm.input_source
            assert source is not None
            self.arm.advance(source(), dt)


class RigDrives:
    """The drives of ``joints`` (:func:`served_joints`), each on a bus handle that
    ``open_bus(bus_name)`` opens, served in turn by :meth:`serve` (module docstring)."""

    def __init__(self, request: RunRequest, joints: Sequence[JointSpec], open_bus: OpenBus) -> None:
        check_rig_process(request, "emulate")
        s = request.scenario
        Ts = request.sample_period_s
        self.request = request
        index = {j.name: k for k, j in enumerate(s.joints)}
        self.joints = list(joints)
        served = {j.name for j in joints}
        #: The arm's joints this process holds with their amplifiers off (not served).
        self.passive: list[str] = []
        self.arm: ArmPlant | None = None
        plants: dict[str, Any] = {}
        configs = dict(zip((j.name for j in s.joints), s.joint_configs, strict=True))
        if s.robot is not None:
            from hdhil.hostsim.plant.multibody import LinkDynamics

            try:
                arm = ArmPlant(
                    LinkDynamics.from_urdf(s.robot.path),
                    [plant for plant, _ in s.joint_configs],
                    [request.seed + k for k in range(len(s.joints))],
                )
                arm.prepare(Ts)
            except ValueError as exc:
                raise ConfigError(f"scenario {s.name}: {exc}") from None
            self.arm = arm
            clock = joints[0].name
            for j in joints:
                plants[j.name] = CoupledJoint(arm, index[j.name], clock=j.name == clock)
            self.passive = [j.name for j in s.joints if j.name not in served]
        else:
            for j in joints:
                plants[j.name] = Plant(configs[j.name][0], request.seed + index[j.name])
        self.drives: list[DriveNode] = []
        self.buses: list[can.BusABC] = []
        for j in joints:
            cfg = DriveConfig(
                sample_period_s=Ts,
                actuation=request.actuation,  # type: ignore[arg-type]
                node_id=j.node_id,
                controller_node_id=j.controller_node_id,
                truth_joint_index=index[j.name],
            )
            bus = open_bus(j.bus)
            self.buses.append(bus)
            self.drives.append(DriveNode(bus, plants[j.name], cfg))
        if self.arm is not None:
            by_joint = {j.name: d for j, d in zip(joints, self.drives, strict=True)}
            held = [by_joint.get(j.name) for j in s.joints]
            self.arm.input_source = lambda: [0.0 if d is None else d.io.step_V for d in held]

    def serve(self, stop: Callable[[], bool], duration_s: float | None = None) -> None:
        """Boot every drive and serve them until ``stop()`` or ``duration_s`` wall seconds.

        The drives take one frame each in turn, so a backlog (the process was held off
        the CPU; the clock drive steps the arm for each SYNC) is worked off by all of
        them together, not one drive's after another's; their timers run every
        :data:`~hdhil.rig.loop.RECV_SLICE_S`. With nothing waiting the process sleeps
        on the handles' sockets where they have them (``select``), else briefly."""
        drives = self.drives
        t_end = time.monotonic() + duration_s if duration_s else math.inf
        fds = _filenos(self.buses)
        now = time.monotonic()
        for drive in drives:
            drive.boot(now)
        next_tick = now
        while not stop():
            now = time.monotonic()
            if now >= t_end:
                break
            if now >= next_tick:
                for drive in drives:
                    drive.tick(now)
                next_tick = now + RECV_SLICE_S
            handled = False
            for drive in drives:
                msg = drive.bus.recv(0)
                if msg is not None:
                    drive.on_message(msg)
                    handled = True
            if not handled:
                if fds:
                    select.select(fds, [], [], max(0.0, min(next_tick, t_end) - now))
                else:
                    time.sleep(IDLE_SLEEP_S)

    def summary(self) -> dict[str, Any]:
        """The JSON summary: per joint its drive's counters and states, the arm's
        passive joints, and the ``verdict`` of the first drive that went to a fault."""
        out: dict[str, Any] = {"node": "drives", "scenario": self.request.name,
                               "buses": sorted({j.bus for j in self.joints}),
                               "joints": {}}  # fmt: skip
        verdict = None
        for j, drive in zip(self.joints, self.drives, strict=True):
            d = drive.diagnostics
            out["joints"][j.name] = {
                "bus": j.bus, "node_id": j.node_id, "syncs": d.syncs, "commands": d.commands,
                "missed_syncs": d.missed_syncs, "nmt_state": nmt_state_name(drive.nmt_state),
                "drive_state": getattr(drive.drive_state, "name", str(drive.drive_state)),
            }  # fmt: skip
            v = drive_verdict(drive)
            if v is not None and verdict is None:
                verdict = {**v, "joint": j.name}
        if self.arm is not None:
            out["arm"] = {"plant_time_s": self.arm.time, "clock": self.joints[0].name,
                          "passive": self.passive}  # fmt: skip
        if verdict is not None:
            out["verdict"] = verdict
        return out


def _filenos(buses: Sequence[can.BusABC]) -> list[int]:
    """The buses' file descriptors when every bus has one (``udp_multicast``, SocketCAN),
    else none."""
    fds = []
    for bus in buses:
        try:
            fd = bus.fileno()
        except (AttributeError, NotImplementedError, OSError):
            return []
        if not isinstance(fd, int) or fd < 0:
            return []
        fds.append(fd)
    return fds


class JointTelemetry(can.Listener):
    """One joint's torque error from its controller's telemetry on the bus: ``CTRL_TPDO1``
    (``T_meas``) then ``CTRL_TPDO2`` (``tau_sD``) of the same sample, ``e = T_meas −
    tau_sD``; the samples of the first ``skip_s`` seconds (wall time since the first
    telemetry frame) are not counted."""

    def __init__(self, telemetry_id: int, control_id: int, skip_s: float) -> None:
        self._meas = (
            codec("control", "CTRL_TPDO1")
            .expect("T_meas", "T_filtered", "velocity", "current")
            .at(telemetry_id)
        )
        self._tele = (
            codec("control", "CTRL_TPDO2")
            .expect("dtau_s_hat", "tau_lgd_hat", "tau_sD", "e_hat")
            .at(control_id)
        )
        self.skip_s = skip_s
        self._t0: float | None = None
        self._t_meas: float | None = None
        self.frames = 0
        self.samples = 0
        self._sum_sq = 0.0
        self._within = 0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.is_remote_frame:
            return
        if msg.arbitration_id == self._meas.frame_id:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = now
            self.frames += 1
            counted = now - self._t0 >= self.skip_s
            self._t_meas = self._meas.decode(msg.data)[0] if counted else None
        elif msg.arbitration_id == self._tele.frame_id and self._t_meas is not None:
            e = self._t_meas - self._tele.decode(msg.data)[2]
            self._t_meas = None
            self.samples += 1
            self._sum_sq += e * e
            self._within += abs(e) <= GOAL_NM

    def result(self) -> dict[str, Any]:
        n = self.samples
        return {
            "telemetry_frames": self.frames,
            "samples": n,
            "rms_error_measured": math.sqrt(self._sum_sq / n) if n else None,
            "share_within_goal_measured": self._within / n if n else None,
        }


class RigController:
    """The controller nodes of bus ``bus`` of the request's rig (module docstring), each
    on a handle ``open_bus(bus)`` opens; booted with the drives by :meth:`boot`, run for
    the request's cycles by :meth:`run`, summed up per joint by :meth:`summary`."""

    def __init__(
        self,
        request: RunRequest,
        bus: str,
        open_bus: OpenBus,
        boot_timeout_s: float,
        realtime: RealtimeConfig | None = None,
    ) -> None:
        check_rig_process(request, "firmware")
        s = request.scenario
        self.request = request
        self.bus_name = bus
        spec = dict(s.buses)[bus]
        configs = dict(zip((j.name for j in s.joints), s.joint_configs, strict=True))
        on_bus = served_joints(request, [bus])
        ids = sorted({j.controller_node_id for j in on_bus},
                     key=lambda cid: (cid != spec.controller_node_id, cid))  # fmt: skip
        if ids[0] != spec.controller_node_id:
            raise ConfigError(
                f"bus {bus}: no joint is served by its controller node {spec.controller_node_id}"
                " (the node that produces the bus's SYNC)"
            )
        self.nodes: list[ControllerNode] = []
        self.handles: list[can.BusABC] = []
        #: Per joint, in layout order: (spec, node, rank).
        self.joints: list[tuple[JointSpec, ControllerNode, int]] = []
        for cid in ids:
            served = [j for j in on_bus if j.controller_node_id == cid]
            setups = [JointSetup(configs[j.name][1], j.node_id, j.name) for j in served]
            handle = open_bus(bus)
            self.handles.append(handle)
            try:
                node = ControllerNode(handle, node_id=cid, joints=setups,
                                      sync_producer=cid == spec.controller_node_id,
                                      boot_timeout_s=boot_timeout_s)  # fmt: skip
            except ValueError as exc:
                raise ConfigError(f"bus {bus}: {exc}") from None
            self.nodes.append(node)
            for rank, j in enumerate(served):
                self.joints.append((j, node, rank))
        order = {j.name: k for k, j in enumerate(on_bus)}
        self.joints.sort(key=lambda t: order[t[0].name])
        self.telemetry: dict[str, JointTelemetry] = {}
        for j, node, rank in self.joints:
            link = node.joints[rank].link
            if configs[j.name][1].control.law != Law.NONE:
                self.telemetry[j.name] = JointTelemetry(
                    link.telemetry_cob_id, link.control_cob_id, request.evaluate_from_s
                )
        self.tap: BusTap | None = None
        if self.telemetry:
            self.handles.append(tap_bus := open_bus(bus))
            self.tap = BusTap({0: tap_bus}, list(self.telemetry.values()))
        self.realtime = realtime
        self.pacer: RealtimeLoop | None = None
        self.operational_cycles = 0
        self.startup_s: float | None = None
        self.timeouts = 0
        #: The start-up check's lines (a drive found in FAULT was reset).
        self.recovery: list[str] = []
        #: Per joint, whether the session ended clean (the drive's 0x1016 entry cleared).
        self.ended_clean: dict[str, bool] = {}

    def _isrs(self) -> list[Any]:
        return [node.joints[rank].isr for _, node, rank in self.joints]

    def _diagnostics(self) -> list[Any]:
        return [node.joints[rank].diagnostics for _, node, rank in self.joints]

    def boot(self, stop: Callable[[], bool]) -> dict[str, Any] | None:
        """Boot every node and wait for its drives' boot-ups (or the timeout); the JSON
        summary with a start-up verdict when a node gave up, else None. A drive found in
        FAULT from an earlier session is reset first (:attr:`recovery` says so)."""
        for j, node, _ in self.joints:
            line = start_session(node.bus, j.node_id, node.node_id)
            if line is not None:
                self.recovery.append(f"joint {j.name}: {line}")
        loop = NodeLoop(self.nodes, node_time=time.monotonic)
        loop.boot()
        nodes = self.nodes
        loop.run(stop, lambda: all(n.phase != "wait-boot" or n.boot_error for n in nodes))
        failed = [n for n in nodes if n.boot_error]
        if failed and not stop():
            verdict = {"phase": "start-up", "node": failed[0].node_id,
                       "reason": str(failed[0].boot_error), "startup_cycles": 0,
                       "cycles_planned": self.request.cycles}  # fmt: skip
            return {**self.summary(stopped=True), "verdict": verdict}
        return None

    def run(self, stop: Callable[[], bool], realtime: bool = True) -> int:
        """SYNC cycles until every joint's interrupt ran the request's cycles, a node left
        operation, or ``stop()``; then walk the drives back to "stopped". ``realtime``: at
        the sample period (statistics from operation on, the machine floor after the run
        with ``RealtimeConfig.floor_s``), else in network lockstep. Returns the cycles in
        operation."""
        Ts = self.request.sample_period_s
        producer = self.nodes[0]
        diagnostics = self._diagnostics()
        nodes = self.nodes
        pacer = self.pacer = RealtimeLoop(Ts, self.realtime) if realtime else None

        def expects_answer() -> bool:
            return all(d.sensor_frames > 0 for d in diagnostics) and all(
                n.phase in ("starting", "operational", "stopping") for n in nodes
            )

        loop = NodeLoop(
            nodes,
            producer=producer,
            answers=lambda: min(d.commands_sent for d in diagnostics),
            expects_answer=expects_answer,
            listeners=[self.tap] if self.tap is not None else [],
            listen_every=1,
            period_s=Ts,
            pacer=pacer,
        )
        isrs = self._isrs()
        cycles = self.request.cycles
        t0 = time.monotonic()
        if pacer is not None:
            pacer.instrument(producer)
            pacer.enter()
            pacer.start()
        try:
            joints = [node.joints[rank] for _, node, rank in self.joints]
            while min(isr.samplecount for isr in isrs) < cycles and not stop():
                if any(j.phase == "safe" for j in joints):
                    break  # a joint gone safe ends the bus's run (its verdict)
                loop.cycle()
                if all(n.phase == "operational" for n in nodes):
                    if self.startup_s is None:
                        self.startup_s = time.monotonic() - t0
                    if pacer is not None and not pacer.recording:
                        pacer.begin_recording()
                    self.operational_cycles += 1
            if pacer is not None:
                pacer.end_recording()
            for node in nodes:
                node.request_stop()
            for _ in range(MAX_STOP_CYCLES):
                if all(n.phase in ("stopped", "safe") for n in nodes):
                    break
                loop.cycle()
            if pacer is not None:
                pacer.measure_floor()
        finally:
            if pacer is not None:
                pacer.exit()
        self.timeouts = loop.timeouts
        for j, node, _ in self.joints:  # the drives stay up without their master
            self.ended_clean[j.name] = end_session(
                node.bus, j.node_id, node.node_id, node.services.produce_heartbeat
            )
        return self.operational_cycles

    def summary(self, stopped: bool) -> dict[str, Any]:
        """The JSON summary: per joint its samples, phase, drive state and torque error
        (:class:`JointTelemetry`), the real-time statistics, and a ``verdict`` when a
        joint did not run its cycles (none after a stop by the user)."""
        if self.tap is not None:
            self.tap.poll()
        joints: dict[str, Any] = {}
        for j, node, rank in self.joints:
            cj = node.joints[rank]
            state = cj.drive_state
            row: dict[str, Any] = {
                "node_id": j.node_id, "controller_node_id": node.node_id,
                "samples": cj.isr.samplecount, "phase": str(cj.phase.value),
                "drive_state": getattr(state, "name", str(state)),
                "sensor_frames": cj.diagnostics.sensor_frames,
            }  # fmt: skip
            if j.name in self.telemetry:
                row["tracking"] = self.telemetry[j.name].result()
            if cj.diagnostics.safe_reason:
                row["safe_reason"] = cj.diagnostics.safe_reason
            if j.name in self.ended_clean:
                row["ended_clean"] = self.ended_clean[j.name]
            joints[j.name] = row
        out: dict[str, Any] = {
            "node": "controller", "scenario": self.request.name, "bus": self.bus_name,
            "operational_cycles": self.operational_cycles,
            "syncs_sent": self.nodes[0].diagnostics.syncs_sent,
            "cycle_timeouts": self.timeouts, "startup_s": self.startup_s,
            "joints": joints,
        }  # fmt: skip
        if self.recovery:
            out["recovery"] = self.recovery
        if self.pacer is not None:
            out["realtime"] = self.pacer.result()
        short = [name for name, r in joints.items() if r["samples"] < self.request.cycles]
        short.sort(key=lambda name: "safe_reason" not in joints[name])  # the cause first
        if short and not stopped:
            row = joints[short[0]]
            out["verdict"] = {
                "phase": row["phase"], "node": row["controller_node_id"],
                "time_s": row["samples"] * self.request.sample_period_s,
                "reason": f"joint {short[0]} ran {row['samples']} of {self.request.cycles} "
                f"cycles" + (f": {row['safe_reason']}" if "safe_reason" in row else ""),
            }  # fmt: skip
        return out
