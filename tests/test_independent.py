"""The independent re-computations (``tools/docs/independent/``, numpy and scipy only)
against what the documentation states and, where the two should agree, against hdhil."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import re
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
INDEPENDENT = ROOT / "tools" / "docs" / "independent"
PAPERS = ROOT / "docs" / "papers.md"


def _module(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"independent_{name}", INDEPENDENT / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while defined
    spec.loader.exec_module(module)
    return module


fig5 = _module("vertechy_fig5")
fig7 = _module("vertechy_fig7")
gains = _module("vertechy_gains")


def test_independent_modules_import_no_hdhil() -> None:
    for path in INDEPENDENT.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert not re.search(r"^\s*(from|import)\s+hdhil", text, re.M), path.name


@pytest.fixture(scope="module")
def figures() -> dict[str, float]:
    return fig7.figures()


def _doc_row(label: str) -> str:
    """The cells after ``label`` in docs/papers.md's table row that starts with it."""
    for line in PAPERS.read_text(encoding="utf-8").splitlines():
        if line.startswith(f"| {label}"):
            return line
    raise AssertionError(f"docs/papers.md has no table row starting with {label!r}")


def _numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"(?<![\w.])\d+\.\d+", text)]


def test_fig7_bounds_are_the_ones_the_docs_state(figures: dict[str, float]) -> None:
    """docs/papers.md states the perfect-state bound, the ideal continuous LQG and the
    two readings that approach 0.3 Nm: they are what the independent script computes."""
    assert _numbers(_doc_row("JTF1, printed k1..k4, perfect state"))[-1] == round(
        figures["perfect_state"], 2
    )
    assert _numbers(_doc_row("JTF1, printed k1..k4 and L"))[-1] == round(figures["ideal_lqg"], 2)
    jtf3, jtf2 = _numbers(_doc_row("JTF3 / JTF2 on the same observer"))
    assert (jtf3, jtf2) == (round(figures["ideal_jtf3"], 2), round(figures["ideal_jtf2"], 2))
    assert _numbers(_doc_row("`lqg-tracking-slow-link`"))[1] == round(figures["slow_link"], 2)
    assert _numbers(_doc_row("`lqg-tracking-squared-weights`"))[0] == round(
        figures["squared_weights"], 2
    )


def test_fig7_printed_gains_cannot_reach_the_printed_figure(figures: dict[str, float]) -> None:
    """Even with perfect state estimates the printed gains leave more than 0.3 Nm, and the
    ranking JTF1 < JTF3 < JTF2 holds on the ideal LQG."""
    assert figures["perfect_state"] > 0.3
    assert figures["perfect_state"] < figures["ideal_lqg"]
    assert figures["ideal_lqg"] < figures["ideal_jtf3"] < figures["ideal_jtf2"]
    assert figures["slow_link"] < 0.35 and figures["squared_weights"] < 0.35


def test_fig7_steady_state_matches_a_time_simulation() -> None:
    """The closed form is the steady state of the loop: a plain ODE integration (scipy)
    of the perfect-state loop lands on it."""
    from scipy.integrate import solve_ivp

    k1, k2, k3, k4 = fig7.PRINTED_K
    jm, jl, k, c = fig7.JM, fig7.JL, fig7.K, fig7.C
    a, w = math.radians(20.0), 2 * math.pi

    def rhs(t: float, x: np.ndarray) -> list[float]:
        th, thd, thdd = a * math.sin(w * t), a * w * math.cos(w * t), -a * w * w * math.sin(w * t)
        ts, tsd = k * (th - x[0]), k * (thd - x[1])
        tlgd = jl * thdd + ts + c / k * tsd
        sd = 20 * math.sin(0.4 * math.pi * t)
        tau_m = -(k1 * (ts - sd) + k2 * tsd + k3 * tlgd + k4 * sd)
        return [x[1], (tau_m + ts + c / k * tsd) / jm]

    t = np.linspace(1.0, 6.0, 10001)
    sol = solve_ivp(rhs, (0.0, 6.0), [0.0, a * w], t_eval=t, method="LSODA", rtol=1e-9,
                    atol=1e-12)  # fmt: skip
    th = a * np.sin(w * t)
    e = k * (th - sol.y[0]) - 20 * np.sin(0.4 * np.pi * t)
    assert np.max(np.abs(e)) == pytest.approx(fig7.max_error(observer=None), abs=2e-3)


@pytest.mark.slow
def test_fig7_agrees_with_the_firmware_loop(figures: dict[str, float]) -> None:
    """hdhil's firmware loop (``firmware.tracking``: the torque-control stage at 1 kHz)
    with the command acting in its own sample is the sampled version of the ideal LQG:
    within 0.05 Nm of it for every law and reading, scored over the inputs' whole period."""
    from hdhil.firmware.config import ControlConfig, Law
    from hdhil.firmware.lqg_design import LqgWeights
    from hdhil.firmware.tracking import TrackingPlant, simulate_tracking

    base = ControlConfig(law=Law.JTF1, torque_per_volt=20.0, torque_limit_Nm=150.0,
                         delay_samples=0)  # fmt: skip

    def e(control: ControlConfig, law: Law | None = None, link_Hz: float = 1.0) -> float:
        period = 10.0 if link_Hz == 0.5 else 5.0
        r = simulate_tracking(control, 2.0 + period, TrackingPlant(link_frequency_Hz=link_Hz),
                              law=law, evaluate_from_s=2.0)  # fmt: skip
        return r["max_abs_e"]

    squared = dataclasses.replace(base, weights=LqgWeights(q1=500.0**2, q2=0.1**2))
    assert e(base) == pytest.approx(figures["ideal_lqg"], abs=0.05)
    assert e(base, Law.JTF2) == pytest.approx(figures["ideal_jtf2"], abs=0.05)
    assert e(base, Law.JTF3) == pytest.approx(figures["ideal_jtf3"], abs=0.05)
    assert e(base, link_Hz=0.5) == pytest.approx(figures["slow_link"], abs=0.05)
    assert e(squared) == pytest.approx(figures["squared_weights"], abs=0.05)


def test_gains_equal_hdhil_design() -> None:
    """scipy's Riccati solvers on the paper's model give hdhil's k1..k4 and L (the same
    reading: Q = diag(q1, q2)), the printed ones within 1.7 % (0.22 % with Jl = 0.7125),
    and Eq. 6's squared weights give the design hdhil runs in lqg-tracking-squared-weights."""
    from hdhil.firmware.lqg_design import JointParams, LqgWeights, design_kalman, design_lq

    k = gains.lq_gains()
    d = design_lq(JointParams(), LqgWeights())
    assert k == pytest.approx([d.k1, d.k2, d.k3, d.k4], rel=1e-6)
    assert gains.kalman_gain() == pytest.approx(
        np.ravel(design_kalman(JointParams(), LqgWeights().W, LqgWeights().V)), rel=1e-6
    )
    assert k == pytest.approx(gains.PRINTED_K, rel=0.017)
    assert gains.lq_gains(jl=0.7125) == pytest.approx(gains.PRINTED_K, rel=0.0022)
    assert gains.kalman_gain(jl=0.7125) == pytest.approx(gains.PRINTED_L, rel=0.0022)
    sq = design_lq(JointParams(), LqgWeights(q1=500.0**2, q2=0.1**2))
    assert gains.lq_gains(squared=True) == pytest.approx([sq.k1, sq.k2, sq.k3, sq.k4], rel=1e-6)
    assert fig7.lq_gains_squared() == pytest.approx(gains.lq_gains(squared=True), rel=1e-9)


@pytest.mark.slow  # imports scipy.signal (about 1 s)
def test_fig5_half_power_equals_hdhil_method_on_the_exact_response() -> None:
    """hdhil's half-power method (``hdhil identify``) applied to the exact magnitude of
    Eq. 2 gives the independent figures; fn is the documented 17.08 Hz."""
    from hdhil.analysis.identification import FrequencyResponse, half_power

    assert round(fig5.natural_frequency_Hz(), 2) == 17.08
    j = fig5.JM * fig5.JL / (fig5.JM + fig5.JL)
    f = np.linspace(0.0, 50.0, 5001)
    s = 2j * np.pi * f
    H = (fig5.K / fig5.JM) / (s * s + (fig5.C / j) * s + fig5.K / j)
    ones = np.ones_like(f)
    fr = FrequencyResponse(f=f, H=H, pxx=ones, coherence=ones, band=(1, len(f) - 1),
                           nperseg=len(f), fs=1000.0)  # fmt: skip
    hp = half_power(fr)
    fp, c = fig5.half_power()
    assert hp.fn_Hz == pytest.approx(fp, abs=0.01)
    assert 2 * hp.zeta * (2 * np.pi * hp.fn_Hz) * j == pytest.approx(c, rel=3e-3)
    assert hp.fn_exact_Hz == pytest.approx(fig5.natural_frequency_Hz(), rel=1e-3)
