"""``hdhil run`` of a rig of several joints: lockstep on the simulated buses, in one
process (hdhil.rig.rigrun).

Expected values come from the single-joint run (a joint of a rig of independent plants
is the single-joint rig with the same seed), from the ripple filter's purpose (filtered
below raw) and from repetition (the same seed, the same figures).
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

from hdhil.rig.request import resolve
from hdhil.rig.rigrun import format_rig_result, run_rig

TWO = Path(__file__).parent / "data" / "rig-two-joints.toml"


def _figures(result) -> dict:
    d = result.as_dict()
    for key in ("wall_s", "us_per_cycle", "real_time_factor"):
        del d[key]
    return d


@pytest.mark.slow
def test_two_joints_on_one_bus_run_in_lockstep_and_score() -> None:
    """Both drives reach operation enabled, each joint is scored from its own telemetry
    and truth, the ripple filter brings each joint's error below its raw error, and the
    same seed gives the same figures twice."""
    # scored from the start (the scenario's evaluate_from_s is free-motion's 0.3 s)
    first = run_rig(resolve(TWO, duration_s=0.3, seed=5, evaluate_from_s=0.0))
    assert first.verdict is None and not first.interrupted
    assert first.cycles == 300 and first.simulated_s == pytest.approx(0.3)
    assert [j.name for j in first.joints] == ["A", "B"]
    for j in first.joints:
        assert j.drive_state == "OPERATION_ENABLED" and j.bus == "can0"
        t = j.torque
        assert t["samples"] >= 300
        assert t["rms_error_filtered"] < t["rms_error_raw"]
    assert [j.node_id for j in first.joints] == [2, 3]
    # each joint its own noise stream: the two joints' errors differ
    a, b = (j.torque for j in first.joints)
    assert a["rms_error_raw"] != b["rms_error_raw"]
    assert first.worst_joint["rms_error_filtered"]["joint"] in ("A", "B")
    again = run_rig(resolve(TWO, duration_s=0.3, seed=5, evaluate_from_s=0.0))
    assert _figures(again) == _figures(first)
    text = format_rig_result(first)
    assert "worst joint" in text and "candidate filters  per joint" in text
    assert (  # a row in the table and a line of candidate filters each
        sum(line.startswith("    A ") or line.startswith("    B ") for line in text.splitlines())
        == 4
    )


@pytest.mark.slow
def test_a_joint_of_independent_plants_is_the_single_joint_rig() -> None:
    """Joint A of a rig of independent plants (no [robot]) is the single-joint run of its
    scenario with the same seed: the same torque errors to the last bit (its frames at
    the single joint's identifiers, its truth at joint index 0, its plant's noise stream
    the seed), and the same evaluation of the candidate filters."""
    from hdhil.rig.runner import run_lockstep

    # B's filter as A's: the paper's filter starts its interrupts 16 samples later, and
    # the rig runs until every joint has run its samples
    same = {"joints": {"B": {"firmware": {"ripple": {"mode": "recommended"}}}}}
    rig = run_rig(resolve(TWO, overrides=[same], duration_s=0.5, seed=9, evaluate_from_s=0.0))
    single = run_lockstep(resolve("free-motion", duration_s=0.5, seed=9, evaluate_from_s=0.0))
    a = rig.joints[0].torque
    assert a["samples"] == single.torque["samples"]
    for key in ("rms_true", "rms_error_raw", "rms_error_filtered", "max_error_raw"):
        assert a[key] == single.torque[key], key
    ev, expected = rig.joints[0].evaluation, single.evaluation
    assert ev is not None and expected is not None and ev["samples"] == expected["samples"] > 0
    assert [(c["name"], c["rms_error"]) for c in ev["candidates"]] == [
        (c["name"], c["rms_error"]) for c in expected["candidates"]
    ]
    assert rig.joints[1].evaluation["candidates"] != ev["candidates"]  # B: its own joint
    text = format_rig_result(rig)
    firmware = next(c for c in ev["candidates"] if c["name"].startswith("firmware"))
    assert f"A        firmware (recommended) {firmware['rms_error']:.4f} Nm" in text
    assert (
        run_rig(resolve(TWO, duration_s=0.05, seed=9), evaluate=False).joints[0].evaluation is None
    )


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("mujoco") is None, reason="the arm extra")
def test_rehabexos_runs_every_joint_in_operation() -> None:
    """The four joints of rehabexos on two buses, the arm's plant moved once a cycle, a
    person wearing it: every joint reaches operation and gets its tracking row (the
    share of |e| <= 0.5 Nm on the measured torque after the first second, from the
    telemetry of every 10th cycle, printed per joint), and every joint meets the goal
    of 95 %."""
    result = run_rig(resolve("rehabexos", duration_s=3.0))
    assert result.verdict is None and result.cycles == 3000
    assert [j.name for j in result.joints] == ["J1", "J2", "J3", "J4"]
    assert [j.bus for j in result.joints] == ["can0", "can0", "can1", "can1"]
    assert result.buses["can1"]["channel"] == 2
    for j in result.joints:
        assert j.drive_state == "OPERATION_ENABLED"
        # the buses' telemetry every 10th cycle (telemetry_every): scored from those
        assert j.tracking is not None and 195 <= j.tracking["samples"] <= 205
        assert j.tracking["share_within_goal_measured"] >= 0.95, j.name
    worst = result.worst_joint["share_within_goal_measured"]
    assert worst["value"] == min(j.tracking["share_within_goal_measured"] for j in result.joints)
    text = format_rig_result(result)
    for j in result.joints:
        share = 100 * j.tracking["share_within_goal_measured"]
        row = next(line for line in text.splitlines() if line.startswith(f"    {j.name} "))
        assert f"{share:7.1f}%" in row and not math.isnan(share)


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("mujoco") is None, reason="the arm extra")
def test_an_arm_rig_is_deterministic(tmp_path: Path) -> None:
    """The same seed and start time give a byte-identical trace of an arm's rig (the
    arm's dynamics, the person's stroke and every joint's noise included); another
    seed does not."""
    traces = []
    for k, seed in enumerate((3, 3, 4)):
        path = tmp_path / f"arm{k}.blf"
        run_rig(resolve("rehabexos", duration_s=0.2, seed=seed), trace=path, start_time=1.7e9)
        traces.append(path.read_bytes())
    assert traces[0] == traces[1]
    assert traces[0] != traces[2]


@pytest.mark.slow
def test_hdhil_run_prints_a_row_per_joint_and_json(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    from hdhil.cli import main

    monkeypatch.chdir(tmp_path)
    run = ["run", "--scenario", str(TWO), "--duration", "0.1", "--skip", "0", "--trace", ""]
    # two joints with telemetry every cycle need 105.7 % of the bus: refused as by hdhil
    # plan, one line, exit 2, before anything runs
    assert main(run) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bus can0 needs 105.7 %" in err and "hdhil plan" in err
    (tmp_path / "decimated.toml").write_text("[buses.can0]\ntelemetry_every = 10\n")
    run += ["--override", "decimated.toml"]
    assert main(run) == 0
    out = capsys.readouterr().out
    assert "2 joints on 1 bus(es)" in out and "worst joint" in out
    assert not list(tmp_path.glob("*.blf"))
    assert main([*run, "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert [j["name"] for j in data["joints"]] == ["A", "B"]
    assert data["worst_joint"]["rms_error_filtered"]["joint"] in ("A", "B")


@pytest.mark.slow
def test_a_rig_trace_has_a_channel_per_bus_and_decodes_by_joint(tmp_path: Path) -> None:
    """Two buses: each on its own channel (0 and 2, the truth on 1), the sidecar records
    the layout, and the trace decodes with the rig's databases by joint name on each
    channel (the same identifier, a different joint); the same seed and start time give
    the same bytes."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.canopen.mapping import trace_decoder

    two_buses = {
        "buses": {"can1": {"bitrate": 1_000_000}},
        "joints": {"A": {"bus": "can0"}, "B": {"bus": "can1", "node_id": 2}},
    }
    request = resolve(TWO, overrides=[two_buses], duration_s=0.05, seed=4)
    traces = [tmp_path / f"rig{k}.blf" for k in range(2)]
    for path in traces:
        result = run_rig(request, trace=path, start_time=1.7e9)
        assert result.trace == str(path) and result.verdict is None
    assert traces[0].read_bytes() == traces[1].read_bytes()
    decoder = trace_decoder(traces[0])
    seen: dict[tuple[str, str], int] = {}
    trace = read_trace(traces[0])
    try:
        for msg in trace:
            frame = decoder.classify(msg)
            key = (frame.bus, frame.message or "?")
            seen[key] = seen.get(key, 0) + 1
    finally:
        trace.close()
    assert seen[("can0", "A_DRIVE_TPDO1")] >= 50 and seen[("can1", "B_DRIVE_TPDO1")] >= 50
    assert seen[("truth", "B_TRUTH_TORQUE")] >= 50
    assert not any(name == "?" for _, name in seen)


DECIMATED = Path(__file__).parent / "data" / "rig-decimated.toml"


@pytest.mark.slow
def test_decimated_telemetry_is_sent_in_the_planned_cycles_at_the_planned_load(
    tmp_path: Path,
) -> None:
    """A bus's telemetry_every: the controller nodes (the SYNC producer and a node that
    follows its SYNC) send each telemetry frame every 10th cycle, in the cycle the
    planner gives it; the trace's worst-case load of the planned frames (hdhil dump
    --stats) is the planner's; every joint is scored from the telemetry present."""
    from hdhil.analysis.rigplan import plan_scenario
    from hdhil.can.traces.reader import read_trace
    from hdhil.can.traces.stats import StatsAccumulator
    from hdhil.canopen.mapping import trace_decoder

    request = resolve(DECIMATED, duration_s=0.2, seed=3, evaluate_from_s=0.0)
    trace = tmp_path / "rig.blf"
    result = run_rig(request, trace=trace, start_time=1.7e9)
    assert result.verdict is None
    plan = plan_scenario(request.scenario).buses[0]
    planned = {t.frame.can_id: t.frame for t in plan.frames}
    telemetry = {i: f for i, f in planned.items() if f.role == "telemetry"}
    assert len(telemetry) == 4 and {f.period_cycles for f in telemetry.values()} == {10}
    cycle, cycles_of = -1, {i: set() for i in telemetry}
    decoder = trace_decoder(trace)
    stats = StatsAccumulator(decoder=decoder)
    with read_trace(trace) as frames:
        for msg in frames:
            stats.add(decoder.classify(msg, decode=False))
            if msg.channel != 0:
                continue
            if msg.arbitration_id == 0x080:
                cycle += 1
            elif msg.arbitration_id in telemetry:
                cycles_of[msg.arbitration_id].add(cycle % 10)
    assert cycles_of == {i: {f.offset_cycles} for i, f in telemetry.items()}
    ids = stats.result()["ids"]
    measured = sum(e["load_percent"] for e in ids if e["bus"] == "can0" and e["id"] in planned)
    assert measured == pytest.approx(plan.load * 100, abs=0.2)
    # the run's own figure: the planned frames and the service frames on top
    assert plan.load < result.buses["can0"]["worst_case_load"] < plan.load + 0.03
    for j in result.joints:
        assert 15 <= j.torque["samples"] <= 21  # 200 cycles, one in ten
        assert j.tracking is not None and 15 <= j.tracking["samples"] <= 21
        # a joint's CTRL_TPDO1 and CTRL_TPDO2 go in one cycle: its measured torque is
        # scored against the desired torque of the same sample
        assert not math.isnan(j.tracking["rms_error_measured"])
    phases = {f.offset_cycles for f in telemetry.values()}
    assert phases == {0, 1}  # A's frames in cycle 0 of ten, B's in cycle 1


FD = Path(__file__).parent / "data" / "rig-fd.toml"


@pytest.mark.slow
def test_an_fd_bus_runs_with_packed_frames_at_the_planned_load(tmp_path: Path) -> None:
    """On a CAN FD bus the drives' sensor frames go in one FD frame and the commands in
    another (FD_DRIVE_TPDO1, FD_DRIVE_RPDO1, bit-rate switching), the telemetry as FD
    frames; both joints run and are scored; the trace decodes every joint's signals from
    the packed frame by name, and its worst-case load of the planned frames (hdhil dump
    --stats, FD phases at their bit rates) is the planner's."""
    from hdhil.analysis.rigplan import plan_scenario
    from hdhil.can.traces.reader import read_trace
    from hdhil.can.traces.stats import StatsAccumulator
    from hdhil.canopen.mapping import trace_decoder

    request = resolve(FD, duration_s=0.2, seed=2, evaluate_from_s=0.0)
    trace = tmp_path / "fd.blf"
    result = run_rig(request, trace=trace, start_time=1.7e9)
    assert result.verdict is None
    for j in result.joints:
        assert j.drive_state == "OPERATION_ENABLED" and j.samples == 200
        assert 15 <= j.torque["samples"] <= 21 and j.tracking["samples"] >= 15
    plan = plan_scenario(request.scenario).buses[0]
    planned = {t.frame.can_id: t.frame for t in plan.frames}
    decoder = trace_decoder(trace)
    stats = StatsAccumulator(decoder=decoder)
    seen: dict[str, int] = {}
    with read_trace(trace) as frames:
        for msg in frames:
            frame = decoder.classify(msg)
            stats.add(frame)
            if msg.channel != 0:
                continue
            seen[frame.message or "?"] = seen.get(frame.message or "?", 0) + 1
            if frame.message == "FD_DRIVE_TPDO1":
                assert msg.is_fd and msg.bitrate_switch and len(msg.data) == 16
                assert {"A_ADC_torque", "B_ENC_count"} <= set(frame.signals)
            if frame.message is not None and "CTRL_TPDO" in frame.message:
                assert msg.is_fd and msg.bitrate_switch
    assert seen["FD_DRIVE_TPDO1"] >= 200 and seen["FD_DRIVE_RPDO1"] >= 200
    assert "?" not in seen and not [n for n in seen if n.endswith("DRIVE_TPDO1") and "FD" not in n]
    ids = stats.result()["ids"]
    measured = sum(e["load_percent"] for e in ids if e["bus"] == "fd0" and e["id"] in planned)
    assert measured == pytest.approx(plan.load * 100, abs=0.2)
    assert plan.load < result.buses["fd0"]["worst_case_load"] < plan.load + 0.03
    # the truth channel carries every joint's truth, more than a bus could: no budget
    truth = stats.result()["buses"]["truth"]
    assert truth["load_percent"] > 60 and not truth["over_limit"]
    text = format_rig_result(result)
    assert "FD_DRIVE_TPDO1" in text
    # the candidate filters read each joint's own sensor frame: not on a packing FD bus
    assert "candidate filters not evaluated: an FD bus packs" in text
    assert all(j.evaluation is None for j in result.joints)
    from hdhil.rig.trace_score import score_rig_trace

    ev, _ = score_rig_trace(trace, request)
    assert ev["buses"]["fd0"]["fd"] and all(j["evaluation"] is None for j in ev["joints"])
