"""A rig of several joints as scenario data (hdhil.rig.layout): buses, joints, URDF."""

from __future__ import annotations

from pathlib import Path

import pytest

from hdhil.core.dataconf import ConfigError
from hdhil.rig.scenario import load_scenario, scenario_data, scenario_from_dict

HEAD = '[scenario]\nname = "rig"\nduration_s = 1.0\n'

URDF = """<?xml version="1.0"?>
<robot name="two">
  <link name="base"/><link name="upper"/><link name="tool"/><link name="fore"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="upper"/>
    <limit lower="-1" upper="1" effort="50" velocity="2"/>
  </joint>
  <joint name="flange" type="fixed"><parent link="upper"/><child link="tool"/></joint>
  <joint name="elbow" type="continuous"><parent link="upper"/><child link="fore"/></joint>
</robot>
"""


def write(tmp_path: Path, text: str, name: str = "rig.toml") -> Path:
    path = tmp_path / name
    path.write_text(HEAD + text)
    return path


def test_single_joint_scenarios_have_no_rig() -> None:
    s = load_scenario("free-motion")
    assert not s.is_rig and s.joints == () and s.buses == ()
    assert "joints" not in scenario_data(s) and "buses" not in scenario_data(s)


def test_joints_on_two_buses_with_their_own_plant_and_firmware(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
[plant.drivetrain]
k_flex = 1.0e4
[buses.a]
bitrate = 1000000
[buses.b]
fd = true
data_bitrate = 5000000
[joints.J1]
bus = "a"
[joints.J2]
bus = "a"
node_id = 7
[joints.J2.plant.drivetrain]
k_flex = 2.0e4
[joints.J3]
bus = "b"
[joints.J3.firmware.ripple]
mode = "paper"
""",
    )
    s = load_scenario(path)
    assert s.is_rig
    assert [(j.name, j.bus, j.node_id) for j in s.joints] == [
        ("J1", "a", 2),  # the lowest free node-ID from 2 (the controller is 1)
        ("J2", "a", 7),
        ("J3", "b", 2),
    ]
    buses = dict(s.buses)
    assert not buses["a"].fd and buses["b"].fd and buses["b"].data_bitrate == 5_000_000
    (p1, f1), (p2, _), (_, f3) = s.joint_configs
    assert p1.drivetrain.k_flex == 1.0e4 and p2.drivetrain.k_flex == 2.0e4
    assert f1.ripple.mode == "recommended" and f3.ripple.mode == "paper"
    # the plain form loads back to the same scenario, joint configurations included
    again = scenario_from_dict(scenario_data(s))
    assert again == s and again.joint_configs == s.joint_configs


def test_auto_node_ids_skip_the_ones_given(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "[joints.A]\n[joints.B]\nnode_id = 2\n[joints.C]\n",
    )
    s = load_scenario(path)
    assert [(j.name, j.node_id) for j in s.joints] == [("A", 3), ("B", 2), ("C", 4)]
    assert [name for name, _ in s.buses] == ["control"]


def test_the_urdf_gives_the_joints_and_tables_override_them(tmp_path: Path) -> None:
    (tmp_path / "arm.urdf").write_text(URDF)
    path = write(
        tmp_path,
        '[robot]\nurdf = "arm.urdf"\n[joints.elbow]\nnode_id = 9\n',
    )
    s = load_scenario(path)
    # revolute and continuous joints, in the file's order; the fixed one joins its links
    assert [(j.name, j.node_id) for j in s.joints] == [("shoulder", 2), ("elbow", 9)]
    assert s.robot is not None and Path(s.robot.urdf) == tmp_path / "arm.urdf"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('[joints.A]\nbus = "x"\n', r"joints\.A\.bus: no bus 'x'"),
        (
            "[buses.a]\n[buses.b]\n[joints.A]\n",
            r"joints\.A\.bus: the rig has buses a, b; say which",
        ),
        ("[joints.A]\nnode_id = 2\n[joints.B]\nnode_id = 2\n", "node-ID 2 is already taken"),
        ("[joints.A]\nnode_id = 1\n", "node-ID 1 is already taken"),  # the controller's
        ("[joints.A]\nnode_id = 128\n", r"node_id must be a CANopen node-ID 1\.\.127"),
        ("[joints.A]\ngear = 3\n", r"unknown key joints\.A\.gear"),
        ("[joints.A.plant.drivetrain]\nk_flux = 1\n", r"joints\.A\.plant.*k_flux"),
        ("[buses.a]\ndata_bitrate = 5000000\n[joints.A]\n", "needs fd = true"),
        ("[buses.a]\n", r"a rig needs joints"),
        ('[robot]\nurdf = "missing.urdf"\n', "robot.urdf: no such file"),
    ],
)
def test_rig_mistakes_are_one_line_errors(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        load_scenario(write(tmp_path, text))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("kind", ["prismatic", "floating", "planar"])
def test_a_joint_type_hdhil_cannot_emulate_is_refused(tmp_path: Path, kind: str) -> None:
    (tmp_path / "arm.urdf").write_text(URDF.replace('type="continuous"', f'type="{kind}"'))
    with pytest.raises(ConfigError, match=f"joint 'elbow' is '{kind}'"):
        load_scenario(write(tmp_path, '[robot]\nurdf = "arm.urdf"\n'))


def test_a_joint_table_must_name_a_urdf_joint(tmp_path: Path) -> None:
    (tmp_path / "arm.urdf").write_text(URDF)
    with pytest.raises(ConfigError, match=r"joints\.wrist: the URDF has no actuated joint"):
        load_scenario(write(tmp_path, '[robot]\nurdf = "arm.urdf"\n[joints.wrist]\n'))


def test_runs_refuse_a_rig_with_one_line_and_exit_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from hdhil.cli import main

    monkeypatch.chdir(tmp_path)
    path = write(tmp_path, "[joints.A]\n[joints.B]\n")
    # hdhil run takes a rig in lockstep on simbus (tests/test_rig_run.py), not yet in real
    # time or on another interface
    for extra in (["--realtime"], ["--interface", "virtual"]):
        assert main(["run", "--scenario", str(path), "--duration", "0.01", *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "lays out 2 joints" in err
        assert not list(tmp_path.glob("*.blf"))
    from hdhil.rig.request import resolve
    from hdhil.rig.runner import run_lockstep

    with pytest.raises(ConfigError, match=r"lays out 2 joint\(s\) on 1 bus\(es\)"):
        run_lockstep(resolve(path, duration_s=0.01))
