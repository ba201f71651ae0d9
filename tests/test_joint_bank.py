"""Several joints per cycle: the plant bank and the filter bank against N scalar objects,
and the measurement that chooses between them (hostsim.plant.bank, analysis.joint_scaling)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hdhil.analysis.joint_scaling import (
    KalmanBank,
    crossover,
    format_joint_scaling,
    joint_scaling,
)
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.ripple import HarmonicKalman
from hdhil.hostsim.plant import (
    DriveTrainConfig,
    GravityConfig,
    LinkMotionConfig,
    LoadTorqueConfig,
    Plant,
    PlantConfig,
    SensorConfig,
)
from hdhil.hostsim.plant.bank import VECTOR_CROSSOVER, PlantBank, ScalarPlants, plant_bank

DT = 1e-3


def _arm() -> list[PlantConfig]:
    """Three different joints: default, a shoulder under gravity with another gear and
    friction, and one whose torque sensor reads the spring only."""
    base = PlantConfig()
    shoulder = replace(
        base,
        gravity=GravityConfig(mgl_Nm=3.0, offset_deg=10.0),
        drivetrain=DriveTrainConfig(gear_ratio=80.0, coulomb_motor=0.8),
    )
    wrist = replace(base, sensors=SensorConfig(torque_measures="spring"))
    return [base, shoulder, wrist]


def _volts(k: int, n: int) -> list[float]:
    return [2.0 * math.sin(k * DT * (3.0 + 2.0 * j)) for j in range(n)]


def test_plant_bank_equals_scalar_plants_to_round_off() -> None:
    cfgs, seeds = _arm(), [4, 5, 6]
    bank = PlantBank(cfgs, seeds)
    plants = [Plant(c, s) for c, s in zip(cfgs, seeds, strict=True)]
    bank.set_load_torque([0.0, -0.5, 1.5])
    plants[1].set_load_torque(-0.5)
    plants[2].set_load_torque(1.5)
    worst, mismatched, samples = 0.0, 0, 0
    for k in range(1000):
        volts = _volts(k, 3)
        counts = bank.step(volts, DT)
        for j, p in enumerate(plants):
            p.advance(volts[j], DT)
            ref = p.sample()
            assert all(isinstance(c, int) for c in counts[j])
            # a count may flip where the voltage sits on a rounding boundary
            assert max(abs(a - b) for a, b in zip(ref, counts[j], strict=True)) <= 1
            mismatched += ref != counts[j]
            samples += 1
        if k % 50 == 0:
            ref_state = np.array([[p._d, p._wm, p._wl, p._i, p._ql] for p in plants])
            err = np.abs(bank.state - ref_state) / (1.0 + np.abs(ref_state))
            worst = max(worst, float(err.max()))
    assert worst < 1e-10
    assert mismatched <= samples // 1000
    assert bank.time == pytest.approx(plants[0].time, abs=1e-15)
    # the joints went somewhere: gravity and load moved the state far from rest
    assert np.all(np.abs(bank.state[:, 4]) > 0.01)


def test_plant_bank_noise_streams_are_the_plants() -> None:
    """Joint k of a bank draws the noise of Plant(cfgs[k], seeds[k]) across block refills."""
    cfg = replace(
        PlantConfig(),
        sensors=SensorConfig(torque_noise_Nm=0.5, tacho_noise_radps=2.0, current_noise_A=0.2),
    )
    bank = PlantBank([cfg, cfg], [11, 12])
    plants = [Plant(cfg, 11), Plant(cfg, 12)]
    for _ in range(1400):  # past the first block of 4096 normals (1365 samples)
        got = bank.sample()
        assert got == [p.sample() for p in plants]
    assert got[0] != got[1]


def test_scalar_plants_are_bitwise_plant() -> None:
    cfgs, seeds = _arm(), [1, 2, 3]
    group = ScalarPlants(cfgs, seeds)
    plants = [Plant(c, s) for c, s in zip(cfgs, seeds, strict=True)]
    for k in range(200):
        volts = _volts(k, 3)
        got = group.step(volts, DT)
        want = []
        for p, v in zip(plants, volts, strict=True):
            p.advance(v, DT)
            want.append(p.sample())
        assert got == want
    assert np.array_equal(group.state, [[p._d, p._wm, p._wl, p._i, p._ql] for p in plants])


def test_plant_bank_picks_the_path_by_joint_count() -> None:
    cfg = PlantConfig()
    few = plant_bank([cfg] * (VECTOR_CROSSOVER - 1), list(range(VECTOR_CROSSOVER - 1)))
    many = plant_bank([cfg] * VECTOR_CROSSOVER, list(range(VECTOR_CROSSOVER)))
    assert isinstance(few, ScalarPlants)
    assert isinstance(many, PlantBank)
    held = replace(cfg, link=LinkMotionConfig(kind="hold"))
    assert isinstance(plant_bank([held] * 32, list(range(32))), ScalarPlants)


def test_plant_bank_rejects_what_it_cannot_step() -> None:
    cfg = PlantConfig()
    with pytest.raises(ValueError, match="free links"):
        PlantBank([cfg, replace(cfg, link=LinkMotionConfig(kind="hold"))], [0, 1])
    with pytest.raises(ValueError, match="free links"):
        PlantBank([replace(cfg, load=LoadTorqueConfig(kind="constant", bias_Nm=1.0))], [0])
    with pytest.raises(ValueError, match="one seed per joint"):
        PlantBank([cfg, cfg], [0])
    bank = PlantBank([cfg, cfg], [0, 1])
    with pytest.raises(ValueError, match="numbers of volts"):
        bank.advance([0.0, math.nan], DT)
    with pytest.raises(ValueError, match="numbers of volts"):
        bank.advance([0.0], DT)


def test_kalman_bank_equals_scalar_filters_to_round_off() -> None:
    """Moving, standing and switching joints: ripple, x and P as N HarmonicKalman."""
    fw = FirmwareConfig()
    n = 4
    bank = KalmanBank(fw.ripple, fw.gear_ratio, n)
    filters = [HarmonicKalman(fw.ripple, fw.gear_ratio) for _ in range(n)]
    rng = np.random.default_rng(3)
    worst_ripple = worst_x = worst_p = 0.0
    for k in range(600):
        angle = 0.05 * k * np.array([1.0, 0.0, 2.0, 0.7]) + 0.01 * rng.standard_normal(n)
        vel = np.array([50.0, 0.0, 100.0, 1.0 if k % 100 < 50 else 35.0])
        y = 0.4 * np.sin(2.0 * angle) + 0.1 + 0.05 * rng.standard_normal(n)
        ripple = bank.step(y, vel, angle)
        for j, f in enumerate(filters):
            want = f.step(float(y[j]), float(vel[j]), float(angle[j]))
            worst_ripple = max(worst_ripple, abs(want - ripple[j]))
        x_ref = np.array([f.x for f in filters])
        p_ref = np.array([f._P for f in filters])
        worst_x = max(worst_x, float(np.abs(bank.x - x_ref).max()))
        worst_p = max(worst_p, float((np.abs(bank.P_upper - p_ref) / np.abs(p_ref).max()).max()))
    assert worst_ripple < 1e-11
    assert worst_x < 1e-11
    assert worst_p < 1e-11
    # the moving joints learned a ripple, the standing one kept its harmonics at 0
    assert np.all(np.abs(bank.x[[0, 2], 0:2]).max(axis=1) > 0.05)
    assert np.all(bank.x[1, :-1] == 0.0)


def test_joint_scaling_rows_are_sane() -> None:
    rows = joint_scaling((1, 3), steps=5, repeats=3)
    assert [r["joints"] for r in rows] == [1, 3]
    keys = ("plant_scalar_us", "plant_vector_us", "filter_scalar_us", "filter_vector_us")
    for row in rows:
        assert all(math.isfinite(row[k]) and row[k] > 0.0 for k in keys)
    lines = format_joint_scaling(rows)
    assert lines[0].startswith("| joints")
    assert len(lines) == 2 + len(rows) + 2
    with pytest.raises(ValueError):
        joint_scaling((0,), steps=5)


def test_crossover_is_where_vectorised_stays_ahead() -> None:
    def row(n: int, scalar: float, vector: float) -> dict[str, float]:
        return {"joints": n, "plant_scalar_us": scalar, "plant_vector_us": vector}

    rows = [row(1, 5, 40), row(8, 45, 44), row(10, 55, 56), row(16, 90, 57), row(32, 180, 70)]
    assert crossover(rows, "plant") == 16  # the win at 8 did not hold at 10
    assert crossover(rows[:2], "plant") == 8
    assert crossover([row(1, 5, 40)], "plant") is None
