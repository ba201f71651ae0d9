"""The one-node-per-process library (:mod:`hdhil.rig.standalone`) called directly, without
argparse: the drive and the controller on one virtual bus, a controller whose drive never
boots, the logger's recording and sidecar, and the faults a process refuses; each checked
against what ``hdhil emulate``/``firmware``/``log`` print or write."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Callable

import can
import pytest

from hdhil.can.traces.sidecar import read_metadata
from hdhil.canopen.cia402 import State
from hdhil.cli import main
from hdhil.core.dataconf import ConfigError
from hdhil.core.faultbase import FaultLog
from hdhil.rig.faults import FaultConfig, FaultInjector
from hdhil.rig.request import resolve
from hdhil.rig.standalone import (
    StandaloneController,
    StandaloneDrive,
    controller_faults,
    drive_faults,
    log_metadata,
    record,
)


def _channel(name: str) -> str:
    return f"hdhil-standalone-{name}-{time.monotonic_ns()}"


def _no_faults() -> FaultInjector:
    return FaultInjector(FaultConfig(), FaultLog(None, keep=False), stream="test")


@pytest.mark.realtime
def test_drive_and_controller_on_one_bus_run_the_request(capsys):
    request = resolve("free-motion", duration_s=0.05)
    channel = _channel("pair")
    drive_bus = can.Bus(interface="virtual", channel=channel)
    ctrl_bus = can.Bus(interface="virtual", channel=channel)
    drive = StandaloneDrive(request, drive_bus, None, _no_faults())
    stop_drive = threading.Event()
    served = threading.Thread(target=drive.serve, args=(stop_drive.is_set,), daemon=True)
    served.start()
    try:
        ctrl = StandaloneController(request, ctrl_bus, _no_faults(), boot_timeout_s=2.0)
        assert ctrl.boot(lambda: False) is None
        assert ctrl.run(lambda: False) == request.cycles
        summary = ctrl.summary(stopped=False)
    finally:
        stop_drive.set()
        served.join(5)
        ctrl_bus.shutdown()
    drive_summary = drive.summary()
    drive_bus.shutdown()
    assert summary["node"] == "controller" and "verdict" not in summary
    assert summary["operational_cycles"] == request.cycles
    assert summary["phase"] == "stopped" and summary["syncs_sent"] >= request.cycles
    assert drive_summary["node"] == "drive" and drive_summary["syncs"] >= request.cycles
    assert drive_summary["nmt_state"] in ("OPERATIONAL", "PRE-OPERATIONAL", "STOPPED")
    assert drive_summary["drive_state"] in State.__members__

    # `hdhil firmware` against a drive served the same way prints the same summary
    channel = _channel("cmd")
    cmd_drive_bus = can.Bus(interface="virtual", channel=channel)
    cmd_drive = StandaloneDrive(request, cmd_drive_bus, None, _no_faults())
    stop_drive.clear()
    served = threading.Thread(target=cmd_drive.serve, args=(stop_drive.is_set,), daemon=True)
    served.start()
    try:
        code = main(["firmware", "--interface", "virtual", "--channel", channel,
                     "--lockstep", "--duration", "0.05"])  # fmt: skip
    finally:
        stop_drive.set()
        served.join(5)
        cmd_drive_bus.shutdown()
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0
    assert printed.keys() == summary.keys()
    for key in ("node", "operational_cycles", "phase", "mapping", "faults"):
        assert printed[key] == json.loads(json.dumps(summary[key])), key


def test_the_drive_summary_has_plain_state_names():
    """``hdhil emulate``'s JSON: the CiA 402 state and the NMT state by name, as a script
    compares them ("FAULT", "PRE-OPERATIONAL"), not as Python reprs or heartbeat codes."""
    request = resolve("free-motion", duration_s=0.05)
    bus = can.Bus(interface="virtual", channel=_channel("names"))
    try:
        drive = StandaloneDrive(request, bus, None, _no_faults())
        drive.node.boot(time.monotonic())
        booted = json.loads(json.dumps(drive.summary()))
        drive.node.state_machine.fault(0x8100)
        faulted = json.loads(json.dumps(drive.summary()))
    finally:
        bus.shutdown()
    assert booted["nmt_state"] == "PRE-OPERATIONAL"
    assert booted["drive_state"] == "SWITCH_ON_DISABLED" and "verdict" not in booted
    assert faulted["drive_state"] == "FAULT" and faulted["verdict"]["phase"] == "fault"
    assert faulted["nmt_state"] == "PRE-OPERATIONAL"


def test_firmware_paces_in_real_time_unless_lockstep_is_asked_for():
    """``hdhil firmware``'s pacing options: real time by default (``--realtime`` kept as a
    no-op), network lockstep only with ``--lockstep``, never both."""
    from hdhil.cli import build_parser

    parser = build_parser(["firmware"])
    assert parser.parse_args(["firmware"]).lockstep is False
    assert parser.parse_args(["firmware", "--realtime"]).lockstep is False
    assert parser.parse_args(["firmware", "--lockstep"]).lockstep is True
    assert main(["firmware", "--lockstep", "--realtime"]) == 2
    help_text = " ".join(parser._subparsers._group_actions[0].choices["firmware"]
                         .format_help().split())  # fmt: skip
    assert "NEVER with a motor" in help_text and "no effect" in help_text


def _when_stopping_on_signals(action: Callable[[], None]) -> threading.Thread:
    """Run ``action`` once this process's SIGTERM handler is the command's stop request
    (:func:`hdhil.core.signals.stop_on_signals`), i.e. once the command is in its loop."""

    def wait() -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            handler = signal.getsignal(signal.SIGTERM)
            if "stop_on_signals" in getattr(handler, "__qualname__", ""):
                action()
                return
            time.sleep(0.005)

    thread = threading.Thread(target=wait, daemon=True)
    thread.start()
    return thread


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.parametrize("command", ["emulate", "log"])
def test_emulate_and_log_stopped_by_sigterm_exit_0(command, tmp_path, capsys):
    """A server ended by Ctrl-C or SIGTERM after a clean stop exits 0 with its summary,
    as python-can's can.logger does (130 stays for interrupted work)."""
    bus = ["--interface", "virtual", "--channel", _channel(command)]
    argv = [command, *bus, "--duration", "30"]
    if command == "log":
        argv.append(str(tmp_path / "stopped.blf"))
    sender = _when_stopping_on_signals(lambda: os.kill(os.getpid(), signal.SIGTERM))
    t0 = time.monotonic()
    code = main(argv)
    sender.join(5)
    assert code == 0 and time.monotonic() - t0 < 20
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    if command == "log":
        assert printed["frames"] == 0 and (tmp_path / "stopped.blf").is_file()
    else:
        assert printed["drive_state"] == "SWITCH_ON_DISABLED" and "verdict" not in printed


@pytest.mark.realtime
def test_controller_without_a_drive_gives_the_start_up_verdict_the_command_prints(capsys):
    request = resolve("free-motion", duration_s=0.3)
    bus = can.Bus(interface="virtual", channel=_channel("nodrive"))
    try:
        ctrl = StandaloneController(request, bus, _no_faults(), boot_timeout_s=0.2)
        failed = ctrl.boot(lambda: False)
    finally:
        bus.shutdown()
    assert failed is not None
    verdict = failed["verdict"]
    assert verdict["phase"] == "start-up" and verdict["node"] == 2
    assert "sent no boot-up within 0.2 s" in verdict["reason"]

    code = main(["firmware", "--interface", "virtual", "--channel", _channel("nodrive-cmd"),
                 "--boot-timeout", "0.2", "--duration", "0.3"])  # fmt: skip
    captured = capsys.readouterr()
    printed = json.loads(captured.out.strip().splitlines()[-1])
    assert code == 1
    assert printed.keys() == failed.keys()
    assert printed["verdict"] == json.loads(json.dumps(verdict))
    assert captured.err.startswith("hdhil: firmware stopped in start-up")


@pytest.mark.realtime
def test_record_writes_the_frames_and_the_sidecar(tmp_path):
    channel = _channel("log")
    control = can.Bus(interface="virtual", channel=channel)
    sender = can.Bus(interface="virtual", channel=channel)
    for i in range(10):
        sender.send(can.Message(arbitration_id=0x181, data=bytes([i] * 8), is_extended_id=False))
    request = resolve("free-motion")
    metadata = log_metadata({"interface": "virtual", "channel": channel, "bitrate": 1000}, request)
    trace = tmp_path / "log.blf"
    try:
        recording = record(trace, control, None, metadata, lambda: False, duration_s=0.3)
    finally:
        sender.shutdown()
        control.shutdown()
    assert recording.frames == 10 and not recording.stopped
    assert trace.exists()
    assert read_metadata(trace) == json.loads(json.dumps(metadata))
    assert metadata["recorded_by"] == "hdhil log" and metadata["scenario"] == "free-motion"
    assert metadata["seed"] == request.seed and metadata["channel"] == channel

    stopped = record(tmp_path / "stop.blf", can.Bus(interface="virtual", channel=_channel("s")),
                     None, log_metadata({}, None), lambda: True)  # fmt: skip
    assert stopped == type(recording)(0, True)


@pytest.mark.realtime
def test_log_metadata_is_the_sidecar_hdhil_log_writes(tmp_path, capsys):
    channel = _channel("logcmd")
    trace = tmp_path / "cmd.blf"
    bus = ["--interface", "virtual", "--channel", channel, "--bitrate", "500000"]
    run = ["--scenario", "free-motion", "--seed", "7"]
    code = main(["log", *bus, str(trace), "--duration", "0.1", *run])
    assert code == 0
    assert json.loads(capsys.readouterr().out) == {"trace": str(trace), "frames": 0}
    expected = log_metadata(
        {"interface": "virtual", "channel": channel, "bitrate": 500000},
        resolve("free-motion", seed=7),
    )
    assert read_metadata(trace) == json.loads(json.dumps(expected))
    assert log_metadata({}, None).keys() == {
        "recorded_by", "interface", "channel", "bitrate", "channels", "time_offset_s"
    }  # fmt: skip


def test_a_process_refuses_faults_that_do_not_act_in_it(tmp_path):
    request = resolve("free-motion")
    with pytest.raises(ConfigError, match=r"--fault truth\.\*: these faults do not act in "
                       r"hdhil firmware \(it injects control\)"):  # fmt: skip
        controller_faults(request, ["truth.loss_rate=0.1"], None)
    with pytest.raises(ConfigError, match=r"do not act in hdhil emulate \(it injects sensors, "
                       r"control\)"):  # fmt: skip
        drive_faults(request, ["truth.loss_rate=0.1"], None, truth=False)
    injector = drive_faults(request, ["seed=3"], tmp_path / "faults.jsonl", truth=True)
    injector.log.close()
    assert (tmp_path / "faults.jsonl").exists()


@pytest.mark.slow
@pytest.mark.realtime
def test_log_records_each_bus_its_own_frames(tmp_path):
    """python-can's udp_multicast hands every group joined on the host's port to each
    socket, so the control bus also receives the truth frames and the truth bus the
    control frames; `hdhil log` (`record`) keeps each bus's own frames only."""
    from hdhil.dbc import codec
    from hdhil.rig.standalone import record

    stamp = time.monotonic_ns()
    control = can.Bus(interface="virtual", channel=f"c{stamp}")
    truth = can.Bus(interface="virtual", channel=f"t{stamp}")
    to_control = can.Bus(interface="virtual", channel=f"c{stamp}")
    to_truth = can.Bus(interface="virtual", channel=f"t{stamp}")
    sync = can.Message(arbitration_id=0x080, data=b"\x01", is_extended_id=False)
    torque = codec("truth", "TRUTH_TORQUE")
    true = can.Message(arbitration_id=torque.frame_id, data=bytes(8), is_extended_id=True)
    for bus in (to_control, to_truth):  # each frame on both buses, as udp_multicast does
        bus.send(sync)
        bus.send(true)
    trace = tmp_path / "own.blf"
    try:
        record(trace, control, truth, {}, lambda: False, duration_s=0.3)
    finally:
        for bus in (control, truth, to_control, to_truth):
            bus.shutdown()
    with can.LogReader(str(trace)) as reader:
        got = sorted((m.channel, m.arbitration_id) for m in reader)
    assert got == [(0, 0x080), (1, torque.frame_id)]
