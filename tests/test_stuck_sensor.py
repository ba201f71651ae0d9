"""Stuck torque and tacho channels: the firmware notices a reading that stops changing
while the motor turns, announces it by EMCY (torque 0x7300, tacho 0x7301) and counts it;
clean runs never trip it."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
from canopen.emcy import EMCY_STRUCT
from conftest import FrameRecorder
from runs import lockstep

from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.stages import StuckChannels
from hdhil.rig.faults import with_fault_flags
from hdhil.rig.scenario import load_scenario

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


@pytest.mark.slow
def test_a_stuck_torque_sensor_in_a_run_raises_emcy_0x7300() -> None:
    scenario = load_scenario("free-motion")
    flags = ["sensors.stuck=[{channel='torque',start_s=1.0,duration_s=0.3}]"]
    stuck = dataclasses.replace(scenario, faults=with_fault_flags(scenario.faults, flags))
    result = lockstep(stuck, 2.0, evaluate=False)
    assert result.faults and result.faults["stuck"] > 0
    assert result.controller["stuck_sensor_events"] == 1
    assert result.frames.get("control 0x081 EMCY_CTRL", 0) >= 2  # raised, then cleared
    clean = lockstep(scenario, 2.0, evaluate=False)
    assert clean.controller["stuck_sensor_events"] == 0


# ------------------------------------------------------------------------ stuck tacho
TS = 1e-3
RAD_PER_COUNT = 2 * math.pi / CPR


def _tacho(check: StuckChannels, n: int, reading: float, counts_per_sample: int,
           start: int = 0, volts: float = 1.0) -> int:  # fmt: skip
    """``n`` samples of a constant tacho ``reading`` (rad/s) while the encoder moves
    ``counts_per_sample``; the torque reading changes every sample (not stuck)."""
    enc = start
    for k in range(n):
        check.step(0.001 * k, reading, enc & 0xFFFF, 1.0, volts)
        enc += counts_per_sample
    return enc


def _checker() -> StuckChannels:
    return StuckChannels(samples=100, motion_rad=2.0, counts_per_rev=CPR, sample_period_s=TS)


def test_a_tacho_reading_held_while_the_encoder_shows_another_speed_is_stuck() -> None:
    check = _checker()
    counts = 30  # 30 counts per ms: 23.6 rad/s
    _tacho(check, 150, 5.0, counts)  # the tacho says 5 rad/s
    assert check.tacho_stuck and not check.torque_stuck
    assert check.tacho_events == 1 and check.events == 1
    check.step(1.0, 23.5, 0, 1.0, 1.0)  # it reads again: the flag falls
    assert not check.tacho_stuck and check.tacho_events == 1


@pytest.mark.parametrize("counts", [30, -30, 200])
def test_a_constant_tacho_that_agrees_with_the_encoder_is_not_stuck(counts: int) -> None:
    """A steady speed: the reading may stay put for long (noise below one count)."""
    check = _checker()
    _tacho(check, 2000, counts * RAD_PER_COUNT / TS, counts, start=40_000)
    assert not check.tacho_stuck and check.tacho_events == 0


def test_standstill_and_saturation_never_make_a_stuck_tacho() -> None:
    check = _checker()
    _tacho(check, 1000, 50.0, 0)  # the encoder does not move: nothing to judge by
    _tacho(check, 1000, 50.0, 30, volts=9.995)  # at full scale: saturation, not stuck
    assert not check.tacho_stuck and check.tacho_events == 0


def test_lost_samples_count_as_time_for_the_encoder_velocity() -> None:
    """Every other sample lost: the encoder moves twice as far between the samples seen;
    with the gaps counted the velocities agree (no false alarm)."""
    check = _checker()
    v = 30 * RAD_PER_COUNT / TS
    enc = 0
    for k in range(2000):
        check.step(0.001 * k, v, enc & 0xFFFF, 1.0, 1.0)
        check.missed()
        enc += 60
    assert not check.tacho_stuck


@pytest.mark.slow
def test_a_stuck_tacho_in_a_run_raises_emcy_0x7301_and_counts() -> None:
    scenario = load_scenario("speed-chirp")  # the motor speed keeps changing
    flags = ["sensors.stuck=[{channel='tacho',start_s=1.0}]"]
    stuck = dataclasses.replace(scenario, faults=with_fault_flags(scenario.faults, flags))
    frames = FrameRecorder()
    result = lockstep(stuck, 3.0, evaluate=False, extra_listeners=[frames])
    emcys = [EMCY_STRUCT.unpack(bytes(m.data)) for m in frames.with_id(0x081, extended=False)]
    codes = [(code, manufacturer[0]) for code, _register, manufacturer in emcys]
    assert result.faults and result.faults["stuck"] > 0
    assert result.controller["stuck_tacho_events"] == 1
    assert result.controller["stuck_sensor_events"] == 1
    assert (0x7301, 2) in codes  # "tacho fault", channel 2 in manufacturer byte 0
    assert (0x7300, 1) not in codes  # the torque channel is fine


def test_no_stuck_channel_on_clean_runs_of_the_shipped_scenarios() -> None:
    """The golden summaries (every shipped scenario at its full duration, standstill
    phases included; ``tests/test_golden.py`` checks the runs still give them) count no
    stuck channel."""
    golden = json.loads((Path(__file__).parent / "data" / "golden.json").read_text())
    controllers = [s["controller"] for key, s in golden.items() if key.startswith("summary/")]
    assert len(controllers) >= 8
    for c in controllers:
        assert c["stuck_sensor_events"] == 0 and c["stuck_tacho_events"] == 0


class _LoopReference:
    """The check written as one loop over the channels (the form the stage's docstring
    describes), to hold the stage's unrolled step to it."""

    def __init__(self, samples: int, motion_rad: float, Ts: float | None) -> None:
        self.samples, self.Ts = samples, Ts
        self.needed = motion_rad * CPR / (2.0 * math.pi)
        self.last: list[float | None] = [None, None]
        self.run, self.moved = [0, 0], [0.0, 0.0]
        self.signed = self.periods = 0
        self.since, self.raw_last = 1, None
        self.flags, self.events, self.tacho_events, self.revision = [False, False], 0, 0, 0

    def missed(self) -> None:
        self.since += 1

    def step(self, torque: float, velocity: float, encoder: int, tq_V: float, ta_V: float):
        periods, self.since = self.since, 1
        raw = encoder & 0xFFFF
        signed = 0 if self.raw_last is None else ((raw - self.raw_last + 0x8000) & 0xFFFF) - 0x8000
        self.raw_last = raw
        channels = ((torque, tq_V), (velocity, ta_V)) if self.Ts else ((torque, tq_V),)
        for i, (value, volts) in enumerate(channels):
            if value != self.last[i] or abs(volts) >= 9.99:
                self.last[i], self.run[i], self.moved[i] = value, 0, 0.0
                if i == 1:
                    self.signed = self.periods = 0
                if self.flags[i]:
                    self.flags[i] = False
                    self.revision += 1
                continue
            self.run[i] += 1
            self.moved[i] += abs(signed)
            if i == 1:
                self.signed += signed
                self.periods += periods
            if self.flags[i] or self.run[i] < self.samples or self.moved[i] < self.needed:
                continue
            if i == 1:
                v_enc = self.signed * 2.0 * math.pi / CPR / (self.periods * self.Ts)
                if abs(v_enc - value) <= 2.0 + 0.05 * abs(v_enc):
                    continue
            self.flags[i] = True
            self.revision += 1
            self.events += 1
            self.tacho_events += i

    def state(self) -> tuple:
        return (*self.flags, self.events, self.tacho_events, self.revision)


@pytest.mark.parametrize("Ts", [None, 1e-3])
def test_the_step_matches_the_check_written_as_a_loop(Ts: float | None) -> None:
    import random

    rng = random.Random(7)
    check = StuckChannels(samples=20, motion_rad=0.5, counts_per_rev=CPR, sample_period_s=Ts)
    ref = _LoopReference(20, 0.5, Ts)
    enc, torque, velocity = 0, 1.0, 50.0
    trips = 0
    for k in range(6000):
        if rng.random() < 0.02:  # a lost frame
            check.missed()
            ref.missed()
        phase = (k // 300) % 4  # held torque, held tacho, both held, both moving
        if phase in (2, 3) or rng.random() < 0.05:
            torque = round(rng.uniform(-3, 3), 2)
        if phase in (1, 3) or rng.random() < 0.05:
            velocity = rng.choice((50.0, 50.27, 80.0, 0.0))
        enc += rng.choice((0, 3, 8, 9, -4, 30000))
        tq_V = 9.995 if rng.random() < 0.01 else 1.0
        check.step(torque, velocity, enc & 0xFFFF, tq_V, 0.5)
        ref.step(torque, velocity, enc & 0xFFFF, tq_V, 0.5)
        got = (check.torque_stuck, check.tacho_stuck, check.events, check.tacho_events,
               check.revision)  # fmt: skip
        assert got == ref.state(), k
        trips = max(trips, check.events)
    assert trips > 2  # the sequence did trip both channels
    if Ts:
        assert check.tacho_events > 0
