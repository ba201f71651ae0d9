"""``hdhil evaluate`` of a rig's trace: the table per joint and the worst joint, the same
figures ``hdhil run`` printed for the run that wrote the trace (hdhil.rig.trace_score.
score_rig_trace, the run's scorers from hdhil.rig.rigrun.joint_scoring).

Expected values are the run's own: each joint's torque and tracking figures, its printed
cells and the worst joint, equal to the last bit. The joints sit on two buses at the same
node-ID (the same identifiers on both), and differ, so a joint scored from another's
frames would show.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hdhil.cli import main
from hdhil.rig.request import resolve
from hdhil.rig.rigrun import format_rig_result, run_rig

TWO = Path(__file__).parent / "data" / "rig-two-joints.toml"

#: Two joints, each on a bus of its own at node-ID 2.
TWO_BUSES = {
    "buses": {"can0": {"bitrate": 1_000_000}, "can1": {"bitrate": 1_000_000}},
    "joints": {"A": {"bus": "can0", "node_id": 2}, "B": {"bus": "can1", "node_id": 2}},
}


def _canonical(rows: list[dict]) -> str:
    """Rows as JSON text: equal floats print alike, and NaN equals NaN."""
    return json.dumps(rows, sort_keys=True)


def _score_cells(text: str, names: tuple[str, ...], skip: int) -> dict[str, list[str]]:
    """Each joint's row of a printed table from its RMS raw column on (``skip`` columns
    before it: joint, bus, node and for a run state and samples)."""
    out = {}
    for line in text.splitlines():
        if line.startswith("  worst joint"):
            break  # the table ends; per-joint lines below are the candidate filters
        cells = line.split()
        if line.startswith("    ") and cells and cells[0] in names:
            out[cells[0]] = cells[skip:]
    return out


def _run_and_evaluate(
    request, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> tuple[object, dict, str]:
    trace = tmp_path / "rig.blf"
    result = run_rig(request, trace=trace, start_time=1.7e9)
    assert result.verdict is None and result.trace == str(trace)
    assert main(["evaluate", str(trace), "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert main(["evaluate", str(trace)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    return result, ev, captured.out


@pytest.mark.slow
def test_evaluate_of_a_rig_trace_prints_the_runs_torque_figures_per_joint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A rig scored on the ripple filter (free-motion's joints, B with the paper's
    filter): every joint's torque figures, printed cells and the worst joint are the
    run's."""
    request = resolve(TWO, overrides=[TWO_BUSES], duration_s=0.3, seed=5, evaluate_from_s=0.0)
    result, ev, text = _run_and_evaluate(request, tmp_path, capsys)
    assert [j["name"] for j in ev["joints"]] == ["A", "B"]
    assert ev["buses"] == {"can0": {"channel": 0, "fd": False, "joints": ["A"]},
                           "can1": {"channel": 2, "fd": False, "joints": ["B"]}}  # fmt: skip
    a, b = ev["joints"]
    assert a["torque"]["samples"] >= 300 and a["torque"] != b["torque"]
    run_rows = [{k: v for k, v in j.__dict__.items() if k not in ("drive_state", "samples")}
                for j in result.joints]  # fmt: skip
    assert _canonical(ev["joints"]) == _canonical(run_rows)
    assert ev["worst_joint"] == result.worst_joint
    assert "rms_error_filtered" in ev["worst_joint"]
    import hdhil.api

    assert _canonical(hdhil.api.evaluate_trace(tmp_path / "rig.blf")["joints"]) == _canonical(
        run_rows
    )
    ran = format_rig_result(result)
    assert _score_cells(text, ("A", "B"), 3) == _score_cells(ran, ("A", "B"), 5)
    worst = [line for line in ran.splitlines() if line.startswith("  worst joint")]
    assert worst and worst == [line for line in text.splitlines() if "worst joint" in line]


@pytest.mark.slow
def test_evaluate_of_a_rig_trace_prints_the_runs_tracking_figures_per_joint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A rig of torque-controlled joints (lqg-tracking's, B with a noisy torque sensor):
    every joint's tracking figures from the run's evaluation start are the run's, and
    ``--skip`` moves the tracking's start as the run's ``--skip`` does."""
    layout = {**TWO_BUSES, "joints": {**TWO_BUSES["joints"], "B": {
        "bus": "can1", "node_id": 2, "plant": {"sensors": {"torque_noise_Nm": 0.05}}}}}  # fmt: skip
    request = resolve("lqg-tracking", overrides=[layout], duration_s=0.6, seed=3,
                      evaluate_from_s=0.2)  # fmt: skip
    result, ev, text = _run_and_evaluate(request, tmp_path, capsys)
    assert ev["skip_s"] == 0.2 and ev["scored"] == ["tracking"]
    a, b = (j["tracking"] for j in ev["joints"])
    assert a["samples"] == 400 and a["rms_error"] != b["rms_error"]
    assert _canonical([j["tracking"] for j in ev["joints"]]) == _canonical(
        [j.tracking for j in result.joints]
    )
    assert ev["worst_joint"] == result.worst_joint
    ran = format_rig_result(result)
    assert _score_cells(text, ("A", "B"), 3) == _score_cells(ran, ("A", "B"), 5)
    # --skip: the run from 0.4 s scores what evaluate --skip 0.4 of the same trace does
    later = run_rig(resolve("lqg-tracking", overrides=[layout], duration_s=0.6, seed=3,
                            evaluate_from_s=0.4))  # fmt: skip
    assert main(["evaluate", str(tmp_path / "rig.blf"), "--json", "--skip", "0.4"]) == 0
    moved = json.loads(capsys.readouterr().out)
    assert _canonical([j["tracking"] for j in moved["joints"]]) == _canonical(
        [j.tracking for j in later.joints]
    )


def test_a_rig_trace_without_its_joints_frames_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A rig's sidecar beside a trace without the joints' telemetry and truth: one line,
    exit 2."""
    import can

    from hdhil.rig.rigrun import rig_metadata

    request = resolve(TWO, overrides=[TWO_BUSES], duration_s=0.1)
    trace = tmp_path / "empty.blf"
    with can.BLFWriter(str(trace)) as writer:
        writer.on_message_received(can.Message(arbitration_id=0x80, data=b"", timestamp=1.0))
    (tmp_path / "empty.blf.json").write_text(json.dumps(rig_metadata(request, 1.0)))
    assert main(["evaluate", str(trace)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no joint's telemetry" in err
