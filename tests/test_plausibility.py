"""The sensor plausibility stage (firmware/stages/plausibility.py ``SensorPlausibility``),
its place in the filter chain and the interrupt (firmware/isr.py), and its effect over the
bus with injected tacho spikes and encoder glitches (``[faults.sensors]``)."""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from pathlib import Path

import can
import numpy as np
import pytest
from runs import lockstep

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.firmware.config import FirmwareConfig, PlausibilityConfig, paper_config
from hdhil.firmware.isr import AdcSample, InterruptHandler, TorqueFilterChain
from hdhil.firmware.stages import Differentiator, SensorPlausibility
from hdhil.rig.scenario import load_scenario

TS = 1e-3
CFG = PlausibilityConfig()
CPR = 8000
COUNTS_PER_RAD = CPR / (2 * math.pi)
#: The one-sample velocity bound: noise band + largest acceleration x Ts.
BOUND = CFG.tacho_noise_radps + CFG.max_acceleration_radps2 * TS
M = CFG.max_rejections
#: One tacho volt in rad/s ([Taghirad97] listing A.1 ``volt2radps``).
VOLT = 56.2565


def _stage(cfg: PlausibilityConfig = CFG, encoder: bool = True) -> SensorPlausibility:
    return SensorPlausibility(cfg, TS, CPR, check_encoder=encoder)


def _signed16(x: int) -> int:
    return (x + 0x8000) % 0x10000 - 0x8000


def _counts(velocity: np.ndarray, start: float) -> list[int]:
    """Encoder readings (16-bit, wrapping) of a motor moving at ``velocity`` (rad/s)."""
    angle = start + np.concatenate(([0.0], np.cumsum((velocity[1:] + velocity[:-1]) * TS / 2)))
    return [round(float(a) * COUNTS_PER_RAD) & 0xFFFF for a in angle]


# ------------------------------------------------------------------- velocity


def test_a_tacho_spike_is_replaced_by_the_last_accepted_velocity() -> None:
    check = _stage(encoder=False)
    v = 150.0 + np.random.default_rng(1).normal(0.0, 0.05, 200)
    v[100] += VOLT  # a 1 V spike
    out, rejected = [], []
    for x in v:
        out.append(check.step(float(x), None)[0])
        rejected.append(check.rejected)
    assert out[100] == v[99]  # held
    assert [k for k, r in enumerate(rejected) if r] == [100]
    assert all(out[k] == v[k] for k in range(200) if k != 100)
    assert check.tacho_rejections == 1 and check.tacho_reseeds == 0
    assert not check.tacho_error and check.errors_raised == 0  # an isolated spike


def test_a_ramp_at_the_largest_acceleration_passes_and_a_faster_one_does_not() -> None:
    rng = np.random.default_rng(2)
    k = np.arange(300)
    # the fastest the joint can go, with noise inside the band
    ramp = CFG.max_acceleration_radps2 * TS * k + rng.uniform(-0.5, 0.5, k.size) * (
        CFG.tacho_noise_radps
    )
    check = _stage(encoder=False)
    assert [check.step(float(x), None)[0] for x in ramp] == ramp.tolist()
    assert check.tacho_rejections == 0
    # 2 % faster than the bound, noise-free: the first change is already implausible
    check = _stage(encoder=False)
    check.step(0.0, None)
    assert check.step(1.02 * BOUND, None)[0] == 0.0 and check.rejected
    assert check.step(0.98 * BOUND, None)[0] == 0.98 * BOUND and not check.rejected


def test_the_bound_grows_with_the_samples_held() -> None:
    """After n replaced samples the joint may have moved n + 1 times as far."""
    check = _stage(encoder=False)
    check.step(10.0, None)
    assert check.step(10.0 + VOLT, None)[0] == 10.0  # spike held
    # two samples after the last accepted one: up to noise + 2 x a_max Ts
    two = 10.0 + CFG.tacho_noise_radps + 2 * CFG.max_acceleration_radps2 * TS
    assert check.step(two - 0.01, None)[0] == two - 0.01 and not check.rejected


def test_a_real_velocity_jump_is_accepted_after_max_rejections_and_the_error_clears() -> None:
    """No lock-out: the level is held for M samples (error raised at the M-th), the next
    implausible sample is taken as the new level, and M plausible ones clear the error."""
    jump = 2 * (CFG.tacho_noise_radps + (M + 1) * CFG.max_acceleration_radps2 * TS)
    v = [50.0] * 10 + [50.0 + jump] * 20
    check = _stage(encoder=False)
    out, error, reseeded = [], [], []
    for x in v:
        out.append(check.step(x, None)[0])
        error.append(check.tacho_error)
        reseeded.append(check.reseeded)
    assert out[10 : 10 + M] == [50.0] * M
    assert out[10 + M :] == v[10 + M :]
    assert [k for k, r in enumerate(reseeded) if r] == [10 + M]
    # raised at the M-th replacement, cleared after M plausible samples
    assert [k for k in range(1, 30) if error[k] != error[k - 1]] == [10 + M - 1, 10 + 2 * M]
    assert check.tacho_rejections == M and check.tacho_reseeds == 1 and check.errors_raised == 1


def test_a_noisy_tacho_that_stays_off_is_followed_not_locked_out() -> None:
    """A tacho that keeps jumping around: never more than M samples in a row replaced."""
    check = _stage(encoder=False)
    v = [0.0] + [(-1) ** k * 10 * BOUND for k in range(40)]
    run = longest = 0
    for x in v:
        check.step(x, None)
        run = run + 1 if check.rejected else 0
        longest = max(longest, run)
    assert longest == M
    assert check.tacho_error


def test_a_non_finite_velocity_passes_unchecked() -> None:
    check = _stage()
    check.step(100.0, 0)
    v, _ = check.step(math.nan, 127)
    assert math.isnan(v) and not check.rejected
    assert check.step(100.0, 254) == (100.0, 254) and not check.rejected


# -------------------------------------------------------------------- encoder


@pytest.mark.parametrize(("velocity", "start"), [(150.0, 65000.0), (-150.0, 600.0)])
def test_encoder_increments_across_the_16_bit_wrap_pass(velocity: float, start: float) -> None:
    v = np.full(100, velocity)
    raw = _counts(v, start / COUNTS_PER_RAD)
    assert any(abs(raw[k] - raw[k - 1]) > 30000 for k in range(1, 100))  # it wraps
    check = _stage()
    out = [check.step(velocity, c)[1] for c in raw]
    assert out == raw and check.encoder_rejections == 0


@pytest.mark.parametrize("glitch", [200, -200, 40])
def test_an_encoder_glitch_is_replaced_by_the_predicted_increment(glitch: int) -> None:
    """A glitch (counts lost or gained for good) right at the wrap: the count the stage
    passes on stays continuous, within a count of the clean one, and the later increments
    are the measured ones again."""
    v = np.full(200, 150.0)
    clean = _counts(v, 65300 / COUNTS_PER_RAD)
    wrap = next(k for k in range(1, 200) if clean[k] < clean[k - 1])
    faulty = [c if k < wrap else (c + glitch) & 0xFFFF for k, c in enumerate(clean)]
    check = _stage()
    out = []
    for c in faulty:
        out.append(check.step(150.0, c)[1])
    assert max(abs(_signed16(o - c)) for o, c in zip(out, clean, strict=True)) <= 1
    assert check.encoder_rejections == 1 and not check.encoder_error
    assert all(
        _signed16(out[k] - out[k - 1]) == _signed16(faulty[k] - faulty[k - 1])
        for k in range(wrap + 1, 200)
    )


def test_a_glitch_within_the_tolerance_passes() -> None:
    v = np.full(50, 150.0)
    raw = _counts(v, 0.0)
    small = int(CFG.encoder_tolerance_counts) - 2
    faulty = [c if k < 20 else (c + small) & 0xFFFF for k, c in enumerate(raw)]
    check = _stage()
    assert [check.step(150.0, c)[1] for c in faulty] == faulty
    assert check.encoder_rejections == 0


def test_a_stuck_encoder_is_followed_after_max_rejections_and_clears_when_it_moves() -> None:
    """The encoder stops counting while the tacho says 150 rad/s: M predicted increments,
    then the stuck count is followed (error raised); when it counts again, the error
    clears after M agreeing increments."""
    v = np.full(60, 150.0)
    raw = _counts(v, 0.0)
    stuck = raw[:10] + [raw[9]] * 20 + [(c - raw[29] + raw[9]) & 0xFFFF for c in raw[30:]]
    check = _stage()
    out, error = [], []
    for c in stuck:
        out.append(check.step(150.0, c)[1])
        error.append(check.encoder_error)
    steps = [_signed16(out[k] - out[k - 1]) for k in range(1, 60)]
    predicted = round(150.0 * TS * COUNTS_PER_RAD)
    assert all(abs(s - predicted) <= 1 for s in steps[9 : 9 + M])  # replaced
    assert steps[9 + M : 29] == [0] * (20 - M)  # followed: no lock-out
    assert [k for k in range(1, 60) if error[k] != error[k - 1]] == [10 + M - 1, 30 + M - 1]
    assert check.encoder_rejections == M and check.encoder_reseeds == 20 - M


def test_the_encoder_is_not_checked_without_check_encoder() -> None:
    check = _stage(encoder=False)
    check.step(150.0, 0)
    assert check.step(150.0, 5000) == (150.0, 5000) and check.encoder_rejections == 0


def test_a_missed_sample_widens_the_bounds_to_two_periods() -> None:
    """A lost sensor frame: the next increment covers two periods, and is plausible
    only if the stage is told about the gap."""
    raw = _counts(np.full(10, 150.0), 0.0)
    told, untold = _stage(), _stage()
    for c in raw[:5]:
        told.step(150.0, c)
        untold.step(150.0, c)
    told.missed()
    assert told.step(150.0, raw[6]) == (150.0, raw[6]) and not told.rejected
    untold.step(150.0, raw[6])
    assert untold.rejected and untold.encoder_rejections == 1
    # the velocity bound spans the gap too
    told.missed()
    assert told.step(150.0 + 1.5 * BOUND, raw[8])[0] == 150.0 + 1.5 * BOUND


# ----------------------------------------------------------- differentiator


def test_the_differentiator_is_clamped_and_reseeded() -> None:
    diff = Differentiator()
    assert diff.step(100.0) == pytest.approx(diff.nd[0] * 100.0)  # unlimited: the listing
    diff = Differentiator()
    diff.limit = 1000.0
    assert diff.step(100.0) == 1000.0 and diff.a_1 == 1000.0
    assert diff.step(-100.0) == -1000.0
    diff.reseed(300.0)
    assert diff.step(300.0) == pytest.approx(-diff.dd[1] * -1000.0)  # only the decay


# ----------------------------------------------------------- chain, interrupt


def _spiky(n: int = 400, spikes: tuple[int, ...] = (150, 151, 260)) -> tuple[list, list, list]:
    rng = np.random.default_rng(3)
    k = np.arange(n)
    v_clean = np.full(n, 120.0)
    T = 0.5 + 0.6 * np.cos(2 * 120.0 * TS * k) + rng.normal(0.0, 0.02, n)
    v = v_clean.copy()
    for i, s in enumerate(spikes):
        v[s] += VOLT if i % 2 == 0 else -VOLT
    return T.tolist(), v.tolist(), _counts(v_clean, 0.0)


def test_chain_recommended_skips_the_update_of_a_replaced_sample() -> None:
    T, v, enc = _spiky()
    chain = TorqueFilterChain(FirmwareConfig())
    clean = TorqueFilterChain(FirmwareConfig())
    for k in range(len(T)):
        x_before = chain.kalman.x
        acc, _, _, T_f, ripple = chain.step(T[k], v[k], enc[k])
        acc_clean = clean.step(T[k], 120.0, enc[k])[0]
        assert acc == acc_clean  # the replaced velocity is the clean one here
        assert chain.velocity == 120.0
        if k in (150, 151, 260):
            assert np.array_equal(chain.kalman.x, x_before)  # no update
            assert ripple == chain.kalman.ripple_at(chain.angle)
            assert T_f == T[k] - ripple
    assert chain.kalman.skipped == 3 and chain.plausibility.tacho_rejections == 3


def test_chain_a_level_accepted_after_a_jump_adds_no_acceleration_impulse() -> None:
    """The differentiator is re-seeded at the new level: its output only decays."""
    jump = 2 * (CFG.tacho_noise_radps + (M + 1) * CFG.max_acceleration_radps2 * TS)
    v = [50.0] * 200 + [50.0 + jump] * 50
    chain = TorqueFilterChain(FirmwareConfig())
    acc = []
    for k, x in enumerate(v):
        acc.append(chain.step(0.0, x, round(50.0 * TS * COUNTS_PER_RAD) * k & 0xFFFF)[0])
    assert chain.plausibility.tacho_reseeds == 1
    assert max(abs(a) for a in acc[150:]) < 1.0


def test_chain_without_the_stage_passes_the_spike_into_the_acceleration() -> None:
    T, v, enc = _spiky()
    off = dataclasses.replace(FirmwareConfig(), plausibility=PlausibilityConfig(enabled=False))
    on = TorqueFilterChain(FirmwareConfig())
    unchecked = TorqueFilterChain(off)
    acc_on = [on.step(T[k], v[k], enc[k])[0] for k in range(len(T))]
    acc_off = [unchecked.step(T[k], v[k], enc[k])[0] for k in range(len(T))]
    # the first sample is a step from the listing's v_1 = 0: clamped with the stage
    assert acc_off[0] == pytest.approx(Differentiator().nd[0] * 120.0)
    assert acc_on[0] == CFG.max_acceleration_radps2 < acc_off[0]
    spike_acc = Differentiator().nd[0] * VOLT  # 10 230 rad/s²
    assert max(abs(a) for a in acc_off[100:]) > 0.9 * spike_acc
    assert max(abs(a) for a in acc_on[100:]) < 1.0  # constant velocity: ~0
    assert unchecked.kalman.skipped == 0 and unchecked.plausibility.tacho_rejections == 0


def test_chain_paper_updates_with_the_replaced_velocity() -> None:
    """Paper mode with the stage asked for (it is off by default there): the listing's
    filter runs on the held velocity, exactly as if the spikes had not happened (a
    skipped call would leave its oscillators behind)."""
    T, v, enc = _spiky()
    paper = dataclasses.replace(
        paper_config(FirmwareConfig()), plausibility=PlausibilityConfig(enabled=True)
    )
    chain = TorqueFilterChain(paper)
    clean = TorqueFilterChain(paper)
    for k in range(len(T)):
        assert chain.step(T[k], v[k], enc[k]) == clean.step(T[k], 120.0)
    assert chain.kalman.skipped == 0 and chain.plausibility.tacho_rejections == 3


def test_interrupt_reports_the_replaced_velocity() -> None:
    isr = InterruptHandler(FirmwareConfig())
    lsb = 20.0 / 4096
    tacho = round(120.0 / VOLT / lsb)
    spike = round((120.0 + VOLT) / VOLT / lsb)
    step = round(120.0 * TS * COUNTS_PER_RAD)
    velocities = []
    for k, code in enumerate([tacho] * 20 + [spike] + [tacho] * 5):
        out = isr(AdcSample(torque=0, tacho=code, current=0, encoder=step * k))
        velocities.append(out.velocity)
    assert velocities[20] == velocities[19] == pytest.approx(tacho * lsb * VOLT)
    assert isr.chain.plausibility.tacho_rejections == 1


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ({"max_rejections": 0}, "max_rejections must be an integer >= 1"),
        ({"max_rejections": 2.5}, "max_rejections"),
        ({"max_acceleration_radps2": -1.0}, "max_acceleration_radps2 must be > 0"),
        ({"tacho_noise_radps": math.nan}, "tacho_noise_radps must be a finite number"),
        ({"encoder_tolerance_counts": 0.0}, "encoder_tolerance_counts must be > 0"),
        ({"enabled": "yes"}, "firmware.plausibility.enabled"),
        ({"max_accel": 1.0}, "unknown key firmware.plausibility.max_accel"),
    ],
)
def test_bad_plausibility_settings_are_one_line_errors(table: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        from_dict(FirmwareConfig, {"plausibility": table}, "firmware")
    assert "\n" not in str(err.value)


# --------------------------------------------------------------- over the bus

#: 1 V tacho spikes (56 rad/s) at 2 % of the samples and 200-count encoder glitches at
#: 0.5 %, on the free-motion run.
FAULTS = {
    "seed": 0,
    "sensors": {
        "tacho_spike_rate": 0.02,
        "tacho_spike_V": 1.0,
        "encoder_glitch_rate": 0.005,
        "encoder_glitch_counts": 200,
    },
}


def _run(faults: dict | None, enabled: bool = True, paper: bool = False, log: Path | None = None):
    firmware: dict = {"plausibility": {"enabled": enabled}}
    if paper:
        firmware["ripple"] = {"mode": "paper"}
    overrides: dict = {"firmware": firmware}
    if faults is not None:
        overrides["faults"] = faults
    scenario = load_scenario("free-motion", overrides)
    r = lockstep(scenario, fault_log=log, evaluate_skip_s=scenario.evaluate_from_s)
    fw = next(c for c in r.evaluation["candidates"] if c["name"].startswith("firmware"))
    return r, fw["rms_error"]


def _operational_faults(log: Path, r, kind: str) -> list[dict]:
    """Faults of ``kind`` on the samples the interrupt checked: from the second sample in
    operation (the first has nothing to be checked against) to the last."""
    first = (r.startup_cycles + 1) * r.sample_period_s
    end = (r.startup_cycles + r.cycles) * r.sample_period_s
    records = [json.loads(line) for line in log.read_text().splitlines()]
    at_first = [x for x in records if abs(x["time"] - first + r.sample_period_s) < 1e-9]
    assert not at_first, "the fault seed puts a fault on the first sample in operation"
    return [x for x in records if x["kind"] == kind and first - 1e-9 <= x["time"] < end - 1e-9]


@pytest.mark.slow
@pytest.mark.parametrize("paper", [False, True], ids=["recommended", "paper"])
def test_spikes_and_glitches_over_the_bus(tmp_path: Path, paper: bool) -> None:
    """Filtered-torque RMS error against truth (from the scenario's evaluate_from_s):
    with the stage within 1.2x the clean run, without it far worse; every spike and
    glitch beyond the bounds counted, and no EMCY for isolated faults."""
    _, clean = _run(None, paper=paper)
    log = tmp_path / "faults.jsonl"
    on, rms_on = _run(FAULTS, paper=paper, log=log)
    off, rms_off = _run(FAULTS, enabled=False, paper=paper)
    numbers = f"clean {clean:.4f} Nm, with the stage {rms_on:.4f} Nm, without {rms_off:.4f} Nm"
    assert rms_on <= 1.2 * clean, numbers
    assert rms_off >= 2.0 * clean, numbers

    spikes = _operational_faults(log, on, "tacho_spike")
    glitches = _operational_faults(log, on, "encoder_glitch")
    assert len(spikes) > 20 and len(glitches) > 3  # enough to mean something
    c = on.controller
    bound = CFG.tacho_noise_radps + CFG.max_acceleration_radps2 * TS
    assert c["tacho_rejections"] == sum(abs(x["details"]["volts"]) * VOLT > bound for x in spikes)
    checked = 0 if paper else sum(
        abs(x["details"]["counts"]) > CFG.encoder_tolerance_counts for x in glitches
    )  # fmt: skip
    assert c["encoder_rejections"] == checked
    assert c["plausibility_errors"] == 0 and not any("EMCY_CTRL" in n for n in on.frames)
    assert off.controller["tacho_rejections"] == off.controller["encoder_rejections"] == 0


@pytest.mark.slow
def test_spikes_within_the_bound_are_not_counted(tmp_path: Path) -> None:
    """0.15 V spikes (8.4 rad/s; two in a row of opposite sign 16.9 rad/s) are within
    what the joint can do in a sample: passed on."""
    faults = {"seed": 0, "sensors": {"tacho_spike_rate": 0.02, "tacho_spike_V": 0.15}}
    log = tmp_path / "faults.jsonl"
    r, _ = _run(faults, log=log)
    spikes = _operational_faults(log, r, "tacho_spike")
    assert spikes and all(2 * abs(x["details"]["volts"]) * VOLT < BOUND for x in spikes)
    assert r.controller["tacho_rejections"] == 0


@pytest.mark.slow
def test_a_saturated_tacho_is_bridged_announced_and_cleared(tmp_path: Path) -> None:
    """The tacho ADC at full scale for 50 ms at speed: no lock-out (the run ends in
    operation), every sensor error the controller raises by EMCY is cleared again by
    EMCY 0x0000, and the filtered torque suffers less than without the stage."""
    faults = {
        "seed": 0,
        "sensors": {"saturated": [{"channel": "tacho", "start_s": 1.0, "duration_s": 0.05}]},
    }
    trace = tmp_path / "run.log"
    scenario = load_scenario("free-motion", {"faults": faults})
    r = lockstep(scenario, trace=trace, evaluate_skip_s=scenario.evaluate_from_s)
    _, rms_off = _run(faults, enabled=False)
    rms_on = next(c for c in r.evaluation["candidates"] if c["name"].startswith("firmware"))
    assert r.cycles == 2000 and not r.interrupted
    emcy = [struct.unpack_from("<HB", m.data) for m in can.LogReader(str(trace))
            if m.arbitration_id == 0x081]  # fmt: skip
    raised = [code for code, _ in emcy if code]
    assert raised and set(raised) <= {0x7301, 0x7305}
    assert len(emcy) == 2 * len(raised) == 2 * r.controller["plausibility_errors"]
    assert emcy[-1] == (0x0000, 0x00)  # error register clear at the end
    assert rms_on["rms_error"] < 0.8 * rms_off, (rms_on["rms_error"], rms_off)
