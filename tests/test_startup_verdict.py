"""A start-up that fails is a stop, told as a verdict (which node, phase, why) with exit
code 1; only the user's own input (a DCF value the drive refuses) is an input error, 2."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from hdhil.analysis.soak import run_soak
from hdhil.cli import main
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.request import resolve


def _dcf(tmp_path: Path, values: dict[str, str]) -> Path:
    from tests.test_drive_dcf import _dcf as make

    return make(tmp_path, values)


@pytest.mark.slow
def test_run_that_never_reaches_operation_is_a_verdict(tmp_path, capsys):
    trace = tmp_path / "lossy.blf"
    code = main(["run", "--duration", "1", "--fault", "control.loss_rate=0.99", "--json",
                 "--trace", str(trace)])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 1
    verdict = json.loads(captured.out)["verdict"]
    assert verdict["phase"] == "start-up" and verdict["node"] == 2
    assert "did not reach operation enabled" in verdict["reason"]
    assert verdict["startup_cycles"] >= 500 and verdict["cycles_planned"] == 1000
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("hdhil: run stopped in start-up")
    assert "by node 2" in lines[0] and "Traceback" not in captured.err
    assert trace.exists()  # what happened is kept


def test_run_text_output_names_the_start_up_verdict(capsys):
    code = main(["run", "--duration", "1", "--fault", "control.loss_rate=0.99", "--trace", ""])
    out = capsys.readouterr().out
    assert code == 1
    assert "verdict            stopped in start-up" in out


@pytest.mark.realtime
def test_firmware_without_a_drive_is_a_verdict(capsys):
    channel = f"hdhil-nodrive-{time.monotonic_ns()}"
    code = main(["firmware", "--interface", "virtual", "--channel", channel,
                 "--boot-timeout", "0.2", "--duration", "0.3"])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 1
    summary = json.loads(captured.out.strip().splitlines()[-1])
    verdict = summary["verdict"]
    assert verdict["phase"] == "start-up" and verdict["node"] == 2
    assert "sent no boot-up within 0.2 s" in verdict["reason"]
    assert captured.err.startswith("hdhil: firmware stopped in start-up")


@pytest.mark.realtime
def test_a_dcf_value_the_drive_refuses_is_an_input_error(tmp_path, serve_drive, capsys):
    dcf = _dcf(tmp_path, {"1800sub2": "245"})  # reserved transmission type
    _drive, bus_args = serve_drive(
        lambda bus: DriveNode(bus, Plant(PlantConfig()), DriveConfig())
    )  # fmt: skip
    code = main(["firmware", *bus_args, "--lockstep", "--duration", "0.2", "--drive-dcf", str(dcf)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("hdhil: error:") and "0x1800:02" in err and "0x06090030" in err


def test_soak_that_never_starts_fails_with_the_reason():
    request = resolve("free-motion", faults=["control.loss_rate=0.99"], duration_s=1.0)
    report = run_soak(request, block_s=0.5)
    assert not report.passed
    text = json.dumps(report.as_dict())
    assert "stopped in start-up" in text and "did not reach operation enabled" in text
