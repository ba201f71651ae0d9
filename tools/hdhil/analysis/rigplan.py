"""The plan of a rig: its CAN databases, each bus's worst-case load, and the CPU it needs.

A scenario's layout (:mod:`hdhil.rig.layout`: buses, joints, node-IDs) is turned into
the drives and buses of :mod:`hdhil.canopen.rigdb`, whose databases name and number
every frame of every bus from the object dictionaries: what ``hdhil dbc export
--scenario`` writes. The cyclic messages of each bus's database (those with a cycle
time; the ground truth exists only in simulation and is left out) are that bus's
schedule (:mod:`hdhil.can.schedule`): the SYNC, each drive's sensor PDO and command,
and the controller's telemetry of each joint, decimated when the bus says so
(``telemetry_every``), on a CAN FD bus the drives' PDOs packed per direction into FD
frames as the database has them. Each bus is
planned against the 60 % limit with suggestions computed from its numbers when it is
over.

The CPU a cycle needs comes from the speed cost model (:func:`hdhil.analysis.speed.
bench_cost_model`, measured on this machine when asked): fixed + joints x per joint +
frames x per frame, for the whole rig in one process and for one process per bus, as a
share of the SYNC period. A single-joint scenario plans as the rig it runs: one bus,
the drive at node-ID 2, today's frame names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hdhil.can.schedule import BusPlan, BusSchedule, CyclicFrame, FrameRole, plan_bus
from hdhil.canopen.rigdb import (
    RigBus,
    RigDrive,
    is_telemetry,
    rig_databases,
    telemetry_phases,
    truth_database,
)
from hdhil.rig.layout import DEFAULT_BUS, BusSpec, rigdb_layout
from hdhil.rig.scenario import Scenario

#: Ground-truth frames a joint sends each cycle on the simulated truth channel.
TRUTH_FRAMES_PER_JOINT = 3


def rig_layout(
    scenario: Scenario, mapping: str = "raw", dcf: Path | None = None
) -> tuple[list[RigDrive], list[RigBus]]:
    """The drives and buses of ``scenario`` as :mod:`hdhil.canopen.rigdb` takes them, each
    drive with the shipped ``mapping`` or the drive's ``dcf``."""
    if dcf is not None:
        mapping = "raw"
    if not scenario.is_rig:
        bus = RigBus(DEFAULT_BUS, 1, scenario.bus.bitrate)
        return [RigDrive("", 2, DEFAULT_BUS, mapping, dcf)], [bus]
    return rigdb_layout(scenario.joints, scenario.buses, mapping, dcf)


def scenario_databases(
    scenario: Scenario, mapping: str = "raw", dcf: Path | None = None
) -> dict[str, Any]:
    """One cantools database per bus of ``scenario``'s rig (:func:`rig_databases`)."""
    drives, buses = rig_layout(scenario, mapping, dcf)
    return rig_databases(drives, buses)


def _bus_specs(scenario: Scenario) -> dict[str, BusSpec]:
    if scenario.is_rig:
        return dict(scenario.buses)
    return {DEFAULT_BUS: BusSpec(bitrate=scenario.bus.bitrate)}


def _role(name: str) -> FrameRole:
    if name == "SYNC":
        return "sync"
    if is_telemetry(name):
        return "telemetry"
    if "DRIVE_TPDO" in name:
        return "tpdo"
    if "DRIVE_RPDO" in name:
        return "rpdo"
    return "other"


def _joint_of(message: str, joints: tuple[str, ...]) -> str | None:
    """The joint a message belongs to: rigdb prefixes it with the joint's name (``.`` and
    ``-`` written ``_``); a single joint's frames carry no prefix."""
    if message == "SYNC":
        return None
    if joints == ("",):
        return "joint"
    for joint in joints:
        if message.startswith(joint.replace(".", "_").replace("-", "_") + "_"):
            return joint
    return None


def bus_schedule(
    name: str,
    database: Any,
    spec: BusSpec,
    sample_period_s: float,
    truth: set[str],
    joints: tuple[str, ...] = ("",),
) -> BusSchedule:
    """The cyclic schedule of one bus from its database: every message with a cycle time
    (``GenMsgCycleTime`` in base cycles of one SYNC period) but the ground truth, the
    telemetry every ``spec.telemetry_every`` cycles spread over them
    (:func:`hdhil.canopen.rigdb.telemetry_phases`, the cycles the controller nodes send
    them in).  On an FD bus the database has the drives' PDOs packed into FD frames
    (:func:`hdhil.canopen.rigdb.rig_packing`) and the telemetry as FD frames; each
    message its database's format, with bit-rate switching when the bus has a data bit
    rate."""
    frames = []
    every = spec.telemetry_every
    phases = telemetry_phases(database, every)
    for msg in database.messages:
        if not msg.cycle_time or msg.name in truth:
            continue
        role = _role(msg.name)
        period, offset = int(msg.cycle_time), 0
        if role == "telemetry" and every > 1:
            period *= every
            offset = phases[msg.frame_id]
        joint = _joint_of(msg.name, joints)
        frames.append(
            CyclicFrame(
                msg.name,
                msg.frame_id,
                msg.length,
                period_cycles=period,
                offset_cycles=offset,
                fd=bool(msg.is_fd),
                brs=bool(spec.data_bitrate),
                extended=msg.is_extended_frame,
                role=role,
                joint=joint,
            )
        )
    data_bitrate = spec.data_bitrate or (spec.bitrate if spec.fd else None)
    return BusSchedule(
        name, tuple(frames), spec.bitrate, data_bitrate if spec.fd else None, sample_period_s
    )


@dataclass(frozen=True)
class CpuPrediction:
    """CPU per cycle from the cost model: the whole rig in one process, and per bus."""

    model: dict[str, Any]
    period_us: float
    one_process_us: float
    joints: int
    frames: float
    per_bus_us: dict[str, float]

    @property
    def one_process_share(self) -> float:
        return self.one_process_us / self.period_us


@dataclass(frozen=True)
class RigPlan:
    """Every bus's plan, the joints on each, and the CPU prediction (None: not asked)."""

    scenario: str
    buses: tuple[BusPlan, ...]
    joints: dict[str, tuple[str, ...]]
    cpu: CpuPrediction | None

    @property
    def fits(self) -> bool:
        return all(p.fits for p in self.buses)

    def refusal(self) -> str | None:
        """One line for the first bus over the limit (None: every bus fits)."""
        for p in self.buses:
            if not p.fits:
                hint = f"; {p.suggestions[0]}" if p.suggestions else ""
                return (
                    f"scenario {self.scenario}: bus {p.schedule.name} needs "
                    f"{p.load * 100:.1f} % of its time in the worst case (limit "
                    f"{p.limit * 100:g} %){hint}"
                )
        return None


def predict_cpu(
    model: dict[str, Any], plans: tuple[BusPlan, ...], joints: dict[str, tuple[str, ...]],
    period_s: float,
) -> CpuPrediction:  # fmt: skip
    """The cost model's CPU per cycle for the rig's joints and frames (truth included)."""
    from hdhil.analysis.speed import predict_cycle_us

    per_bus = {}
    total_frames = 0.0
    for p in plans:
        name = p.schedule.name
        frames = sum(1.0 / f.period_cycles for f in p.schedule.frames)
        frames += TRUTH_FRAMES_PER_JOINT * len(joints[name])
        total_frames += frames
        per_bus[name] = predict_cycle_us(model, len(joints[name]), frames)
    n = sum(len(j) for j in joints.values())
    return CpuPrediction(
        model, period_s * 1e6, predict_cycle_us(model, n, total_frames), n, total_frames,
        per_bus,
    )  # fmt: skip


def plan_scenario(
    scenario: Scenario,
    mapping: str = "raw",
    cost_model: dict[str, Any] | None = None,
    dcf: Path | None = None,
) -> RigPlan:
    """Plan ``scenario``'s rig: each bus's schedule and verdict; with ``cost_model`` the
    CPU a cycle needs."""
    databases = scenario_databases(scenario, mapping, dcf)
    drives, buses = rig_layout(scenario, mapping, dcf)
    truth = {m.name for m in truth_database(drives, buses).messages}
    specs = _bus_specs(scenario)
    period = scenario.firmware.sample_period_s
    on_bus = {name: tuple(d.joint for d in drives if d.bus == name) for name in databases}
    plans = tuple(
        plan_bus(bus_schedule(name, db, specs[name], period, truth, on_bus[name]))
        for name, db in databases.items()
    )
    joints = {name: tuple(j or "joint" for j in on_bus[name]) for name in databases}
    cpu = predict_cpu(cost_model, plans, joints, period) if cost_model is not None else None
    return RigPlan(scenario.name, plans, joints, cpu)
