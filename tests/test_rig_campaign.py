"""Campaigns over a rig of several joints: axes naming a joint's setting
(``joints.NAME.KEY``), metrics per joint and for the worst joint, a variant equal to
``hdhil run`` of the same settings; single-joint campaigns keep their columns."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hdhil.cli import main
from hdhil.core import jsonout
from hdhil.core.dataconf import ConfigError
from hdhil.rig.campaign_file import load_campaign
from hdhil.rig.campaign_metrics import METRICS, Criterion, joint_metrics_of, metrics_of
from hdhil.rig.campaign_report import columns
from hdhil.rig.campaign_variants import expand
from hdhil.rig.variant import WALL_CLOCK_KEYS

RIG = """
[campaign]
name = "rig"
scenarios = ["rehabexos"]
duration_s = 1.2  # the torque is scored from rehabexos's evaluate_from_s, 1 s
criteria = ["worst.filtered_rms_err_Nm < 5", "joints.J3.samples >= 1200"]
plots = ["joints.J3.filtered_max_err_Nm"]

[axes]
joints.J3.firmware.control.torque_limit_Nm = [50.0, 75.0]
"""


def _campaign(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "c.toml"
    path.write_text(body, encoding="utf-8")
    return path


def _joint(name: str, rms: float, share: float) -> dict:
    return {"name": name, "samples": 100,
            "torque": {"rms_error_filtered": rms, "rms_error_raw": 2 * rms},
            "tracking": {"rms_error": rms, "share_within_goal_measured": share}}  # fmt: skip


def test_a_rigs_metrics_are_given_per_joint_and_for_the_worst_joint():
    result = {"cycles": 100, "simulated_s": 0.1, "frames": {"can0": 7, "can1": 5},
              "joints": [_joint("J1", 0.2, 0.9), _joint("J2", 0.5, 0.97),
                         _joint("J3", 0.1, 0.8)]}  # fmt: skip
    m = metrics_of(result, 100)  # a rig's result has no single joint's controller figures
    assert m["joints.J2.filtered_rms_err_Nm"] == 0.5
    assert m["joints.J3.share_within_goal_measured"] == 0.8
    # the worst joint: the largest error, the smallest share within the goal
    assert m["worst.filtered_rms_err_Nm"] == 0.5
    assert m["worst.filtered_rms_err_Nm.joint"] == "J2"
    assert m["worst.share_within_goal_measured"] == 0.8
    assert m["worst.share_within_goal_measured.joint"] == "J3"
    assert m["worst.max_abs_e_Nm"] is None  # no joint reports it
    assert m["frames_total"] == 12 and m["cycles"] == 100 and m["stopped_early"] is False
    assert m["kalman_skipped"] is None
    assert joint_metrics_of({"cycles": 1}) == {}  # a single joint's result: none


def test_criteria_and_plots_name_a_joint_or_the_worst_joint():
    assert Criterion.parse("joints.J3.rms_e_Nm < 0.5").metric == "joints.J3.rms_e_Nm"
    assert Criterion.parse("worst.share_within_goal_measured>=0.95").value == 0.95
    assert Criterion.parse("joints.panda_joint7.samples >= 10").metric.endswith("7.samples")
    for bad in ("joints.J3.nope < 1", "worst.rms_e_Nm.joint < 1", "joints.rms_e_Nm < 1"):
        with pytest.raises(ConfigError, match="unknown metric"):
            Criterion.parse(bad)


def test_an_axis_sets_one_joints_key(tmp_path):
    campaign = load_campaign(_campaign(tmp_path, RIG))
    variants = expand(campaign)
    assert [v.values for v in variants] == [
        {"joints.J3.firmware.control.torque_limit_Nm": 50.0},
        {"joints.J3.firmware.control.torque_limit_Nm": 75.0},
    ]
    assert variants[0].joints == ("J1", "J2", "J3", "J4")
    joints = variants[0].settings.scenario["joints"]
    assert joints["J3"]["firmware"]["control"]["torque_limit_Nm"] == 50.0
    assert joints["J1"]["firmware"]["control"]["torque_limit_Nm"] == 150.0  # untouched
    # results.csv: each joint's metrics and the worst joint's after the run's
    cols = columns(campaign, variants[0].joints)
    assert "joints.J4.rms_e_Nm" in cols and "worst.rms_e_Nm.joint" in cols
    assert cols.index("joints.J1.samples") > cols.index(list(METRICS)[-1])


def test_a_single_joint_campaign_keeps_its_columns(tmp_path):
    campaign = load_campaign("smoke")
    assert all(v.joints == () for v in expand(campaign))
    assert columns(campaign, ()) == columns(campaign)
    assert not any(c.startswith(("joints.", "worst.")) for c in columns(campaign))


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (("joints.J3.firmware", "joints.J9.firmware"), "joint J9 is not a joint of scenario"),
        (('"rehabexos"', '"free-motion"'), "scenario free-motion is a single joint"),
        (("joints.J3.samples", "joints.J7.samples"), "joint J7 is not a joint of scenario"),
        ((".firmware.control.torque_limit_Nm =", " ="), "a joint's key is joints.NAME.KEY"),
        (("joints.J3.firmware.control.torque_limit_Nm = [50.0, 75.0]",
          "faults.control.loss_rate = [0.0, 0.01]"), "without [faults]"),
    ],
)  # fmt: skip
def test_what_a_rig_campaign_cannot_take_is_one_line_before_anything_runs(
    tmp_path, capsys, change, words
):
    path = _campaign(tmp_path, RIG.replace(*change))
    out = tmp_path / "out"
    assert main(["campaign", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err, err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.subprocess  # the campaign's worker pool
def test_a_rig_variant_is_what_hdhil_run_json_prints_for_the_same_settings(tmp_path, capsys):
    pytest.importorskip("mujoco", reason="the arm extra (hdhil[arm]): rehabexos's URDF")
    out = tmp_path / "out"
    campaign = _campaign(tmp_path, RIG)
    args = ["campaign", str(campaign), "--workers", "1", "--out", str(out), "--json"]
    assert main(args) == 0  # both criteria pass
    variant = expand(load_campaign(campaign))[0]
    stored = jsonout.restore(json.loads((out / "runs" / f"{variant.digest}.json").read_text()))
    override = tmp_path / "j3.toml"
    override.write_text("[joints.J3.firmware.control]\ntorque_limit_Nm = 50.0\n")
    capsys.readouterr()
    code = main(["run", "--scenario", "rehabexos", "--duration", "1.2", "--override",
                 str(override), "--json"])  # fmt: skip
    assert code == 0
    printed = jsonout.restore(json.loads(capsys.readouterr().out))  # NaN as stored
    for key in WALL_CLOCK_KEYS:
        printed.pop(key, None)
    assert json.dumps(stored["result"], sort_keys=True) == json.dumps(printed, sort_keys=True)
    # ... and results.csv carries every joint's figures and the worst joint's.
    head, *rows = (out / "results.csv").read_text().splitlines()
    row = dict(zip(head.split(","), rows[0].split(","), strict=True))
    by_name = {j["name"]: j for j in printed["joints"]}
    for name, joint in by_name.items():
        assert int(row[f"joints.{name}.samples"]) == joint["samples"] == 1200
        assert 15 <= joint["torque"]["samples"] <= 25  # from 1 s, telemetry every 10th cycle
        rms = joint["torque"]["rms_error_filtered"]
        assert float(row[f"joints.{name}.filtered_rms_err_Nm"]) == rms
    worst = max(by_name.values(), key=lambda j: j["torque"]["rms_error_filtered"])
    assert row["worst.filtered_rms_err_Nm.joint"] == worst["name"]
    assert float(row["worst.filtered_rms_err_Nm"]) == worst["torque"]["rms_error_filtered"]
    assert row["joints.J3.samples >= 1200"] == "pass"
    plot = "joints.J3.filtered_max_err_Nm-over-joints_J3_firmware_control_torque_limit_Nm"
    assert (out / "plots" / f"{plot}.png").is_file()
