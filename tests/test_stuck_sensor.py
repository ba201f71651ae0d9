"""Stuck torque channel: the firmware notices a reading that stops changing while the
motor turns, announces it by EMCY 0x7300 and counts it; clean runs never trip it."""

from __future__ import annotations

import dataclasses

import pytest

from hdhil.can.faults import with_fault_flags
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.stages import StuckChannels
from hdhil.hostsim.scenario import load_scenario
from hdhil.rig.runner import run_lockstep

CPR = FirmwareConfig().calibration.encoder_counts_per_rev


def _feed(check: StuckChannels, n: int, torque: float, counts_per_sample: int,
          volts: float = 1.0, start: int = 0) -> int:  # fmt: skip
    enc = start
    for _ in range(n):
        check.step(torque, 100.0, enc & 0xFFFF, volts, 0.0)
        enc += counts_per_sample
    return enc


def test_a_constant_reading_while_turning_is_stuck() -> None:
    check = StuckChannels(samples=100, motion_rad=2.0, counts_per_rev=CPR)
    enc = _feed(check, 100, 1.25, 30)  # 100 equal readings: 99 repeats, not yet
    assert not check.torque_stuck
    enc = _feed(check, 2, 1.25, 30, start=enc)  # 2 rad = 2546 counts: moved 3030
    assert check.torque_stuck and check.events == 1 and check.revision == 1
    _feed(check, 1, 1.30, 30, start=enc)  # it reads again: the flag falls
    assert not check.torque_stuck and check.events == 1 and check.revision == 2


@pytest.mark.parametrize(
    ("counts_per_sample", "volts"),
    [(0, 1.0), (1, 1.0), (20, 10.0), (20, -10.0)],  # standing still, creeping, saturated
)
def test_standing_still_or_saturated_is_not_stuck(counts_per_sample: int, volts: float) -> None:
    check = StuckChannels(samples=100, motion_rad=2.0, counts_per_rev=CPR)
    _feed(check, 500, 1.25, counts_per_sample, volts)
    assert not check.torque_stuck and check.events == 0


def test_the_encoder_wrap_counts_as_motion() -> None:
    check = StuckChannels(samples=100, motion_rad=2.0, counts_per_rev=CPR)
    _feed(check, 200, 1.25, -30, start=100)  # backwards through 0 -> 65535
    assert check.torque_stuck


def test_a_stuck_torque_sensor_in_a_run_raises_emcy_0x7300() -> None:
    scenario = load_scenario("free-motion")
    flags = ["sensors.stuck=[{channel='torque',start_s=1.0,duration_s=0.3}]"]
    stuck = dataclasses.replace(scenario, faults=with_fault_flags(scenario.faults, flags))
    result = run_lockstep(stuck, 2.0, evaluate=False)
    assert result.faults and result.faults["stuck"] > 0
    assert result.controller["stuck_sensor_events"] == 1
    assert result.frames.get("control 0x081 EMCY_CTRL", 0) >= 2  # raised, then cleared
    clean = run_lockstep(scenario, 2.0, evaluate=False)
    assert clean.controller["stuck_sensor_events"] == 0
