"""Scenario files: loading, overrides and error reporting (hdhil.rig.scenario)."""

from __future__ import annotations

import math
import shutil
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.stages import ReferenceGenerator
from hdhil.hostsim.plant import Plant, PlantConfig, steady_state_motor_velocity
from hdhil.rig.scenario import Scenario, list_scenarios, load_scenario

SHIPPED = Path(__file__).resolve().parents[1] / "tools" / "hdhil" / "rig" / "scenarios"

MINIMAL = """\
[scenario]
name = "tiny"
duration_s = 0.5
"""


def write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_list_scenarios_names_every_shipped_file() -> None:
    names = list_scenarios()
    assert {"free-motion", "misalignment", "speed-chirp", "torque-steps"} <= set(names)
    assert names == sorted(p.stem for p in SHIPPED.glob("*.toml"))


def test_every_shipped_scenario_loads() -> None:
    for name in list_scenarios():
        scn = load_scenario(name)
        assert isinstance(scn, Scenario)
        assert isinstance(scn.plant, PlantConfig)
        assert scn.duration_s > 0


def test_free_motion_by_name_and_by_path_agree(tmp_path: Path) -> None:
    by_name = load_scenario("free-motion")
    copy = tmp_path / "copy.toml"
    shutil.copy(SHIPPED / "free-motion.toml", copy)
    by_path = load_scenario(str(copy))
    assert by_path == by_name
    assert load_scenario(copy) == by_name  # a Path works too
    assert by_name.name == "free-motion"
    assert by_name.firmware.reference.wave.name == "STEP"


def test_free_motion_step_is_an_exact_dac_code() -> None:
    """The step reaches the amplifier unchanged through the 12-bit DAC."""
    scn = load_scenario("free-motion")
    amplitude = scn.firmware.reference.amplitude_V
    dac = scn.plant.dac
    assert dac.to_volts(dac.to_counts(amplitude)) == amplitude


def test_minimal_file_gets_defaults(tmp_path: Path) -> None:
    scn = load_scenario(write(tmp_path, MINIMAL))
    assert scn == Scenario("tiny", "", 0.5, 0, PlantConfig(), FirmwareConfig())


def test_overrides_merge_into_the_file() -> None:
    base = load_scenario("free-motion")
    scn = load_scenario(
        "free-motion",
        {
            "scenario": {"seed": 9},
            "plant": {"drivetrain": {"b_motor": 2.5}, "substeps": 8},
            "firmware": {"reference": {"amplitude_V": 0.5}},
        },
    )
    assert scn.seed == 9
    assert scn.duration_s == base.duration_s
    assert scn.plant.drivetrain.b_motor == 2.5
    assert scn.plant.drivetrain.J_motor == base.plant.drivetrain.J_motor
    assert scn.plant.ripple == base.plant.ripple
    assert scn.plant.substeps == 8
    assert scn.firmware.reference.amplitude_V == 0.5
    assert scn.firmware.reference.step_time_s == base.firmware.reference.step_time_s
    # the shipped scenario itself is untouched by an earlier override
    assert load_scenario("free-motion") == base


def one_line_error(*args, match: str) -> str:
    with pytest.raises(ConfigError, match=match) as info:
        load_scenario(*args)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_a_file_starts_from_its_base_scenario(tmp_path: Path) -> None:
    """``[scenario] base``: a shipped name, or a .toml path relative to the file; the
    file's own tables are deep-merged over the base's."""
    (tmp_path / "sub").mkdir()
    mine = write(tmp_path, 'scenario = {base = "free-motion", name = "mine"}\n'
                 "[plant.drivetrain]\nb_motor = 2.5\n", "sub/mine.toml")  # fmt: skip
    scn, fm = load_scenario(mine), load_scenario("free-motion")
    assert scn.name == "mine" and scn.plant.drivetrain.b_motor == 2.5
    assert scn.duration_s == fm.duration_s and scn.firmware == fm.firmware
    assert scn.plant.drivetrain.coulomb_motor == fm.plant.drivetrain.coulomb_motor
    child = write(tmp_path, 'scenario = {base = "mine.toml", seed = 7}\n', "sub/child.toml")
    two = load_scenario(child)  # a base's own base, the path relative to the file
    assert (two.name, two.seed, two.plant.drivetrain.b_motor) == ("mine", 7, 2.5)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('scenario = {base = "a.toml", name = "b"}\n', "leads back to a file of its chain"),
        ("scenario = {base = 3}\n", "scenario.base must be a scenario name or a .toml path"),
        ('scenario = {base = "nope"}\n', "nope"),
    ],
)
def test_a_bad_base_is_refused_in_one_line(tmp_path: Path, text: str, message: str) -> None:
    write(tmp_path, 'scenario = {base = "b.toml", name = "a", duration_s = 1}\n', "a.toml")
    with pytest.raises(ConfigError, match=message):
        load_scenario(write(tmp_path, text, "b.toml"))


def test_unknown_name_lists_the_known_ones() -> None:
    message = one_line_error("free-motoin", match="unknown scenario 'free-motoin'")
    assert "free-motion" in message


def test_missing_file() -> None:
    one_line_error("/nonexistent/dir/x.toml", match="not found")


def test_malformed_toml_reports_the_line(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + "[plant.drivetrain]\nb_motor = = 2\n")
    message = one_line_error(path, match="invalid TOML")
    assert "line 5" in message
    assert str(path) in message


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ("[plant.drivetrain]\nb_motr = 2.0\n", r"unknown key plant\.drivetrain\.b_motr"),
        ("[plant]\nsubstep = 2\n", r"unknown key plant\.substep"),
        (
            '[plant.drivetrain]\nb_motor = "high"\n',
            r"plant\.drivetrain\.b_motor: expected a number",
        ),
        ("[plant]\nsubsteps = 2.5\n", r"plant\.substeps: expected an integer"),
        ("[plant.drivetrain]\nJ_load = -1.0\n", r"J_load must be > 0"),
        ("[plant.adc]\nbits = 40\n", r"bits must be 2\.\.16"),
        ("[plant]\ndrivetrain = 3\n", r"plant\.drivetrain: expected a table"),
        ("[buses]\nbitrate = 500000\n", r"buses\.bitrate: expected a table"),
        ("[bus]\nbitrate = 5\n", r"bus.bitrate must be"),
        ("[link]\nactuation = 'later'\n", r"link.actuation: must be one of"),
        ("firmware = 3\n", r"firmware: expected a table"),
    ],
)
def test_bad_content_gives_config_error_naming_the_key(
    tmp_path: Path, extra: str, match: str
) -> None:
    # bare keys must precede tables in TOML: put a top-level key before [scenario]
    text = extra + MINIMAL if not extra.startswith("[") else MINIMAL + extra
    one_line_error(write(tmp_path, text), match=match)


@pytest.mark.parametrize(
    ("header", "match"),
    [
        ('[scenario]\nname = "x"\n', r"missing key scenario\.duration_s"),
        ("[scenario]\nduration_s = 1.0\n", r"missing key scenario\.name"),
        ('[scenario]\nname = "x"\nduration_s = -1.0\n', r"duration_s must be > 0"),
        ('[scenario]\nname = "x"\nduration_s = 1.0\nseed = -3\n', r"seed must be an integer >= 0"),
        ('[scenario]\nname = ""\nduration_s = 1.0\n', r"name must be a non-empty string"),
        ('[scenario]\nname = "x"\nduration_s = 1.0\nseeds = 3\n', r"unknown key scenario\.seeds"),
        ("[plant]\nsubsteps = 2\n", r"missing \[scenario\]"),
    ],
)
def test_bad_header(tmp_path: Path, header: str, match: str) -> None:
    one_line_error(write(tmp_path, header), match=match)


def test_override_with_bad_value_is_reported() -> None:
    one_line_error(
        "free-motion", {"plant": {"bridge": {"volt2Nm": 0}}}, match=r"volt2Nm must be > 0"
    )


# --------------------------------------------------------------------------- shipped physics


def test_every_shipped_firmware_table_is_valid_firmware_configuration() -> None:
    for name in list_scenarios():
        scn = load_scenario(name)
        from_dict(FirmwareConfig, scn.firmware, "firmware")
        assert scn.description, name


class Trace:
    """Plant-only run of a scenario (no CAN): the firmware's reference through the DAC,
    held over each sample period; arrays per 1 ms sample."""

    def __init__(self, name: str, dt: float = 1e-3) -> None:
        self.scn = scn = load_scenario(name)
        fw = from_dict(FirmwareConfig, scn.firmware, "firmware")
        ref = ReferenceGenerator(fw.reference, fw.sample_period_s)
        plant = Plant(scn.plant, seed=scn.seed)
        dac, adc = scn.plant.dac, scn.plant.adc
        per = round(fw.sample_period_s / dt)
        n = round(scn.duration_s / fw.sample_period_s)
        cols = ("t", "w_m", "w_out", "th_out", "T_true", "T_meas", "mis", "i", "load")
        self.__dict__.update({c: np.empty(n * per if c == "T_true" else n) for c in cols})
        self.t_fine = np.empty(n * per)
        gain = scn.plant.bridge.volt2Nm
        for k in range(n):
            volts = dac.to_volts(dac.to_counts(ref.value(k)))
            for j in range(per):
                plant.advance(volts, dt)
                self.T_true[k * per + j] = plant.truth().T_true_Nm
                self.t_fine[k * per + j] = plant.time
            self.t[k] = plant.time
            truth = plant.truth()
            self.w_m[k] = truth.omega_motor_radps
            self.w_out[k] = truth.omega_output_radps
            self.th_out[k] = truth.theta_output_rad
            self.T_meas[k] = adc.to_volts(plant.sample()[0]) * gain
            self.mis[k] = truth.ripple.misalignment
            self.i[k] = truth.current_A
            self.load[k] = truth.tau_l_Nm
        self.plant = plant


@cache
def trace(name: str, dt: float = 1e-3) -> Trace:
    return Trace(name, dt)


def test_misalignment_scenario_fig_10() -> None:
    """Constant ~156 rad/s after a short acceleration, >= 3 output revolutions, expected
    torque constant, measured torque sinusoidal at the output angle with 10 Nm p-p."""
    tr = trace("misalignment")
    late = tr.t > 1.0
    assert tr.scn.duration_s >= 15.0
    assert np.mean(tr.w_m[late]) == pytest.approx(156.0, abs=4.0)
    assert np.ptp(tr.w_m[late]) < 0.01 * 156
    assert tr.th_out[-1] > 3 * 2 * math.pi
    assert np.ptp(tr.T_true[late]) < 0.1  # the true (expected) torque is constant
    # the measurement: fit DC + sinusoid at the output angle (+ nothing else)
    th, y = tr.th_out[late], tr.T_meas[late]
    basis = np.column_stack([np.ones_like(th), np.cos(th), np.sin(th)])
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    assert 2 * math.hypot(coef[1], coef[2]) == pytest.approx(10.0, abs=0.1)
    # it is at the output velocity: the spectral line sits at mean(w_out)
    spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(len(y)), n=1 << 18))
    freqs = 2 * math.pi * np.fft.rfftfreq(1 << 18, 1e-3)
    band = freqs < 20.0
    peak = freqs[band][np.argmax(spec[band])]
    assert peak == pytest.approx(np.mean(tr.w_out[late]), rel=0.03)
    assert 4.0 < np.ptp(tr.mis) / 2 <= 5.0 + 1e-9


def test_speed_chirp_sweeps_20_to_200_rad_s_and_back() -> None:
    tr = trace("speed-chirp")
    after = tr.t > 1.0
    w = tr.w_m[after]
    t = tr.t[after]
    assert np.max(w) == pytest.approx(200.0, abs=6.0)
    assert np.min(w) == pytest.approx(20.0, abs=4.0)
    assert t[np.argmax(w)] == pytest.approx(5.0, abs=0.5)
    assert t[np.argmin(w)] == pytest.approx(15.0, abs=0.5)
    bias = from_dict(FirmwareConfig, tr.scn.firmware).reference.bias_V
    assert w[-1] == pytest.approx(steady_state_motor_velocity(tr.scn.plant, bias), rel=0.05)
    assert np.max(np.abs(tr.i)) < tr.scn.plant.amplifier.current_limit_A

    # the ripple line sweeps with the speed: the 2x peak of the measured torque
    def line(t0: float) -> tuple[float, float]:
        sel = (tr.t > t0 - 0.25) & (tr.t < t0 + 0.25)
        y = tr.T_meas[sel]
        spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(len(y)), n=1 << 14))
        f = 2 * math.pi * np.fft.rfftfreq(1 << 14, 1e-3)
        return float(f[np.argmax(spec)]), float(np.mean(tr.w_m[sel]))

    for t0 in (5.0, 10.0, 14.0):
        peak, speed = line(t0)
        assert peak == pytest.approx(2 * speed, rel=0.05), t0


@pytest.mark.slow
def test_torque_steps_show_in_the_true_torque_with_flexspline_ringing() -> None:
    """Load steps make T_true step (~-d tau, most at once) and ring at the flexspline
    mode; the motor keeps running (no stall, current far from its limit)."""
    tr = trace("torque-steps", 1e-4)
    scn = tr.scn
    load = scn.plant.load
    d = scn.plant.drivetrain
    assert load.kind == "steps" and len(load.step_times_s) >= 4
    assert len({abs(b - a) for a, b in zip((0.0, *load.step_values_Nm[:-1]),
                                           load.step_values_Nm, strict=True)}) >= 3  # fmt: skip
    running = tr.t > 0.9
    assert np.min(tr.w_m[running]) > 90.0
    assert np.max(tr.w_m[running]) < 180.0
    assert np.max(np.abs(tr.i)) < 0.2 * scn.plant.amplifier.current_limit_A
    omega_n = d.natural_frequency_radps
    prev = 0.0
    for t_step, value in zip(load.step_times_s, load.step_values_Nm, strict=True):
        k = round(t_step / 1e-4)
        before = np.mean(tr.T_true[k - 500 : k - 10])
        after = np.mean(tr.T_true[k + 300 : k + 600])  # ringing gone (~6 ms decay)
        jump = after - before
        assert jump == pytest.approx(-(value - prev), rel=0.1)
        ring = tr.T_true[k : k + 300] - after
        overshoot = -np.sign(value - prev) * ring
        assert np.max(overshoot) > 0.25 * abs(jump)  # rings past the new level
        crossings = np.flatnonzero(np.diff(np.sign(ring)) != 0)
        period = 2 * np.mean(np.diff(crossings[:4])) * 1e-4
        assert 2 * math.pi / period == pytest.approx(omega_n, rel=0.1)
        prev = value
