"""Faults that do what they say: delay and jitter act through the simulated bus's timing,
a silenced node sends nothing at all, truth faults reach the evaluation, and faults act
(or are refused) on every interface ``hdhil run`` opens.

Every check reads what happened from the run's own trace with python-can's reader, or
from the nodes' counters, never from the fault configuration.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import subprocess
import sys

import can
import pytest
from runs import lockstep
from test_multiprocess import GROUP_CONTROL, _hdhil

from hdhil.can.faults import FaultyTransmitBus
from hdhil.can.simbus import SimClock
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.dbc import database, node_ids
from hdhil.rig.faults import FaultConfig, FaultInjector, with_fault_flags
from hdhil.rig.scenario import load_scenario

TS = 1e-3
_names = itertools.count()


def _scenario(*flags: str, name: str = "free-motion"):
    sc = load_scenario(name)
    return dataclasses.replace(sc, faults=with_fault_flags(sc.faults, list(flags)))


def _run(tmp_path, *flags: str, duration: float = 0.6, **kwargs):
    """A free-motion run with ``flags`` as --fault flags; its trace (simulated time, start
    time 0) read back with python-can's BLF reader."""
    trace = tmp_path / f"run{next(_names)}.blf"
    controller = {}

    def keep(node):  # the controller, for its counters after the run
        controller["node"] = node

    result = lockstep(_scenario(*flags), duration_s=duration, trace=trace, start_time=0.0,
                          monitor=keep, monitor_every=1, **kwargs)  # fmt: skip
    with can.BLFReader(trace) as reader:
        frames = list(reader)
    return result, frames, controller.get("node")


def _senders() -> dict[int, set[str]]:
    """control.dbc: which nodes transmit each identifier."""
    return {m.frame_id: set(m.senders) for m in database("control").messages}


# --------------------------------------------------------------- delay and jitter
def test_a_delayed_frame_is_receivable_only_when_the_clock_reaches_it():
    inj = FaultInjector(from_dict(FaultConfig, {"control": {"delay_us": 1500.0}}))
    clock = SimClock()
    name = f"t-timing-{next(_names)}"
    tx = can.Bus(interface="simbus", channel=name, clock=clock, faults=inj.channel("control"))
    rx = can.Bus(interface="simbus", channel=name)
    try:
        got: list[tuple[int, float]] = []
        for k in range(6):
            clock.now, clock.horizon = k * TS, (k + 1) * TS
            if k == 0:
                tx.send(can.Message(arbitration_id=0x182, is_extended_id=False, data=b"\x01"))
            while (m := rx.recv(0)) is not None:
                got.append((k, m.timestamp))
        # On the wire 0..~50 us, then 1.5 ms late: receivable in the step of 1.5 ms
        # (cycle 1), stamped with its delivery time, not before.
        assert len(got) == 1
        k, t = got[0]
        assert k == 1 and 1.5e-3 < t < 1.6e-3
        assert clock.now == 5 * TS  # nobody's clock was stretched
    finally:
        tx.shutdown()
        rx.shutdown()


def test_a_node_answers_a_delayed_frame_at_the_time_it_received_that_frame():
    """Two delayed frames come due in one step; the receiver answers the first at its
    receive time, not at the second's (a bus attached before the faults were set takes
    the fault-aware path too)."""
    inj = FaultInjector(from_dict(FaultConfig, {"control": {"delay_us": 300.0}}))
    clock = SimClock(horizon=TS)
    name = f"t-timing-{next(_names)}"
    rx = can.Bus(interface="simbus", channel=name, clock=clock)  # before the faults
    tx = can.Bus(interface="simbus", channel=name, clock=clock, faults=inj.channel("control"))
    try:
        for fid in (0x100, 0x101):
            tx.send(can.Message(arbitration_id=fid, is_extended_id=False, data=bytes(8)))
        seen = []

        def answer(msg: can.Message) -> None:
            seen.append(msg)
            if msg.arbitration_id == 0x100:
                rx.send(can.Message(arbitration_id=0x200, is_extended_id=False, data=b"\x01"))

        rx.dispatch(answer)
        a, b = seen
        reply = tx.recv(0)
        assert reply is not None and reply.arbitration_id == 0x200
        assert a.timestamp < b.timestamp < TS
        # The wire is free when 0x100 arrives; the reply goes on it then (a 1-byte frame
        # takes at most 65 us at 1 Mbit/s) and arrives 300 us after its end: not started
        # at 0x101's receive time.
        sent_for = reply.timestamp - 300e-6
        assert 0 < sent_for - a.timestamp <= 65e-6
        assert sent_for < b.timestamp
    finally:
        tx.shutdown()
        rx.shutdown()


@pytest.mark.slow
def test_jitter_of_200us_changes_receive_times_but_stays_within_the_cycle(tmp_path):
    clean, clean_frames, _ = _run(tmp_path)
    jit, jit_frames, _ = _run(tmp_path, "control.jitter_us=200")
    assert jit.faults["delay"] > 0
    control = [(m.arbitration_id, bytes(m.data)) for m in clean_frames if m.channel == 0]
    # The same frames in the same cycles (200 us never reaches the next SYNC here), but
    # received later: the receive times moved.
    shifted = [m.timestamp for m in jit_frames if m.channel == 0]
    plain = [m.timestamp for m in clean_frames if m.channel == 0]
    assert len(shifted) == len(plain) == len(control)
    assert sum(a != b for a, b in zip(shifted, plain, strict=True)) > 0.9 * len(plain)
    assert jit.simulated_s == clean.simulated_s == 0.6


@pytest.mark.slow
def test_frames_delayed_past_the_next_sync_arrive_a_cycle_late_and_are_counted(tmp_path):
    _, clean_frames, _ = _run(tmp_path)
    late, frames, ctrl = _run(tmp_path, "control.jitter_us=800", duration=1.0)
    assert late.verdict is None and late.cycles == 1000 and late.simulated_s == 1.0
    # Simulated time stays simulated time: the trace spans the cycles the controller
    # started (one SYNC each, until it stopped sending them) plus at most the longest
    # delay, not a stretched clock.  A cycle whose sensor frame came late has no sample,
    # so the run has more cycles than samples, as under frame loss.
    span = frames[-1].timestamp
    syncs = late.controller["syncs_sent"]
    assert syncs > late.cycles
    assert span < (syncs + late.startup_cycles + 5) * TS
    # Per controller cycle [k Ts, (k+1) Ts): drive sensor frames (0x182) received.
    sensor = 0x180 + node_ids("control")["DRIVE"]
    per_cycle: dict[int, int] = {}
    for m in frames:
        if m.channel == 0 and m.arbitration_id == sensor:
            k = math.floor(m.timestamp / TS)
            per_cycle[k] = per_cycle.get(k, 0) + 1
    first, last = min(per_cycle), max(per_cycle)
    empty = sum(per_cycle.get(k, 0) == 0 for k in range(first, last + 1))
    doubled = sum(n >= 2 for n in per_cycle.values())
    assert empty > 50 and doubled > 50  # late frames land in the next cycle
    d = ctrl.diagnostics
    # The controller counts a cycle without its sensor frame, and a second one in a cycle.
    assert d.sensor_frames_missed > 50 and d.extra_sensor_frames > 0
    assert d.sensor_frames_missed <= empty
    # The clean run has neither.
    clean_k = [math.floor(m.timestamp / TS) for m in clean_frames
               if m.channel == 0 and m.arbitration_id == sensor]  # fmt: skip
    assert len(clean_k) == len(set(clean_k))


@pytest.mark.slow
def test_a_5ms_delay_keeps_the_run_in_simulated_time(tmp_path):
    r, frames, _ = _run(tmp_path, "control.delay_us=5000", duration=1.0)
    assert r.verdict is None and r.cycles == 1000
    # Every frame is received 5 ms after its transmission; the cycles go on at 1 ms.
    assert frames[-1].timestamp < (r.controller["syncs_sent"] + r.startup_cycles + 10) * TS
    assert frames[-1].timestamp < 1.6  # was 6.5x the run's length before


# --------------------------------------------------------------- silence by sender
def test_a_silenced_controller_sends_no_frame_of_any_identifier(tmp_path):
    start = 0.3
    r, frames, _ = _run(tmp_path, f"control.silence=[{{node=1,start_s={start}}}]")
    senders = _senders()
    # The window in trace time: simulated time (start time 0) from start_s on.
    window = [m for m in frames if m.channel == 0 and m.timestamp >= start + 1e-4]
    before = [m for m in frames if m.channel == 0 and m.timestamp < start]
    assert any("CONTROLLER" in senders.get(m.arbitration_id, ()) for m in before)
    assert window, "the drive keeps transmitting (heartbeats) in the window"
    from_controller = [hex(m.arbitration_id) for m in window
                       if "DRIVE" not in senders.get(m.arbitration_id, ())]  # fmt: skip
    assert from_controller == []
    # The controller kept trying: its SYNCs and heartbeats are logged as silenced.
    assert r.faults["silence"] > 0
    # Without SYNC the drive sends no sensor frame: the controller stops with a reason.
    assert r.verdict is not None and "sensor frame" in r.verdict["reason"]


def test_silence_by_sender_and_by_identifier_on_a_node_process_bus():
    inj = FaultInjector(from_dict(FaultConfig, {"control": {"silence": [
        {"node": 1, "start_s": 0.0}, {"ids": [0x702], "start_s": 0.0}]}}))  # fmt: skip
    name = f"t-timing-{next(_names)}"
    a = can.Bus(interface="virtual", channel=name)
    b = can.Bus(interface="virtual", channel=name)
    ctrl = FaultyTransmitBus(a, inj.channel("control"), clock=lambda: 1.0, node_id=1)
    try:
        for fid in (0x000, 0x080, 0x202, 0x601, 0x701):  # NMT, SYNC, RPDO, SDO, heartbeat
            ctrl.send(can.Message(arbitration_id=fid, is_extended_id=False, data=b"\x00"))
        assert b.recv(0.05) is None
        drive = FaultyTransmitBus(b, inj.channel("control"), clock=lambda: 1.0, node_id=2)
        drive.send(can.Message(arbitration_id=0x182, is_extended_id=False, data=b"\x01"))
        drive.send(can.Message(arbitration_id=0x702, is_extended_id=False, data=b"\x05"))
        got = a.recv(0.5)
        assert got is not None and got.arbitration_id == 0x182
        assert a.recv(0.05) is None  # 0x702 listed by identifier
        assert inj.summary() == {"silence": 6}
    finally:
        a.shutdown()
        b.shutdown()


# --------------------------------------------------------------- truth faults
@pytest.mark.slow
def test_truth_silence_removes_truth_and_the_evaluation_says_so(tmp_path):
    start = 0.4
    skip = 0.3
    r, frames, _ = _run(tmp_path, f"truth.silence=[{{node=2,start_s={start}}}]",
                        evaluate_skip_s=skip)  # fmt: skip
    truth = [m for m in frames if m.channel == 1]
    assert truth and max(m.timestamp for m in truth) < start
    assert r.faults["silence"] > 0 and r.verdict is None
    ev = r.evaluation
    missing = ev["samples_without_truth"]
    # Rows after the 0.3 s skip: with truth until 0.4 s, none after.
    assert 80 <= ev["samples"] <= 110 and missing >= 150
    clean, _, _ = _run(tmp_path, evaluate_skip_s=skip)
    assert "samples_without_truth" not in clean.evaluation
    assert ev["samples"] + missing == clean.evaluation["samples"]
    # The live score pairs each truth frame with one telemetry frame only.
    assert r.torque["samples"] < 0.75 * clean.torque["samples"]


def test_truth_silenced_from_the_start_leaves_nothing_to_score(tmp_path):
    r, frames, _ = _run(tmp_path, "truth.silence=[{node=2,start_s=0}]")
    assert not [m for m in frames if m.channel == 1]
    assert r.evaluation["samples"] == 0 and r.evaluation["samples_without_truth"] > 500
    assert r.torque["samples"] == 0


# --------------------------------------------------------------- other interfaces
def test_run_on_the_virtual_bus_injects_control_faults(tmp_path):
    trace = tmp_path / "virtual.blf"
    r = lockstep(
        _scenario("control.duplicate_rate=0.05"), duration_s=0.3, trace=trace,
        interface="virtual", evaluate=False,
    )  # fmt: skip
    assert r.faults["duplicate"] > 5
    with can.BLFReader(trace) as reader:
        sync = [m for m in reader if m.channel == 0 and m.arbitration_id == 0x080]
    counters = [m.data[0] for m in sync]
    repeats = sum(a == b for a, b in itertools.pairwise(counters))
    assert repeats > 0  # the duplicated SYNCs are on the bus


@pytest.mark.slow
def test_run_on_the_virtual_bus_with_loss_goes_on_in_cycle_time():
    """5 % loss on the virtual bus: a dropped answer closes its cycle after a short wait
    and costs the nodes one cycle of their time (not half a second of their heartbeat
    timers), so the run goes on as on the simulated bus, or stops with the controller's
    own reason."""
    r = lockstep(_scenario("control.loss_rate=0.05", "seed=1"), duration_s=0.5,
                     interface="virtual", evaluate=False)  # fmt: skip
    assert r.faults["loss"] > 20
    assert r.verdict is None and r.cycles == 500
    # Cycles whose sensor frame or command was lost: more SYNCs than samples.
    assert r.controller["syncs_sent"] > r.cycles + r.startup_cycles
    assert r.wall_s < 20


def test_run_on_the_virtual_bus_refuses_what_a_node_cannot_inject():
    with pytest.raises(ConfigError, match="error_frame_rate"):
        lockstep(_scenario("control.error_frame_rate=0.1"), duration_s=0.1,
                     interface="virtual", evaluate=False)  # fmt: skip


@pytest.mark.slow
@pytest.mark.subprocess
def test_run_cli_on_virtual_refuses_error_frames_with_one_line():
    p = subprocess.run(
        [sys.executable, "-m", "hdhil", "run", "--interface", "virtual", "--duration", "0.1",
         "--fault", "control.error_frame_rate=0.1", "--trace", ""],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hdhil: error: ") and "error_frame" in lines[0]


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.netns
@pytest.mark.realtime
def test_run_over_udp_multicast_injects_faults_in_a_private_namespace(netns, tmp_path):
    """hdhil run --interface udp_multicast (inside the test's network namespace, loopback
    only): each node's frames go through the control faults; error frames are refused."""
    trace = tmp_path / "udp.blf"
    bus = ["--interface", "udp_multicast", "--channel", GROUP_CONTROL]
    p = _hdhil(netns, "run", *bus, "--duration", "0.3", "--json", "--no-evaluate",
               "--fault", "control.duplicate_rate=0.05", "--trace", str(trace))  # fmt: skip
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert json.loads(out)["faults"]["duplicate"] > 5
    with can.BLFReader(trace) as reader:
        counters = [m.data[0] for m in reader if m.channel == 0 and m.arbitration_id == 0x080]
    assert sum(a == b for a, b in itertools.pairwise(counters)) > 0
    p = _hdhil(netns, "run", *bus, "--duration", "0.1", "--fault",
               "control.error_frame_rate=0.1", "--trace", "")  # fmt: skip
    out, err = p.communicate(timeout=120)
    assert p.returncode == 2 and err.count("\n") == 1 and "error_frame_rate" in err


# --------------------------------------------------------------- late sensor frames
def test_a_late_sample_after_a_missed_period_passes_the_encoder_check():
    """The controller counted a period as missed, then the late frame of that period came
    (one period's increment; it ran the interrupt on it and skipped the period's own
    frame), then the next sample two periods on: neither increment is an encoder glitch,
    and a glitch still is one."""
    from hdhil.firmware.config import PlausibilityConfig
    from hdhil.firmware.stages import SensorPlausibility

    cpr, v = 8000, 150.0  # rad/s: 191 counts a period, far beyond the 20-count tolerance
    per = v * 1e-3 * cpr / (2 * math.pi)
    check = SensorPlausibility(PlausibilityConfig(), 1e-3, cpr, check_encoder=True)
    counts = [round(k * per) & 0xFFFF for k in range(12)]
    for k in (0, 1, 2, 3):
        check.step(v, counts[k])
    check.missed()  # period 4: no frame in its cycle
    _, c4 = check.step(v, counts[4])  # ... it came late, in period 5's cycle
    late_rejected = check.rejected
    _, c6 = check.step(v, counts[6])  # period 5's frame was skipped as the second
    assert (late_rejected, check.rejected) == (False, False)
    assert (c4, c6) == (counts[4], counts[6])  # no offset added
    _, c7 = check.step(v, counts[7])  # in step again: one period
    assert not check.rejected and c7 == counts[7]
    # Two periods without a gap or a late sample before: a glitch (replaced).
    check.step(v, counts[9])
    assert check.rejected
    # After a missed period, 200 counts more than two periods' increment: a glitch.
    check = SensorPlausibility(PlausibilityConfig(), 1e-3, cpr, check_encoder=True)
    for k in (0, 1, 2):
        check.step(v, counts[k])
    check.missed()
    check.step(v, (counts[4] + 200) & 0xFFFF)
    assert check.rejected


@pytest.mark.slow
def test_reordered_sensor_frames_reach_the_controller_late_without_encoder_rejections(tmp_path):
    r, frames, ctrl = _run(tmp_path, "control.reorder_rate=0.01", "seed=0", duration=1.0)
    d = ctrl.diagnostics
    assert r.faults["reorder"] > 20 and r.verdict is None
    late = [m for m in frames if m.channel == 0 and m.arbitration_id == 0x182]
    assert d.extra_sensor_frames > 3 and d.sensor_frames_missed > 3  # late frames
    assert r.controller["encoder_rejections"] == 0 and r.controller["kalman_skipped"] == 0
    assert len(late) > 1000
