"""Bus schedule planner: the worst-case load of one bus's SYNC-locked cyclic schedule.

A :class:`BusSchedule` is one bus: its bit rate (and data bit rate when it carries CAN FD
frames), its SYNC period and its cyclic frames, each with its identifier, payload
length, period in SYNC cycles and the cycle it starts in.  :func:`plan_bus` gives its
worst-case figures (docs/schedule.md):

- ``load``: the share of the bus time the frames take, each at its worst-case time
  (worst-case stuffing, FD phases at their bit rates), averaged over the schedule's
  hyperperiod: sum of worst-case time / period;
- ``busiest_cycle_s``: the worst-case time from the start of SYNC to the end of the last
  frame of the busiest cycle, the frames sent back to back (bus time only: the nodes'
  own latencies come on top);
- a verdict against a limit (60 % by default): the load at most the limit and the
  busiest cycle inside the SYNC period.

Worst-case frame times are bounds over every payload and CRC for the frame's known
identifier and length (:func:`hdhil.can.bittiming.worst_case_frame_bits_for`,
:func:`hdhil.can.bittiming.worst_case_fd_frame_bits`), never above the identifier-free
bounds of docs/design.md's frame budget.

:func:`cia402_schedule` builds the schedule of N CiA 402 joints (SYNC, per joint an RPDO
and a TPDO with COB-IDs from the node-ID after CiA 301's predefined connection set,
optional telemetry, optional decimation; optionally FD-packed).  When a schedule does
not fit, :func:`suggestions` computes what would: joints per bus, FD packing, decimated
telemetry.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

from hdhil.can.bittiming import (
    fd_length,
    worst_case_fd_frame_bits,
    worst_case_frame_bits_for,
)
from hdhil.can.busload import LOAD_LIMIT
from hdhil.dbc import SYNC_COB_ID, predefined_cob_id

#: What a frame is in the schedule; the suggestions move, pack and decimate by it.
FrameRole = Literal["sync", "rpdo", "tpdo", "telemetry", "other"]

#: Data bit rate assumed for FD packing on a bus that has none (the 1/5 Mbit/s pairing).
DEFAULT_DATA_BITRATE = 5_000_000
#: Hyperperiods longer than this are not walked cycle by cycle: the busiest cycle is
#: then bounded by every frame in one cycle.
_MAX_HYPERPERIOD = 10_000
#: Decimation factors tried for telemetry by :func:`suggestions`.
_DECIMATIONS = (2, 4, 5, 10, 20, 50, 100)


def pdo_cob_id(kind: Literal["rpdo", "tpdo"], number: int, node_id: int) -> int:
    """COB-ID of RPDO/TPDO ``number`` (1-4) of ``node_id`` in CiA 301's predefined
    connection set: TPDOn = 0x180 + 0x100 (n - 1) + node-ID, RPDOn = 0x200 + ..."""
    if not 1 <= number <= 4:
        raise ValueError(f"the predefined connection set has PDOs 1 to 4, not {number}")
    if not 1 <= node_id <= 127:
        raise ValueError(f"a CANopen node-ID is 1 to 127, not {node_id}")
    return predefined_cob_id(kind, number, node_id)


@dataclass(frozen=True)
class CyclicFrame:
    """One cyclic frame: sent in the cycles c with c % period_cycles == offset_cycles
    (cycle 0 starts with the first SYNC).  ``fd``: a CAN FD frame (``length`` up to 64
    bytes, padded to the next FD length), ``brs``: its data phase at the data bit rate.
    ``joint`` names the joint it belongs to (None: the bus's own, such as SYNC)."""

    name: str
    can_id: int
    length: int
    period_cycles: int = 1
    offset_cycles: int = 0
    fd: bool = False
    brs: bool = True
    extended: bool = False
    role: FrameRole = "other"
    joint: str | None = None

    def __post_init__(self) -> None:
        limit = 1 << (29 if self.extended else 11)
        if not 0 <= self.can_id < limit:
            raise ValueError(f"{self.name}: identifier {self.can_id:#x} out of range")
        top = 64 if self.fd else 8
        if not 0 <= self.length <= top:
            kind = "an FD" if self.fd else "a classical"
            raise ValueError(
                f"{self.name}: {kind} frame carries 0 to {top} bytes, not {self.length}"
            )
        if self.period_cycles < 1:
            raise ValueError(f"{self.name}: period must be >= 1 cycle, got {self.period_cycles}")
        if not 0 <= self.offset_cycles < self.period_cycles:
            raise ValueError(
                f"{self.name}: offset must be 0 to {self.period_cycles - 1} cycles, "
                f"got {self.offset_cycles}"
            )

    @classmethod
    def every_ms(
        cls, name: str, can_id: int, length: int, period_ms: float, sync_period_s: float, **fields
    ) -> CyclicFrame:
        """A frame whose period is given in ms: a whole number of SYNC periods."""
        cycles = period_ms * 1e-3 / sync_period_s
        whole = round(cycles)
        if whole < 1 or abs(cycles - whole) > 1e-9 * max(1.0, cycles):
            raise ValueError(
                f"{name}: a period of {period_ms:g} ms is not a whole number of "
                f"{sync_period_s * 1e3:g} ms SYNC periods"
            )
        return cls(name, can_id, length, period_cycles=whole, **fields)

    @property
    def payload(self) -> int:
        """Bytes on the wire: FD lengths padded to the next FD length."""
        return fd_length(self.length) if self.fd else self.length


@dataclass(frozen=True)
class BusSchedule:
    """One bus: ``bitrate`` (nominal), ``data_bitrate`` (None: a classical bus; FD frames
    need one), SYNC period and cyclic frames (the SYNC among them)."""

    name: str
    frames: tuple[CyclicFrame, ...]
    bitrate: int = 1_000_000
    data_bitrate: int | None = None
    sync_period_s: float = 1e-3

    def __post_init__(self) -> None:
        if self.bitrate <= 0:
            raise ValueError(f"bus {self.name}: bit rate must be > 0, got {self.bitrate}")
        if self.data_bitrate is not None and self.data_bitrate < self.bitrate:
            raise ValueError(
                f"bus {self.name}: data bit rate {self.data_bitrate} below the "
                f"nominal {self.bitrate}"
            )
        if not self.sync_period_s > 0:
            raise ValueError(f"bus {self.name}: SYNC period must be > 0, got {self.sync_period_s}")
        seen: dict[tuple[int, bool], str] = {}
        for frame in self.frames:
            if frame.fd and self.data_bitrate is None:
                raise ValueError(
                    f"bus {self.name}: {frame.name} is a CAN FD frame on a classical bus "
                    "(no data bit rate)"
                )
            key = (frame.can_id, frame.extended)
            if key in seen:
                raise ValueError(
                    f"bus {self.name}: {frame.name} and {seen[key]} share identifier "
                    f"{frame.can_id:#x}"
                )
            seen[key] = frame.name

    @property
    def fd(self) -> bool:
        return self.data_bitrate is not None

    @property
    def joints(self) -> tuple[str, ...]:
        """The joints with frames on this bus, in order of appearance."""
        return tuple(dict.fromkeys(f.joint for f in self.frames if f.joint is not None))


def worst_case_seconds(frame: CyclicFrame, bitrate: float, data_bitrate: float | None) -> float:
    """The longest time ``frame`` can take on the wire, interframe space included."""
    if frame.fd:
        bits = worst_case_fd_frame_bits(
            frame.length, frame.extended, brs=frame.brs, arbitration_id=frame.can_id
        )
        return bits.seconds(bitrate, data_bitrate or bitrate)
    return worst_case_frame_bits_for(frame.can_id, frame.extended, frame.length) / bitrate


@dataclass(frozen=True)
class FrameTiming:
    frame: CyclicFrame
    worst_case_s: float


@dataclass(frozen=True)
class BusPlan:
    """The worst-case figures of one bus (see the module's docstring)."""

    schedule: BusSchedule
    frames: tuple[FrameTiming, ...]
    load: float
    busiest_cycle_s: float
    limit: float
    notes: tuple[str, ...]
    suggestions: tuple[str, ...]

    @property
    def busiest_cycle_load(self) -> float:
        return self.busiest_cycle_s / self.schedule.sync_period_s

    @property
    def fits(self) -> bool:
        return self.load <= self.limit and self.busiest_cycle_s <= self.schedule.sync_period_s

    def verdict(self) -> str:
        """One line: the bus, its load against the limit and its busiest cycle."""
        s = self.schedule
        rate = _rate_text(s.bitrate, s.data_bitrate)
        head = (
            f"bus {s.name} ({rate}, SYNC {s.sync_period_s * 1e3:g} ms): worst-case load "
            f"{self.load * 100:.1f} % (limit {self.limit * 100:g} %), SYNC to last frame "
            f"{self.busiest_cycle_s * 1e6:.0f} us"
        )
        if self.fits:
            return head + ": ok"
        if self.busiest_cycle_s > s.sync_period_s:
            return head + ": OVER (the busiest cycle overruns the SYNC period)"
        return head + ": OVER the limit"


def _rate_text(bitrate: float, data_bitrate: float | None) -> str:
    nominal = f"{bitrate / 1e6:g}"
    if data_bitrate is None:
        return f"{nominal} Mbit/s classical"
    return f"{nominal}/{data_bitrate / 1e6:g} Mbit/s FD"


def _figures(schedule: BusSchedule) -> tuple[tuple[FrameTiming, ...], float, float]:
    timings = tuple(
        FrameTiming(f, worst_case_seconds(f, schedule.bitrate, schedule.data_bitrate))
        for f in schedule.frames
    )
    period = schedule.sync_period_s
    load = sum(t.worst_case_s / (t.frame.period_cycles * period) for t in timings)
    hyper = math.lcm(*(f.period_cycles for f in schedule.frames)) if schedule.frames else 1
    if hyper > _MAX_HYPERPERIOD:
        busiest = sum(t.worst_case_s for t in timings)
    else:
        per_cycle = [0.0] * hyper
        for t in timings:
            step = t.frame.period_cycles
            for cycle in range(t.frame.offset_cycles, hyper, step):
                per_cycle[cycle] += t.worst_case_s
        busiest = max(per_cycle, default=0.0)
    return timings, load, busiest


def _fits(schedule: BusSchedule, limit: float) -> tuple[bool, float]:
    _timings, load, busiest = _figures(schedule)
    return load <= limit and busiest <= schedule.sync_period_s, load


def plan_bus(schedule: BusSchedule, limit: float = LOAD_LIMIT) -> BusPlan:
    """The worst-case load and busiest cycle of ``schedule`` and a verdict against
    ``limit``; over it, :func:`suggestions` computed from the numbers."""
    if not 0 < limit <= 1:
        raise ValueError(f"load limit must be in (0, 1], got {limit}")
    timings, load, busiest = _figures(schedule)
    notes = tuple(
        f"{f.name}: {f.length} bytes padded to an FD frame of {f.payload}"
        for f in schedule.frames
        if f.payload != f.length
    )
    plan = BusPlan(schedule, timings, load, busiest, limit, notes, ())
    if not plan.fits:
        plan = replace(plan, suggestions=suggestions(schedule, limit))
    return plan


# --- layouts -------------------------------------------------------------------------


def cia402_schedule(
    joints: int | Sequence[int],
    *,
    name: str = "can0",
    bitrate: int = 1_000_000,
    data_bitrate: int | None = None,
    sync_period_s: float = 1e-3,
    sync_length: int = 1,
    rpdo_length: int = 8,
    tpdo_length: int = 8,
    telemetry: Sequence[int] = (),
    telemetry_every: int = 1,
    first_node_id: int = 2,
    joint_names: Sequence[str] | None = None,
    fd_frames: bool = False,
    fd_packing: bool = False,
) -> BusSchedule:
    """The cyclic schedule of CiA 402 joints on one bus, one drive node per joint.

    ``joints``: a count (node-IDs ``first_node_id``, +1, ...; 2 is the single-joint rig's
    drive) or the node-IDs.  Per joint: RPDO1 (0x200 + node-ID, ``rpdo_length`` bytes,
    the command), TPDO1 (0x180 + node-ID, ``tpdo_length``, the sensors), and one frame
    per entry of ``telemetry`` (its length) as TPDO2-4 of the joint's node-ID (0x280,
    0x380, 0x480 + node-ID); telemetry every ``telemetry_every`` cycles, the joints'
    frames spread over those cycles.  A SYNC of ``sync_length`` bytes (0 or 1, with the
    counter) every cycle.  ``fd_frames``: every PDO an FD frame with BRS (the bus needs
    ``data_bitrate``); ``fd_packing``: the joints' frames packed per direction into FD
    frames (:func:`fd_pack`; ``data_bitrate`` defaults to 5 Mbit/s).
    """
    node_ids = (
        list(range(first_node_id, first_node_id + joints))
        if isinstance(joints, int)
        else list(joints)
    )
    if not node_ids:
        raise ValueError("a schedule needs at least one joint")
    if len(set(node_ids)) != len(node_ids):
        raise ValueError(f"node-IDs repeat: {node_ids}")
    if len(telemetry) > 3:
        raise ValueError(
            "the predefined connection set leaves TPDO2-4: at most 3 telemetry frames per joint"
        )
    if telemetry_every < 1:
        raise ValueError(f"telemetry_every must be >= 1, got {telemetry_every}")
    if sync_length not in (0, 1):
        raise ValueError(f"a CiA 301 SYNC carries 0 or 1 byte, not {sync_length}")
    names = (
        list(joint_names)
        if joint_names is not None
        else [f"J{i + 1}" for i in range(len(node_ids))]
    )
    if len(names) != len(node_ids):
        raise ValueError(f"{len(names)} joint names for {len(node_ids)} joints")
    if fd_packing and data_bitrate is None:
        data_bitrate = DEFAULT_DATA_BITRATE
    if fd_frames and data_bitrate is None:
        raise ValueError("FD frames need a data bit rate")
    frames = [CyclicFrame("SYNC", SYNC_COB_ID, sync_length, role="sync")]
    fd = fd_frames
    for index, (joint, node) in enumerate(zip(names, node_ids, strict=True)):
        for kind, length in (("rpdo", rpdo_length), ("tpdo", tpdo_length)):
            frames.append(
                CyclicFrame(
                    f"{joint}_{kind.upper()}1",
                    pdo_cob_id(kind, 1, node),  # type: ignore[arg-type]
                    length,
                    fd=fd,
                    role=kind,  # type: ignore[arg-type]
                    joint=joint,
                )
            )
        for number, length in enumerate(telemetry, 2):
            frames.append(
                CyclicFrame(
                    f"{joint}_TPDO{number}",
                    pdo_cob_id("tpdo", number, node),
                    length,
                    period_cycles=telemetry_every,
                    offset_cycles=index % telemetry_every,
                    fd=fd,
                    role="telemetry",
                    joint=joint,
                )
            )
    schedule = BusSchedule(name, tuple(frames), bitrate, data_bitrate, sync_period_s)
    return fd_pack(schedule) if fd_packing else schedule


def fd_pack(schedule: BusSchedule, data_bitrate: int | None = None) -> BusSchedule:
    """The joints' frames packed into FD frames with BRS: per role (RPDO, TPDO, each
    telemetry frame), period and offset, the joints' payloads one after another in
    frames of at most 64 bytes (a joint's payload never split); a packed frame takes the
    identifier of the first joint frame it carries.  Frames of no joint (SYNC) stay as
    they are.  The bus gets ``data_bitrate`` (default: its own, else 5 Mbit/s).

    A packed TPDO has one transmitter for all its joints: a multi-axis drive (CiA 402
    allows up to eight axes in one device) or a gateway."""
    rate = data_bitrate or schedule.data_bitrate or DEFAULT_DATA_BITRATE
    groups: dict[tuple[FrameRole, int, int, int], list[CyclicFrame]] = {}
    slots: dict[tuple[str | None, str], int] = {}
    kept: list[CyclicFrame] = []
    for frame in schedule.frames:
        if frame.joint is None:
            kept.append(frame)
            continue
        slot = slots.get((frame.joint, frame.role), 0)
        slots[(frame.joint, frame.role)] = slot + 1
        key = (frame.role, slot, frame.period_cycles, frame.offset_cycles)
        groups.setdefault(key, []).append(frame)
    packed: list[CyclicFrame] = []
    for (role, _slot, period, offset), members in groups.items():
        chunks: list[list[CyclicFrame]] = [[]]
        for frame in members:
            if chunks[-1] and sum(f.length for f in chunks[-1]) + frame.length > 64:
                chunks.append([])
            chunks[-1].append(frame)
        for chunk in chunks:
            first = chunk[0]
            joints = "+".join(str(f.joint) for f in chunk)
            packed.append(
                CyclicFrame(
                    f"{first.name.removeprefix(str(first.joint) + '_')} ({joints})",
                    first.can_id,
                    sum(f.length for f in chunk),
                    period_cycles=period,
                    offset_cycles=offset,
                    fd=True,
                    brs=True,
                    extended=any(f.extended for f in chunk),
                    role=role,
                )
            )
    return BusSchedule(
        schedule.name, (*kept, *packed), schedule.bitrate, rate, schedule.sync_period_s
    )


def decimate_telemetry(schedule: BusSchedule, every: int) -> BusSchedule:
    """The schedule with each telemetry frame sent every ``every`` of its present
    periods, the frames spread over the cycles in between (round robin)."""
    if every < 1:
        raise ValueError(f"decimation must be >= 1, got {every}")
    frames = []
    index = 0
    for frame in schedule.frames:
        if frame.role == "telemetry":
            period = frame.period_cycles * every
            offset = (frame.offset_cycles + frame.period_cycles * (index % every)) % period
            frame = replace(frame, period_cycles=period, offset_cycles=offset)
            index += 1
        frames.append(frame)
    return replace(schedule, frames=tuple(frames))


def _without_joints(schedule: BusSchedule, keep: Sequence[str]) -> BusSchedule:
    frames = tuple(f for f in schedule.frames if f.joint is None or f.joint in keep)
    return replace(schedule, frames=frames)


def joints_that_fit(schedule: BusSchedule, limit: float = LOAD_LIMIT) -> int:
    """How many of the schedule's joints (its first ones, with their frames as they
    are) fit on one bus like it under ``limit``."""
    joints = schedule.joints
    count = 0
    for k in range(1, len(joints) + 1):
        if not _fits(_without_joints(schedule, joints[:k]), limit)[0]:
            break
        count = k
    return count


def suggestions(schedule: BusSchedule, limit: float = LOAD_LIMIT) -> tuple[str, ...]:
    """Concrete changes for a schedule over ``limit``, computed from its numbers, one
    line each: how many of its joints fit per bus like it, FD packing's load for the
    same joints, decimated telemetry's load."""
    out: list[str] = []
    joints = schedule.joints
    rate = _rate_text(schedule.bitrate, schedule.data_bitrate)
    pct = limit * 100
    if joints:
        fit = joints_that_fit(schedule, limit)
        if fit == 0:
            _ok, alone = _fits(_without_joints(schedule, joints[:1]), limit)
            out.append(
                f"move joints to other buses: not even one joint fits on a {rate} bus "
                f"like this ({alone * 100:.1f} % with {joints[0]} alone)"
            )
        elif fit < len(joints):
            buses = math.ceil(len(joints) / fit)
            _ok, load = _fits(_without_joints(schedule, joints[:fit]), limit)
            out.append(
                f"move joints to other buses: at most {fit} of these joints per {rate} bus "
                f"({load * 100:.1f} % with {fit}), {buses} buses for all {len(joints)}"
            )
        if any(f.joint is not None for f in schedule.frames):
            packed = fd_pack(schedule)
            ok, load = _fits(packed, limit)
            verdict = "fits" if ok else f"over {pct:g} %"
            rates = _rate_text(packed.bitrate, packed.data_bitrate)
            out.append(
                f"FD packing (the {len(joints)} joints in one FD frame per direction at "
                f"{rates}): {load * 100:.1f} %, {verdict}"
            )
    if any(f.role == "telemetry" for f in schedule.frames):
        for every in _DECIMATIONS:
            ok, load = _fits(decimate_telemetry(schedule, every), limit)
            if ok:
                out.append(
                    f"decimated telemetry (every {every} cycles, spread): {load * 100:.1f} %, fits"
                )
                break
        else:
            bare = replace(
                schedule, frames=tuple(f for f in schedule.frames if f.role != "telemetry")
            )
            _ok, load = _fits(bare, limit)
            out.append(
                f"decimated telemetry does not suffice: {load * 100:.1f} % even without "
                f"telemetry (limit {pct:g} %)"
            )
    return tuple(out)
