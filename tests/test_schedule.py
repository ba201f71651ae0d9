"""The bus schedule planner: worst-case load, busiest cycle, verdict and suggestions for
CiA 402 joints on classical and FD buses."""

from __future__ import annotations

import cantools
import pytest

from hdhil.can import busload
from hdhil.can.bittiming import worst_case_fd_frame_bits
from hdhil.can.schedule import (
    BusSchedule,
    CyclicFrame,
    cia402_schedule,
    decimate_telemetry,
    fd_pack,
    joints_that_fit,
    pdo_cob_id,
    plan_bus,
    suggestions,
)
from hdhil.dbc import worst_case_frame_bits


def test_cob_ids_of_the_predefined_connection_set() -> None:
    # CiA 301: TPDO1..4 at 0x180/0x280/0x380/0x480 + node-ID, RPDO1..4 at 0x200/.../0x500.
    assert [pdo_cob_id("tpdo", n, 5) for n in (1, 2, 3, 4)] == [0x185, 0x285, 0x385, 0x485]
    assert [pdo_cob_id("rpdo", n, 5) for n in (1, 2, 3, 4)] == [0x205, 0x305, 0x405, 0x505]
    with pytest.raises(ValueError, match="node-ID"):
        pdo_cob_id("tpdo", 1, 128)
    schedule = cia402_schedule([3, 7], telemetry=(8, 4))
    ids = {f.name: f.can_id for f in schedule.frames}
    assert ids == {
        "SYNC": 0x080,
        "J1_RPDO1": 0x203, "J1_TPDO1": 0x183, "J1_TPDO2": 0x283, "J1_TPDO3": 0x383,
        "J2_RPDO1": 0x207, "J2_TPDO1": 0x187, "J2_TPDO2": 0x287, "J2_TPDO3": 0x387,
    }  # fmt: skip


def _unstuffed_us(length: int) -> int:
    return 47 + 8 * length  # classical base frame at 1 Mbit/s, IFS included


@pytest.mark.parametrize("joints", [1, 2, 3, 4, 7])
def test_classical_1_mbit_fits_two_joints_with_8_byte_pdos(joints: int) -> None:
    plan = plan_bus(cia402_schedule(joints))
    # Every frame every cycle: load = busiest cycle = SYNC + 2 PDOs per joint, each
    # between its unstuffed length and docs/design.md's identifier-free bound.
    low = (_unstuffed_us(1) + 2 * joints * _unstuffed_us(8)) * 1e-6
    high = (worst_case_frame_bits(1) + 2 * joints * worst_case_frame_bits(8)) * 1e-6
    assert low < plan.busiest_cycle_s <= high
    assert plan.load == pytest.approx(plan.busiest_cycle_s / 1e-3)
    assert plan.fits == (joints <= 2)
    assert (plan.load <= 0.60) == (joints <= 2)
    assert plan.verdict().endswith(": ok") == (joints <= 2)
    assert bool(plan.suggestions) == (joints > 2)


def test_fd_packing_puts_seven_joints_on_one_bus() -> None:
    plan = plan_bus(cia402_schedule(7, fd_packing=True, data_bitrate=5_000_000))
    assert plan.fits and plan.load < 0.60
    names = [t.frame.name for t in plan.frames]
    assert names == ["SYNC", "RPDO1 (J1+J2+J3+J4+J5+J6+J7)", "TPDO1 (J1+J2+J3+J4+J5+J6+J7)"]
    assert [t.frame.payload for t in plan.frames] == [1, 64, 64]  # 56 bytes padded
    assert len(plan.notes) == 2 and "56 bytes padded to an FD frame of 64" in plan.notes[0]
    # Each packed frame at most the identifier-free FD bound at 1/5 Mbit/s (~169 us).
    bound = worst_case_fd_frame_bits(64).seconds(1e6, 5e6)
    assert all(t.worst_case_s <= bound for t in plan.frames[1:])
    assert plan.busiest_cycle_s <= 65e-6 + 2 * bound
    # Without BRS the same packing does not fit.
    slow = cia402_schedule(7, fd_packing=True, data_bitrate=1_000_000)
    assert not plan_bus(slow).fits


def test_packing_splits_at_64_bytes_without_splitting_a_joint() -> None:
    packed = fd_pack(cia402_schedule(12, rpdo_length=6))
    rpdos = [f for f in packed.frames if f.role == "rpdo"]
    assert [f.length for f in rpdos] == [60, 12]  # 10 joints x 6 bytes, then 2
    assert len({f.can_id for f in packed.frames}) == len(packed.frames)


def test_suggestions_are_computed_from_the_numbers() -> None:
    schedule = cia402_schedule(7)
    lines = suggestions(schedule)
    assert joints_that_fit(schedule) == 2
    assert lines[0].startswith("move joints to other buses: at most 2 of these joints")
    assert "4 buses for all 7" in lines[0]
    packed_load = plan_bus(fd_pack(schedule)).load
    assert lines[1] == (
        "FD packing (the 7 joints in one FD frame per direction at 1/5 Mbit/s FD): "
        f"{packed_load * 100:.1f} %, fits"
    )
    assert all("\n" not in line for line in lines)


def test_decimated_telemetry_is_suggested_and_spread() -> None:
    # Two joints, 5-byte command, 8-byte sensors and 8-byte telemetry each: over 60 %
    # every cycle; telemetry every 4th cycle, the joints' frames in different cycles.
    schedule = cia402_schedule(2, rpdo_length=5, telemetry=(8,))
    assert not plan_bus(schedule).fits
    lines = suggestions(schedule)
    decimated = [line for line in lines if line.startswith("decimated telemetry")]
    assert len(decimated) == 1
    every = int(decimated[0].split("every ")[1].split()[0])
    plan = plan_bus(decimate_telemetry(schedule, every))
    assert plan.fits and f"{plan.load * 100:.1f} %" in decimated[0]
    assert not plan_bus(decimate_telemetry(schedule, every - 1)).fits
    # Spread: no cycle carries both joints' telemetry.
    offsets = [f.offset_cycles for f in plan.schedule.frames if f.role == "telemetry"]
    assert len(set(offsets)) == 2
    timings = {t.frame.name: t.worst_case_s for t in plan.frames}
    busiest = sum(v for k, v in timings.items() if "TPDO2" not in k) + timings["J1_TPDO2"]
    assert plan.busiest_cycle_s == pytest.approx(busiest)


def test_busiest_cycle_overrun_is_refused_even_under_the_mean_limit() -> None:
    # Decimated frames all in cycle 0: the mean load is low, cycle 0 overruns 1 ms.
    frames = [CyclicFrame("SYNC", 0x80, 1, role="sync")]
    frames += [CyclicFrame(f"T{i}", 0x300 + i, 8, period_cycles=10) for i in range(8)]
    plan = plan_bus(BusSchedule("can1", tuple(frames)))
    assert plan.load < 0.60
    assert plan.busiest_cycle_s > 1e-3 and not plan.fits
    assert "overruns the SYNC period" in plan.verdict()
    spread = [
        CyclicFrame(f"T{i}", 0x300 + i, 8, period_cycles=10, offset_cycles=i) for i in range(8)
    ]
    assert plan_bus(BusSchedule("can1", (frames[0], *spread))).fits


def test_periods_in_ms_and_invalid_schedules() -> None:
    frame = CyclicFrame.every_ms("T", 0x181, 8, 2.0, sync_period_s=1e-3)
    assert frame.period_cycles == 2
    with pytest.raises(ValueError, match="not a whole number"):
        CyclicFrame.every_ms("T", 0x181, 8, 1.5, sync_period_s=1e-3)
    with pytest.raises(ValueError, match="0 to 8 bytes"):
        CyclicFrame("T", 0x181, 12)
    with pytest.raises(ValueError, match="classical bus"):
        BusSchedule("can0", (CyclicFrame("T", 0x181, 12, fd=True),))
    with pytest.raises(ValueError, match="share identifier"):
        BusSchedule("can0", (CyclicFrame("A", 0x181, 8), CyclicFrame("B", 0x181, 8)))
    with pytest.raises(ValueError, match="offset"):
        CyclicFrame("T", 0x181, 8, period_cycles=2, offset_cycles=2)


def test_busload_counts_fd_messages_of_a_database(monkeypatch) -> None:
    db = cantools.database.Database()
    db.messages.append(cantools.database.Message(0x181, "PACKED", 64, [], cycle_time=1, is_fd=True))
    monkeypatch.setattr(busload, "database", lambda _bus: db)
    load = busload.schedule_load("control", 1_000_000, 1e-3, data_bitrate=5_000_000)
    expected = worst_case_fd_frame_bits(64).seconds(1e6, 5e6) / 1e-3
    assert load.worst_case_load == pytest.approx(expected)
    without_brs = busload.schedule_load("control", 1_000_000, 1e-3)
    assert without_brs.worst_case_load == pytest.approx(
        worst_case_fd_frame_bits(64, brs=False).total / 1e6 / 1e-3
    )
