"""hdhil plan and hdhil dbc export --scenario: a rig's buses planned and its databases
generated from the layout (hdhil.analysis.rigplan)."""

from __future__ import annotations

import json
from pathlib import Path

import can
import cantools
import pytest

from hdhil.analysis.rigplan import plan_scenario
from hdhil.can.bittiming import worst_case_frame_bits_for
from hdhil.can.busload import schedule_load
from hdhil.cli import main
from hdhil.rig.scenario import load_scenario


def test_a_single_joint_plans_the_load_hdhil_run_checks() -> None:
    """The same quantity in both commands: the run's schedule check of the shipped DBC
    and the plan of the generated database."""
    plan = plan_scenario(load_scenario("free-motion"))
    (bus,) = plan.buses
    assert bus.load == pytest.approx(schedule_load("control", 1_000_000, 1e-3).worst_case_load)
    assert plan.fits and plan.joints == {"control": ("joint",)}


def test_rehabexos_two_joints_per_bus_with_decimated_telemetry() -> None:
    plan = plan_scenario(load_scenario("rehabexos"))
    assert [p.schedule.name for p in plan.buses] == ["can0", "can1"]
    assert plan.joints == {"can0": ("J1", "J2"), "can1": ("J3", "J4")}

    def us(can_id: int, length: int) -> float:
        return worst_case_frame_bits_for(can_id, False, length)  # at 1 Mbit/s: 1 bit = 1 us

    # SYNC, both sensor PDOs and commands every cycle; the controller's two telemetry
    # frames of each joint every 10th cycle
    expected = (
        us(0x080, 1)
        + us(0x182, 8) + us(0x183, 8) + us(0x202, 5) + us(0x203, 5)
        + (us(0x181, 8) + us(0x281, 8) + us(0x381, 8) + us(0x481, 8)) / 10
    ) / 1000  # fmt: skip
    for p in plan.buses:
        assert p.load == pytest.approx(expected)
        assert p.fits and p.load <= 0.60
        # the busiest cycle: every-cycle frames plus one telemetry frame
        assert p.busiest_cycle_s < 1e-3


def test_fd_variants_fit_on_one_bus() -> None:
    for name, joints in (("rehabexos-fd", 4), ("arm7-fd", 7)):
        plan = plan_scenario(load_scenario(name))
        (bus,) = plan.buses
        assert len(plan.joints[bus.schedule.name]) == joints
        assert bus.fits and bus.schedule.data_bitrate == 5_000_000
        packed = [t for t in bus.frames if t.frame.fd and t.frame.length > 8]
        assert packed  # each direction's frames of the joints share FD frames


def test_arm7_on_four_classical_buses() -> None:
    plan = plan_scenario(load_scenario("arm7"))
    assert [len(j) for j in plan.joints.values()] == [2, 2, 2, 1]
    assert plan.fits


def write_rig(tmp_path: Path, joints: int, every: int = 1) -> Path:
    path = tmp_path / "rig.toml"
    text = f'[scenario]\nname = "rig"\nduration_s = 1.0\n[buses.c]\ntelemetry_every = {every}\n'
    for i in range(1, joints + 1):
        # a controller node reports two joints' telemetry (docs/rigdb.md)
        controller = 1 if i <= 2 else 100 + (i - 1) // 2
        text += f'[joints.J{i}]\nbus = "c"\ncontroller_node_id = {controller}\n'

    path.write_text(text)
    return path


def test_a_bus_over_the_limit_is_refused_with_a_suggestion(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_rig(tmp_path, 3)
    assert main(["plan", "--scenario", str(path), "--no-cpu"]) == 2
    out, err = capsys.readouterr()
    assert "OVER" in out and "move joints to other buses" in out
    assert err.count("\n") == 1
    assert err.startswith("hdhil: error: scenario rig: bus c needs ")
    assert "limit 60 %" in err and "at most 1 of these joints" in err


def test_plan_json_and_the_cpu_prediction(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_rig(tmp_path, 2, every=10)
    assert main(["plan", "--scenario", str(path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    (bus,) = data["buses"]
    assert data["fits"] and bus["joints"] == ["J1", "J2"] and bus["worst_case_load"] <= 0.6
    cpu = data["cpu"]
    m = cpu["model"]
    frames = sum(1 / f["every_cycles"] for f in bus["frames"]) + 3 * 2  # truth per joint
    assert cpu["frames_per_cycle"] == pytest.approx(frames)
    assert cpu["one_process_us"] == pytest.approx(
        m["fixed_us"] + 2 * m["per_joint_us"] + frames * m["per_frame_us"]
    )
    assert m["per_joint_us"] > 0 and m["per_frame_us"] > 0


def test_dbc_export_of_a_rig_one_database_per_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rehab.dbc"
    assert main(["dbc", "export", str(out), "--scenario", "rehabexos"]) == 0
    files = sorted(p.name for p in tmp_path.glob("*.dbc"))
    assert files == ["rehab-can0.dbc", "rehab-can1.dbc"]
    # a third-party reader decodes J3's sensor frame on can1 by name
    db = cantools.database.load_file(str(tmp_path / "rehab-can1.dbc"))
    msg = db.get_message_by_name("J3_DRIVE_TPDO1")
    data = msg.encode({s.name: 0 for s in msg.signals})
    frame = can.Message(arbitration_id=msg.frame_id, data=data, is_extended_id=False)
    assert db.decode_message(frame.arbitration_id, frame.data) == {s.name: 0 for s in msg.signals}
    assert "J1_DRIVE_TPDO1" not in {m.name for m in db.messages}  # J1 is on can0


def test_dbc_export_of_a_single_joint_scenario_is_the_merged_database(tmp_path: Path) -> None:
    a, b = tmp_path / "a.dbc", tmp_path / "b.dbc"
    assert main(["dbc", "export", str(a), "--scenario", "free-motion"]) == 0
    assert main(["dbc", "export", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()


def test_dbc_export_of_a_rig_writes_all_or_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "rehab-can1.dbc").mkdir()  # the second bus's file cannot be written
    assert main(["dbc", "export", str(tmp_path / "rehab.dbc"), "--scenario", "rehabexos"]) == 2
    assert not (tmp_path / "rehab-can0.dbc").exists()
    assert "not a regular file" in capsys.readouterr().err
