"""hdhil.core.expm: scipy.linalg.expm bitwise, on every shipped scenario's plant."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.core import expm as expm_mod
from hdhil.core.expm import expm
from hdhil.firmware import tracking
from hdhil.firmware.tracking import TrackingPlant
from hdhil.hostsim.plant import Plant, linear
from hdhil.hostsim.plant.config import LinkMotionConfig, LoadTorqueConfig
from hdhil.rig.scenario import list_scenarios, load_scenario


def same_bits(x: np.ndarray, y: np.ndarray) -> bool:
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def plant_matrices(monkeypatch: pytest.MonkeyPatch) -> list[np.ndarray]:
    """Every matrix the shipped scenarios' plants exponentiate (free link, prescribed
    sine and hold, a person), at their step sizes."""
    seen: list[np.ndarray] = []

    def spy(a: np.ndarray) -> np.ndarray:
        seen.append(np.array(a))
        return scipy.linalg.expm(a)

    monkeypatch.setattr(linear, "expm", spy)
    for name in list_scenarios():
        scenario = load_scenario(name)
        cfg = scenario.plant
        if cfg.link.worn or cfg.link.holds_weight:  # a person wears the arm: its actuator
            cfg = dataclasses.replace(cfg, link=LinkMotionConfig())
        dt = scenario.firmware.sample_period_s
        prescribed = [LinkMotionConfig(kind=kind) for kind in ("sine", "hold", "person")]
        configs = [cfg] + [
            dataclasses.replace(cfg, link=link, load=LoadTorqueConfig()) for link in prescribed
        ]
        for c in configs:
            plant = Plant(c)
            plant.prepare(dt)
            plant.advance(0.1, dt)
    monkeypatch.undo()
    return seen


def test_shipped_plants_exponentiate_bitwise_as_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    matrices = plant_matrices(monkeypatch)
    assert len(matrices) >= len(list_scenarios())
    if expm_mod.scipy_kernel() is None:
        pytest.skip("this scipy's expm is not the wrapper hdhil.core.expm repeats")
    for a in matrices:
        assert expm_mod._generic(a)  # the kernel path, not the fallback
        assert same_bits(expm(a), scipy.linalg.expm(a))


def test_tracking_plant_exponentiates_bitwise_as_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[np.ndarray] = []
    monkeypatch.setattr(tracking, "expm", lambda a: seen.append(np.array(a)) or expm(a))
    for plant in (TrackingPlant(), TrackingPlant(current_lag_s=0.0)):
        plant.discrete(1e-3)
    assert len(seen) == 2
    for a in seen:
        assert same_bits(expm(a), scipy.linalg.expm(a))


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(2, 9),
    scale=st.sampled_from([1e-6, 1e-3, 1.0, 10.0, 50.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_random_matrices_bitwise_as_scipy(n: int, scale: float, seed: int) -> None:
    """Small and large norms: no squaring, and many squarings."""
    a = np.random.default_rng(seed).standard_normal((n, n)) * scale
    assert same_bits(expm(a), scipy.linalg.expm(a))


@pytest.mark.parametrize(
    "a",
    [
        np.triu(np.arange(1.0, 10.0).reshape(3, 3)),  # triangular: scipy's own branch
        np.diag([1.0, -2.0, 0.5]),  # diagonal
        np.array([[0.0, 1.0], [-1.0, 0.0]], dtype=np.float32),
        np.array([[0.0, 1j], [1j, 0.0]]),
        np.ones((2, 3, 3)),  # batched
        np.array([[2.0]]),
    ],
)
def test_other_inputs_go_to_scipy(a: np.ndarray) -> None:
    assert not expm_mod._generic(a)
    assert same_bits(expm(a), scipy.linalg.expm(a))


def test_other_scipy_releases_go_to_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the kernel (another scipy release), scipy.linalg.expm does the work."""
    monkeypatch.setattr(expm_mod, "scipy_kernel", lambda: None)
    calls = []
    real = scipy.linalg.expm
    monkeypatch.setattr(scipy.linalg, "expm", lambda a: calls.append(a) or real(a))
    a = np.array([[0.0, 1.0], [-4.0, -0.1]])
    assert same_bits(expm(a), real(a))
    assert len(calls) == 1


def test_release_parsing() -> None:
    assert expm_mod._release("1.17.1") == (1, 17)
    assert expm_mod._release("1.18.0rc1") == (1, 18)
    assert expm_mod._release("2") is None
    assert (1, 18) not in expm_mod.WRAPPER_RELEASES


def test_release_read_as_scipy_reads_it() -> None:
    """The release in the package's version.py is scipy.__version__'s."""
    import scipy

    text = (Path(scipy.__file__).parent / "version.py").read_text(encoding="utf-8")
    match = expm_mod._VERSION.search(text)
    assert match is not None
    assert match.group(1) == scipy.__version__
    assert (expm_mod.scipy_kernel() is not None) == (
        expm_mod._release(scipy.__version__) in expm_mod.WRAPPER_RELEASES
    )


def test_kernel_leaves_sys_modules_as_it_found_them() -> None:
    """Loading the kernel alone adds no scipy.linalg submodule to sys.modules, and
    keeps scipy.linalg's own where scipy.linalg is imported (as it is here)."""
    import sys

    name = "scipy.linalg._matfuncs_expm"
    own = sys.modules[name]
    expm_mod.scipy_kernel.cache_clear()
    try:
        kernel = expm_mod.scipy_kernel()
        assert sys.modules[name] is own
        if kernel is not None:
            a = np.array([[0.0, 1.0], [-4.0, -0.1]])
            assert same_bits(expm(a), scipy.linalg.expm(a))
    finally:
        expm_mod.scipy_kernel.cache_clear()
