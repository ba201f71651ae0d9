"""Extreme physics: what the plant's stepper cannot integrate is refused before the run,
naming the key and its limit (:mod:`hdhil.hostsim.plant.stability`); a reading beyond the
float range saturates the converters instead of raising; a plant whose state still goes
non-finite stops the run with a verdict saying what and when, and its JSON stays valid."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from hdhil.cli import main
from hdhil.core import jsonout
from hdhil.core.converter import Converter
from hdhil.core.errors import ConfigError
from hdhil.hostsim.plant import (
    AmplifierConfig,
    DriveTrainConfig,
    NonFiniteStateError,
    Plant,
    PlantConfig,
    SensorConfig,
    step_problems,
)
from hdhil.hostsim.plant.stability import MAX_HELD_SLOPE_STEP
from hdhil.rig.scenario import list_scenarios, load_scenario

Ts = 1e-3


def _strict(text: str) -> Any:
    def refuse(token: str) -> Any:
        raise ValueError(f"invalid JSON token {token}")

    return json.loads(text, parse_constant=refuse)


# ------------------------------------------------------------------ the converters
@pytest.mark.parametrize(
    ("volts", "code"),
    [(math.inf, 2047), (-math.inf, -2048), (1e308, 2047), (-1e308, -2048), (math.nan, 0),
     (1.0, 205)],
)  # fmt: skip
def test_the_converter_saturates_a_voltage_beyond_any_float(volts: float, code: int) -> None:
    assert Converter().to_counts(volts) == code


def test_a_very_stiff_joint_reads_saturated_counts_not_an_overflow() -> None:
    """The reported case: k_flex near the float32 limit made the plant's torque reading
    infinite and the ADC conversion raise OverflowError."""
    cfg = PlantConfig(drivetrain=DriveTrainConfig(k_flex=3e38))
    plant = Plant(cfg)
    adc = cfg.adc
    failures = 0
    for k in range(400):
        try:
            plant.advance(2.0 if k < 200 else -2.0, Ts)
        except NonFiniteStateError:
            failures += 1
        counts = plant.sample()
        assert all(adc.code_min <= c <= adc.code_max for c in counts[:3])
        assert 0 <= counts[3] < 1 << 16
    assert failures, "the map no longer overflows: pick a stiffer joint"


def test_an_encoder_count_beyond_any_float_reads_zero() -> None:
    plant = Plant(PlantConfig(sensors=SensorConfig(encoder_counts_per_rev=10**300)))
    plant.hold_locked(1e10, 0.0)  # theta * counts/rad overflows to inf
    assert plant.sample()[3] == 0


# ------------------------------------------------------------- refused up front
@pytest.mark.parametrize(
    ("plant", "message"),
    [
        ({"drivetrain": {"k_flex": 3e38}}, r"k_flex must be <= 2\.61e\+15 with these inertias"),
        ({"drivetrain": {"c_flex": 1e8}}, r"c_flex must be <= 6\.52e\+06"),
        ({"drivetrain": {"b_motor": 1e10}}, r"b_motor must be <= 1\.2e\+08"),
        ({"amplifier": {"current_lag_s": 1e-20}}, r"current_lag_s = 1e-20 .* >= 2\.5e-09"),
        ({"drivetrain": {"J_load": 1e-20, "k_flex": 1e-20, "c_flex": 0.0, "b_load": 0.0,
                         "coulomb_load": 0.0}}, r"J_load = 1e-20 kg m² is below"),
        ({"link": {"kind": "sine", "frequency_Hz": 1e12, "amplitude_deg": 1.0}},
         r"link\.frequency_Hz = 1e\+12 is above"),
        ({"drivetrain": {"coulomb_motor": 50.0, "friction_smoothing": 1e-3}},
         r"friction_smoothing must be >= 0\.0208 \(or plant\.substeps >= 84\)"),
        ({"drivetrain": {"coulomb_load": 5.0, "friction_smoothing": 1e-3}},
         r"coulomb_load 5 Nm on J_load .* friction_smoothing must be >= 0\.0362"),
    ],
)  # fmt: skip
def test_a_plant_the_stepper_cannot_integrate_is_refused_naming_key_and_limit(
    plant: dict[str, Any], message: str
) -> None:
    with pytest.raises(ConfigError, match=message) as info:
        load_scenario("free-motion", {"plant": plant})
    assert "\n" not in str(info.value)
    assert "sub-step of 0.00025 s" in str(info.value)


def test_more_substeps_lift_the_held_friction_bound() -> None:
    table = {"drivetrain": {"coulomb_motor": 50.0, "friction_smoothing": 1e-3}, "substeps": 84}
    assert load_scenario("free-motion", {"plant": table}).plant.substeps == 84


def test_every_shipped_scenario_is_well_inside_its_limits() -> None:
    for name in list_scenarios():
        scenario = load_scenario(name)
        plant, dt = scenario.plant, scenario.firmware.sample_period_s
        assert step_problems(plant, dt) == [], name
        d = plant.drivetrain
        assert d.natural_frequency_radps * dt / plant.substeps < 1.0, name


def test_the_refusal_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    override = tmp_path / "stiff.toml"
    override.write_text("[plant.drivetrain]\nk_flex = 3e38\n")
    trace = tmp_path / "run.blf"
    assert main(["run", "--override", str(override), "--trace", str(trace), "--json"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error: ") and err.count("\n") == 1, err
    assert "plant.drivetrain.k_flex = 3e+38" in err and "k_flex must be <= " in err
    assert not trace.exists()


@pytest.mark.parametrize("factor", [0.9, 1.1])
def test_the_held_friction_bound_is_where_standstill_starts_to_chatter(factor: float) -> None:
    """The bound of :mod:`hdhil.hostsim.plant.stability`: a Coulomb friction held over a
    sub-step brings a kicked motor to rest when h C / (eps J) <= 2 and keeps it
    chattering around zero velocity beyond."""
    C, J, substeps = 50.0, 0.3, 4
    h = Ts / substeps
    eps = factor * h * C / (MAX_HELD_SLOPE_STEP * J)
    cfg = PlantConfig(
        drivetrain=DriveTrainConfig(coulomb_motor=C, friction_smoothing=eps, J_motor=J,
                                    b_motor=0.0, coulomb_load=0.0, b_load=0.0),
        amplifier=AmplifierConfig(current_lag_s=0.0),
        substeps=substeps,
    )  # fmt: skip
    assert bool(step_problems(cfg, Ts)) == (factor < 1.0)
    plant = Plant(cfg)
    plant.advance(0.5, Ts)  # a kick, then the amplifier off
    late = []
    for k in range(2000):
        plant.advance(0.0, Ts)
        if k >= 1800:
            late.append(abs(plant.truth().omega_motor_radps))
    if factor < 1.0:
        assert max(late) > 0.1  # rad/s at the motor: the friction flips every sub-step
    else:
        assert max(late) < 1e-9


def test_the_drive_prepares_only_a_plant_it_can_integrate() -> None:
    plant = Plant(PlantConfig(drivetrain=DriveTrainConfig(k_flex=3e38)))
    with pytest.raises(ValueError, match="k_flex must be <="):
        plant.prepare(Ts)


# ------------------------------------------------------- non-finite during a run
def test_a_step_that_goes_non_finite_raises_and_keeps_the_last_finite_state() -> None:
    plant = Plant(PlantConfig())
    for _ in range(10):
        plant.advance(1.0, Ts)
    state = ("theta_motor_rad", "theta_output_rad", "omega_motor_radps", "omega_output_radps",
             "T_true_Nm", "current_A")  # fmt: skip
    before = [getattr(plant.truth(), name) for name in state]
    plant.set_load_torque(1e308)  # finite, but no float holds the load's acceleration
    with pytest.raises(NonFiniteStateError, match=r"non-finite at t = 0\.011 s \(.*load velocity"):
        plant.advance(1.0, Ts)
    assert plant.time == pytest.approx(0.010)
    assert [getattr(plant.truth(), name) for name in state] == before
    assert all(math.isfinite(x) for x in before)


class _Exploding(Plant):
    """A plant whose load gets a torque no float can integrate from 50 ms on."""

    def advance(self, volts: float, dt: float) -> None:
        if self.time >= 0.05:
            self.set_load_torque(1e308)
        super().advance(volts, dt)


@pytest.mark.slow
def test_a_plant_that_goes_non_finite_stops_the_run_with_a_verdict(tmp_path: Path) -> None:
    import hdhil
    from hdhil.hostsim.drive import DriveNode
    from hdhil.rig.factories import NodeSite
    from hdhil.rig.verdict import format_verdict

    scenario = hdhil.load_scenario("free-motion")

    def make(site: NodeSite) -> DriveNode:
        return DriveNode(site.bus, _Exploding(scenario.plant, site.seed), site.drive_config(),
                         truth_bus=site.truth_bus)  # fmt: skip

    trace = tmp_path / "run.blf"
    result = hdhil.run(scenario, duration_s=0.3, trace=trace, drive_factories=[make])
    verdict = result.verdict
    assert verdict is not None and verdict["phase"] == "plant" and verdict["node"] == 2
    assert verdict["plant_failure"] == verdict["reason"]
    assert "went non-finite at t = 0.05" in verdict["reason"]
    assert "load velocity" in verdict["reason"]
    assert result.cycles < 300 and verdict["stopped_early"]
    assert "by node 2 (plant): the plant's state went non-finite" in format_verdict(verdict)
    data = _strict(jsonout.dumps(result.as_dict(), indent=2))
    assert data["verdict"]["plant_failure"] == verdict["reason"]
    assert trace.exists()
