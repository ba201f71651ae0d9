"""[Vertechy] joint-torque control laws in the firmware, closed over the CAN link.

Configuration (firmware.config.ControlConfig), the controller node's torque-control
telemetry (CTRL_TPDO2), the lqg-tracking scenario, and the §VI tracking figures of
firmware.tracking, checked against the emulator's plant closed around the interrupt
handler.
"""

from __future__ import annotations

import dataclasses
import math

import can
import cantools
import numpy as np
import pytest
from conftest import BusHarness
from runs import lockstep

from hdhil.can.busload import schedule_load
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.dbc import codec, database, dbc_path
from hdhil.firmware.config import (
    JTF1_FF_TRACKING,
    ControlConfig,
    DesiredTorqueConfig,
    FirmwareConfig,
    Law,
    Wave,
)
from hdhil.firmware.controller import ControllerNode
from hdhil.firmware.isr import AdcSample, InterruptHandler
from hdhil.firmware.lqg_design import ControlLaw, Feedforward, LqgWeights, ObserverMethod
from hdhil.firmware.tracking import TrackingPlant, simulate_tracking, tracking_table
from hdhil.hostsim.plant import Plant
from hdhil.rig.scenario import load_scenario

#: The seed's design on the lqg-tracking actuator (20 Nm/V, 150 Nm).
SEED = ControlConfig(law=Law.JTF1, torque_per_volt=20.0, torque_limit_Nm=150.0)
FF = dataclasses.replace(JTF1_FF_TRACKING, torque_per_volt=20.0, torque_limit_Nm=150.0)
#: The emulator's sensor and amplifier in lqg-tracking: 12-bit ADC at 12 Nm/V, 0.4 ms lag.
OUR_PLANT = TrackingPlant(adc_lsb_Nm=12.0 * 10.0 / 2048, current_lag_s=4e-4)


# ----------------------------------------------------------------------------- configuration


def test_law_is_a_plain_integer_code() -> None:
    assert [int(law) for law in Law] == [0, 1, 2, 3, 4]
    assert Law.NONE.control_law is None
    assert [law.control_law for law in Law if law is not Law.NONE] == list(ControlLaw)
    # by name in a scenario, by code as an SDO would write it
    assert from_dict(ControlConfig, {"law": "jtf1_ff"}).law is Law.JTF1_FF
    assert from_dict(ControlConfig, {"law": 3}).law is Law.JTF2


def test_control_config_from_plain_data() -> None:
    cfg = from_dict(
        FirmwareConfig,
        {
            "control": {
                "law": "jtf1",
                "feedforward": "exact",
                "observer": "zoh-observer",
                "joint": {"Jl": 1.2},
                "weights": {"V": 1e5},
                "desired": {"wave": "square", "amplitude_Nm": 5.0, "frequency_Hz": 0.5},
                "torque_per_volt": 20.0,
                "torque_limit_Nm": 150.0,
            }
        },
    )
    c = cfg.control
    assert c.active and c.feedforward is Feedforward.EXACT
    assert c.observer is ObserverMethod.ZOH_OBSERVER
    assert c.joint.Jl == 1.2 and c.joint.Jm == 2.5 and c.weights == LqgWeights(V=1e5)
    assert c.desired.wave is Wave.SQUARE and c.desired.reference().amplitude_V == 5.0
    isr = InterruptHandler(cfg)
    assert isr.control.design.params.Jl == 1.2


def test_defaults_are_the_seeds() -> None:
    c = ControlConfig()
    assert c.law is Law.NONE
    assert (c.joint.Jm, c.joint.Jl, c.joint.k, c.joint.c) == (2.5, 0.7, 6300.0, 11.8)
    assert c.weights == LqgWeights(q1=500.0, q2=0.1, W=0.12, V=1e4)
    assert c.feedforward is Feedforward.LQ and c.delay_samples == 1 and c.predict
    d = c.desired  # seed tau_sD = +20 sin(0.4 pi t) = product sign -20 sin(0.4 pi t)
    assert (d.wave, d.amplitude_Nm, d.frequency_Hz, d.bias_Nm) == (Wave.SINE, -20.0, 0.2, 0.0)


@pytest.mark.parametrize(
    "data, match",
    [
        ({"law": "jtf9"}, "control.law"),
        ({"delay_samples": 2}, "delay_samples"),
        ({"feedback": "T_true"}, "feedback"),
        ({"torque_per_volt": 0.0}, "torque_per_volt"),
        ({"torque_limit_Nm": -1.0}, "torque_limit_Nm"),
        ({"weights": {"V": 0.0}}, "V"),
        ({"desired": {"frequency_Hz": 0.0}}, "frequency"),
        ({"predict": 1}, "predict"),
    ],
)
def test_bad_control_values_are_one_line_errors(data: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        from_dict(FirmwareConfig, {"control": data}, "firmware")


# ----------------------------------------------------------------------------- telemetry frame


def test_ctrl_tpdo2_layout_and_codec_agree_with_cantools() -> None:
    msg = database("control").get_message_by_name("CTRL_TPDO2")
    assert msg.frame_id == 0x281 and msg.length == 8 and msg.cycle_time == 1
    assert [(s.name, s.start, s.length, s.is_signed, s.scale) for s in msg.signals] == [
        ("dtau_s_hat", 0, 16, True, 0.05),
        ("tau_lgd_hat", 16, 16, True, 0.004),
        ("tau_sD", 32, 16, True, 0.004),
        ("e_hat", 48, 16, True, 0.001),
    ]
    assert all(s.comment for s in msg.signals) and msg.comment
    fast = codec("control", "CTRL_TPDO2")
    values = (-123.45, 9.632, -19.996, 0.287)
    data = fast.encode(*values)
    ref = cantools.database.load_file(str(dbc_path("control")))
    decoded = ref.decode_message(0x281, data)
    for name, v, back in zip(fast.signal_names, values, fast.decode(data), strict=True):
        assert back == pytest.approx(v, abs=0.026)
        assert decoded[name] == pytest.approx(back)
    assert fast.decode(fast.encode(5000.0, 0, 0, -40.0))[::3] == pytest.approx((1638.35, -32.768))


def test_bus_load_with_the_control_telemetry() -> None:
    load = schedule_load("control", 1_000_000, 1e-3)
    # SYNC 62 + DRIVE_TPDO1 132 + DRIVE_RPDO1 102 + CTRL_TPDO1 132 + CTRL_TPDO2 132 us
    assert load.worst_case_load == pytest.approx(560 / 1000)
    assert load.fits()


def _run_node(cfg: FirmwareConfig, cycles: int = 5) -> list[can.Message]:
    """The controller node on a simulated bus, fed sensor frames; what it sent."""
    with BusHarness("t-ctrl-node") as harness:  # the host plays the drive
        node = ControllerNode(harness.bus(), cfg)
        sensor = codec("control", "DRIVE_TPDO1")
        for k in range(cycles):
            node.send_sync()
            harness.send(sensor.frame_id, sensor.encode(100 + k, 20, 0, 7 * k))
            node.poll()
            harness.frames()
        return harness.recorder.messages


def test_node_sends_ctrl_tpdo2_only_with_a_law() -> None:
    """Over the bus, from boot: CTRL_TPDO2 once per operational cycle with a law, else never.

    (That its content is the handler's output is tested in tests/test_controller_canopen.py.)
    """
    from hdhil.rig.scenario import load_scenario

    def frames(name: str) -> tuple[dict[str, int], int]:
        r = lockstep(load_scenario(name), duration_s=0.05, trace=None, evaluate=False)
        return {n.split()[-1]: c for n, c in r.frames.items()}, r.cycles

    plain, _ = frames("free-motion")
    assert "CTRL_TPDO2" not in plain and plain["CTRL_TPDO1"] == 50
    controlled, cycles = frames("lqg-tracking")
    assert controlled["CTRL_TPDO2"] == controlled["CTRL_TPDO1"] == cycles == 50


# ----------------------------------------------------------------------------- tracking (§VI)


@pytest.fixture(scope="module")
def table() -> dict[str, dict]:
    return {row["law"]: row for row in tracking_table()}


@pytest.mark.slow
def test_seed_fig7_ranking_and_the_feedforward_reaches_0_3_nm(table) -> None:
    """[Vertechy] §VI: JTF1 < JTF3 < JTF2 in tracking error; JTF1 + feedforward <= 0.3 Nm."""
    e = {law: row["max_abs_e"] for law, row in table.items()}
    rms = {law: row["rms_e"] for law, row in table.items()}
    assert e["jtf1"] < e["jtf3"] < e["jtf2"]
    assert rms["jtf1"] < rms["jtf3"] < rms["jtf2"]
    assert e["jtf1"] == pytest.approx(1.21, abs=0.05)  # not the printed 0.3 Nm
    assert e["jtf2"] == pytest.approx(5.36, abs=0.1)
    assert e["jtf3"] == pytest.approx(2.13, abs=0.05)
    assert e["jtf1_ff (tuned)"] <= 0.3 and rms["jtf1_ff (tuned)"] < 0.15
    assert all(row["saturations"] == 0 for row in table.values())
    # the command stays within what the actuator can give (seed Fig. 8: about 40 Nm)
    assert all(35.0 < row["max_abs_tau_m"] < 60.0 for row in table.values())


@pytest.mark.slow
def test_feedforward_reaches_0_3_nm_on_the_emulators_sensor_and_amplifier() -> None:
    r = simulate_tracking(FF, 5.0, OUR_PLANT)
    assert r["max_abs_e"] <= 0.3
    assert simulate_tracking(SEED, 5.0, OUR_PLANT)["max_abs_e"] > 1.0


@pytest.mark.parametrize(
    "change",
    [
        {"law": Law.JTF1},  # no tau_sD' feedforward
        {"feedforward": Feedforward.LQ},  # the LQ compromise instead of exact gains
        {"weights": LqgWeights()},  # the seed's V = 1e4
    ],
    ids=["no-dtau_sD-ff", "lq-gains", "seed-V"],
)
def test_each_part_of_the_feedforward_configuration_is_needed(change: dict) -> None:
    assert simulate_tracking(dataclasses.replace(FF, **change))["max_abs_e"] > 0.3


@pytest.mark.slow
def test_the_seeds_feedforward_alone_makes_jtf1_worse(table) -> None:
    alone = simulate_tracking(SEED, law=Law.JTF1_FF)["max_abs_e"]
    assert alone > table["jtf1"]["max_abs_e"]


@pytest.mark.slow
def test_jtf1_error_is_the_observer_lag_of_the_link_jerk() -> None:
    """Why JTF1 misses 0.3 Nm: e ≈ 17 ms · dτlgd/dt with τlgd ∋ Jl θl'' (Wiener model of
    Eq. 7): the link-motion error scales with the cube of the link frequency; with the
    link held the seed's 0.3 Nm holds."""
    quiet = DesiredTorqueConfig(wave=Wave.NONE)
    link_only = dataclasses.replace(SEED, desired=quiet)
    lag = {}
    for f in (1.0, 0.5):
        e = simulate_tracking(
            link_only, 6.0, TrackingPlant(link_frequency_Hz=f), evaluate_from_s=2.0
        )["max_abs_e"]
        jerk_torque = 0.7 * math.radians(20.0) * (2 * math.pi * f) ** 3  # Jl A ω³
        lag[f] = e / jerk_torque
    assert lag[1.0] == pytest.approx(0.017, abs=0.001)
    assert lag[0.5] == pytest.approx(0.019, abs=0.0015)
    held = simulate_tracking(SEED, 5.0, TrackingPlant(link_amplitude_deg=0.0))
    assert held["max_abs_e"] == pytest.approx(0.18, abs=0.01)


@pytest.mark.slow
def test_12_bit_dac_quantisation_is_not_the_limit() -> None:
    coarse = simulate_tracking(FF)["max_abs_e"]
    fine = simulate_tracking(FirmwareConfig(control=FF, dac=_dac16()))["max_abs_e"]
    assert abs(coarse - fine) < 0.005


def _dac16():
    from hdhil.core.converter import Converter

    return Converter(bits=16)


@pytest.mark.slow
def test_immediate_actuation_and_noise_variants() -> None:
    immediate = dataclasses.replace(FF, delay_samples=0, predict=False)
    assert simulate_tracking(immediate)["max_abs_e"] <= 0.3
    # seed sensor noise W = 0.12 Nm rms per sample (not in the seed's simulation): the
    # faster observer pays in precision, RMS e about twice the seed design's noise part
    noisy = TrackingPlant(noise_Nm=0.12, seed=3)
    quiet = DesiredTorqueConfig(wave=Wave.NONE)
    still = dataclasses.replace(noisy, link_amplitude_deg=0.0)
    n_seed = simulate_tracking(dataclasses.replace(SEED, desired=quiet), 5.0, still)["rms_e"]
    n_ff = simulate_tracking(dataclasses.replace(FF, desired=quiet), 5.0, still)["rms_e"]
    assert 0.03 < n_seed < n_ff < 3 * n_seed


def test_simulate_tracking_records_and_validates() -> None:
    r = simulate_tracking(SEED, 2.0, record=True)
    assert r["law"] == "jtf1" and r["samples"] == 1000 and len(r["t"]) == 2000
    e = r["T"][1000:] - r["T_D"][1000:]
    assert np.max(np.abs(e)) == pytest.approx(r["max_abs_e"])
    assert np.max(np.abs(r["T_hat"][1000:] - r["T_D"][1000:])) == pytest.approx(r["max_abs_e_hat"])
    with pytest.raises(ValueError, match="control law"):
        simulate_tracking(ControlConfig())
    with pytest.raises(ValueError, match="evaluate_from_s"):
        simulate_tracking(SEED, 1.0, evaluate_from_s=2.0)


# ----------------------------------------------------------------------------- the scenario


def test_lqg_tracking_scenario_is_the_seeds_simulation() -> None:
    sc = load_scenario("lqg-tracking")
    fw = from_dict(FirmwareConfig, sc.firmware, "firmware")
    c, p = fw.control, sc.plant
    assert c.law is Law.JTF1 and c.weights == LqgWeights()
    # the firmware's actuator calibration and limit are the drive's
    assert c.torque_per_volt == pytest.approx(p.torque_per_volt) == 20.0
    assert c.torque_limit_Nm == pytest.approx(p.max_motor_torque_Nm)
    assert fw.calibration.volt2Nm == p.bridge.volt2Nm
    d = p.drivetrain
    assert (d.J_motor, d.J_load, d.k_flex, d.c_flex) == (
        c.joint.Jm,
        c.joint.Jl,
        c.joint.k,
        c.joint.c,
    )
    assert (p.link.kind, p.link.amplitude_deg, p.link.frequency_Hz) == ("sine", 20.0, 1.0)
    assert p.sensors.torque_noise_Nm == 0.0 and p.sensors.torque_measures == "spring"
    assert d.coulomb_motor == 0.0 and p.gravity.mgl_Nm == 0.0  # tau_d = tau_g = 0
    assert 0 < sc.evaluate_from_s < sc.duration_s


def _closed_on_the_emulator(overrides: dict | None = None, duration_s: float = 5.0) -> float:
    """The emulator's plant closed around the interrupt handler, without the bus, with
    the drive's synchronous-RPDO timing (command of sample k active from t(k+1))."""
    sc = load_scenario("lqg-tracking", overrides)
    fw = from_dict(FirmwareConfig, sc.firmware, "firmware")
    plant, isr = Plant(sc.plant, sc.seed), InterruptHandler(fw)
    Ts = fw.sample_period_s
    active = latched = 0.0
    errors = []
    for k in range(round(duration_s / Ts)):
        if k:
            plant.advance(active, Ts)
        counts = plant.sample()
        active = latched
        out = isr(AdcSample(*counts))
        latched = sc.plant.dac.to_volts(out.dac_counts)
        errors.append(plant.truth().T_true_Nm - out.tau_sD)
    return float(np.max(np.abs(errors[round(sc.evaluate_from_s / Ts) :])))


@pytest.mark.slow
def test_pure_simulation_agrees_with_the_emulator() -> None:
    ff = {
        "firmware": {"control": {"law": "jtf1_ff", "feedforward": "exact", "weights": {"V": 1e7}}}
    }
    on_emulator = {"jtf1": _closed_on_the_emulator(), "ff": _closed_on_the_emulator(ff)}
    pure = {
        "jtf1": simulate_tracking(SEED, 5.0, OUR_PLANT)["max_abs_e"],
        "ff": simulate_tracking(FF, 5.0, OUR_PLANT)["max_abs_e"],
    }
    assert on_emulator["jtf1"] == pytest.approx(pure["jtf1"], abs=0.02)
    assert on_emulator["ff"] == pytest.approx(pure["ff"], abs=0.02)
    assert on_emulator["ff"] <= 0.3 < on_emulator["jtf1"]
