"""[Vertechy] Fig. 8 computed without hdhil (tools/docs/independent/vertechy_fig8.py)
against the project's ``lqg-experiment`` run."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import sys
from pathlib import Path

import pytest

from hdhil.cli import main
from hdhil.firmware.lqg_design import JointParams, LqgWeights, design_lqg
from hdhil.rig.scenario import load_scenario

_PATH = Path(__file__).resolve().parents[1] / "tools" / "docs" / "independent" / "vertechy_fig8.py"


def _module():
    spec = importlib.util.spec_from_file_location("vertechy_fig8_standalone", _PATH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look the module up by name
    spec.loader.exec_module(mod)
    return mod


def test_the_independent_computation_imports_no_hdhil() -> None:
    text = _PATH.read_text(encoding="utf-8")
    assert "hdhil" not in "\n".join(
        line for line in text.splitlines() if line.lstrip().startswith(("import ", "from "))
    )


@pytest.mark.slow
def test_independent_design_gives_the_firmware_gains() -> None:
    """The LQ gains and the Kalman gain from the paper's Eqs. 3-8 alone are the ones
    the firmware's design computes."""
    m = _module()
    s = m.Fig8Setup()
    d = design_lqg(JointParams(s.Jm, s.Jl, s.k, s.c), LqgWeights(s.q1, s.q2, s.W, s.V), Ts=s.Ts)
    g = d.gains
    assert m.lq_gains(s) == pytest.approx((g.k1, g.k2, g.k3, g.k4), rel=1e-6)
    assert tuple(m.kalman_gain(s)) == pytest.approx(tuple(d.L), rel=1e-6)


def test_independent_friction_readings() -> None:
    m = _module()
    tanh_, fade = m.Fig8Setup(model="tanh"), m.Fig8Setup(model="fade-in")
    assert m.friction_model(fade, 8.0) == pytest.approx(-13.7 / 2)
    assert abs(m.friction_model(fade, 1.0)) < 0.02
    assert m.friction_model(tanh_, 1.0) == pytest.approx(-13.7 * 0.46211715726)
    with pytest.raises(ValueError, match="fade-in"):
        m.friction_model(m.Fig8Setup(model="sgn"), 1.0)


@pytest.mark.slow
def test_independent_fig8_agrees_with_the_project_run() -> None:
    """10 s of the experiment both ways.  They differ in what the independent model
    leaves out (ADC/DAC quantisation, the noise sequence, the CAN loop), so: max |τm|
    within 3 Nm, the shares of |e| <= 0.5 Nm within 2 points, max |τ̂l − τl| within
    0.5 Nm."""
    m = _module()
    ind = m.simulate(m.Fig8Setup(duration_s=10.0))
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["run", "--scenario", "lqg-experiment", "--duration", "10", "--json"]) == 0
    row = json.loads(buf.getvalue())["tracking"]
    assert ind.max_abs_tau_m == pytest.approx(row["max_abs_tau_m"], abs=3.0)
    assert ind.within_true == pytest.approx(row["share_within_goal"], abs=0.02)
    assert ind.within_measured == pytest.approx(row["share_within_goal_measured"], abs=0.02)
    assert ind.max_abs_tau_l_err == pytest.approx(row["max_external_error"], abs=0.5)


def test_independent_setup_is_the_scenario() -> None:
    """The independent defaults are the scenario's plant: the motor friction exact (no
    viscous term) and the output bearings' Coulomb friction before the handle."""
    m = _module()
    s = m.Fig8Setup()
    plant = load_scenario("lqg-experiment").plant
    d, link = plant.drivetrain, plant.link
    assert s.viscous_Nm_per_motor_radps == d.b_motor / d.gear_ratio
    assert (s.coulomb_Nm, s.velocity_scale_radps) == (
        d.coulomb_motor,
        d.friction_smoothing * d.gear_ratio,
    )
    assert (s.link_coulomb_Nm, s.link_smoothing_radps) == (
        link.bearing_coulomb_Nm,
        link.bearing_smoothing_radps,
    )
    assert (s.W, plant.sensors.torque_noise_Nm) == (0.12, 0.12)
