"""How N joints per 1 kHz cycle are best stepped: N scalar calls or one array step.

An arm emulated in one process runs N joints per cycle; per joint the drive side steps
the plant (:meth:`Plant.advance` + :meth:`Plant.sample`) and the firmware side runs its
ripple filter (:class:`HarmonicKalman`, our design after [Taghirad97]).  Both are
scalar straight-line Python, so N joints cost N times one.  Vectorised with numpy, a
step costs about a microsecond per array operation whatever N, so it loses for small N
and wins for large N.  :func:`joint_scaling` measures, in one process and interleaved,
per cycle and for each N:

- ``plant_scalar_us``: N :class:`Plant` objects, ``advance`` + ``sample`` each;
- ``plant_vector_us``: one :class:`~hdhil.hostsim.plant.bank.PlantBank` step of the same
  N joints (the same equations over arrays, sensor read-out included);
- ``filter_scalar_us``: N :meth:`HarmonicKalman.step` calls;
- ``filter_vector_us``: :class:`KalmanBank`, the same filter over N joints as arrays
  (the kernel's upper-triangle covariance as an (N, n(n+1)/2) array).

Each figure is the median over repeats of the mean over a block of cycles; the variants
take turns within each repeat.  :func:`crossover` reads the smallest N from which the
array step wins.  ``docs/design.md`` ("Stepping several joints") has the table and the
decision it led to; ``hdhil bench`` can print the rows (:func:`format_joint_scaling`).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from hdhil.analysis.tables import markdown_table
from hdhil.firmware.config import FirmwareConfig, RippleFilterConfig
from hdhil.firmware.ripple import HarmonicKalman
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.hostsim.plant.bank import PlantBank

__all__ = [
    "DEFAULT_JOINTS",
    "KalmanBank",
    "crossover",
    "format_joint_scaling",
    "joint_scaling",
]

#: The joint counts of the comparison: one joint, the arms of 2-7 joints, and beyond.
DEFAULT_JOINTS: tuple[int, ...] = (1, 2, 4, 7, 16, 32)
_DT = 1e-3


class KalmanBank:
    """:class:`HarmonicKalman` over N joints as numpy arrays (all joints one config).

    The same equations as the generated scalar kernel: regressor C(k) from the angle,
    ripple from the harmonic columns of x(k|k−1), innovation, u = P Cᵀ, S = C u + R,
    the full update when moving and the Schmidt update of the residual only at
    standstill, then P += Q; a joint whose update leaves S, diag P or x non-finite or
    non-positive keeps its x and restarts at P(0).  Every input must be finite (the
    scalar filter's skip path is not reproduced).  Equal to N scalar filters to round-off.
    """

    def __init__(self, cfg: RippleFilterConfig, gear_ratio: float, joints: int) -> None:
        ref = HarmonicKalman(cfg, gear_ratio)
        self.size = joints
        self.n = n = ref.n
        self._r = n - 1
        self._w = np.array(ref.phase_gains)
        self._R = float(cfg.r)  # type: ignore[arg-type]
        self._standstill = float(cfg.standstill_radps)
        iu, ju = np.triu_indices(n)
        self._iu, self._ju = iu, ju
        full = np.zeros((n, n), dtype=np.intp)
        full[iu, ju] = np.arange(iu.size)
        full[ju, iu] = np.arange(iu.size)
        self._full = full
        self._diag = full[np.arange(n), np.arange(n)]
        self._q = np.diag(ref.Q)
        self._P0 = np.broadcast_to(np.asarray(ref._initial_P()), (joints, iu.size))
        # the upper-triangle entries (j, r) the standstill update touches
        self._col_r = full[:, self._r]
        self._x = np.zeros((joints, n))
        self._P = self._P0.copy()
        self._C = np.ones((joints, n))
        self._initialized = False
        self.covariance_resets = 0

    @property
    def x(self) -> np.ndarray:
        """A copy of the (N, n) states."""
        return self._x.copy()

    @property
    def P_upper(self) -> np.ndarray:
        """A copy of the (N, n(n+1)/2) covariances, upper triangles row by row."""
        return self._P.copy()

    def step(self, y: np.ndarray, velocity: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """One sample of every joint; returns the N ripples (:meth:`HarmonicKalman.step`)."""
        r = self._r
        if not self._initialized:
            self._x[:, r] = y
            self._initialized = True
        x, P, C = self._x, self._P, self._C
        phase = angle[:, None] * self._w
        C[:, 0:r:2] = np.cos(phase)
        C[:, 1:r:2] = np.sin(phase)
        ripple = np.einsum("ij,ij->i", C[:, :r], x[:, :r])
        e = y - ripple - x[:, r]
        u = np.matmul(P[:, self._full], C[:, :, None])[:, :, 0]
        S = self._R + np.einsum("ij,ij->i", u, C)
        k = u / S[:, None]
        moving = (velocity >= self._standstill) | (velocity <= -self._standstill)
        x_new = x + np.where(moving[:, None], k, 0.0) * e[:, None]
        x_new[:, r] = x[:, r] + k[:, r] * e
        P_new = P - np.where(moving[:, None], k[:, self._iu] * u[:, self._ju], 0.0)
        if not moving.all():  # standstill: P(j, r) -= k_r u_j, the rest frozen
            f = np.flatnonzero(~moving)
            P_new[f[:, None], self._col_r] -= k[f, r : r + 1] * u[f]
        P_new[:, self._diag] += self._q
        ok = (
            (S > 0.0)
            & np.isfinite(S)
            & np.all((P_new[:, self._diag] > 0.0) & (P_new[:, self._diag] < math.inf), axis=1)
            & np.isfinite(x_new.sum(axis=1))
        )
        if ok.all():
            self._x, self._P = x_new, P_new
        else:
            self.covariance_resets += int((~ok).sum())
            self._x = np.where(ok[:, None], x_new, x)
            self._P = np.where(ok[:, None], P_new, self._P0)
        return ripple


def _median_us(fn: Callable[[], None], steps: int) -> float:
    t0 = time.perf_counter_ns()
    fn()
    return (time.perf_counter_ns() - t0) / steps / 1e3


def _plant_case(n: int, steps: int) -> tuple[Callable[[], None], Callable[[], None]]:
    cfg = PlantConfig()
    seeds = list(range(n))
    plants = [Plant(cfg, seed) for seed in seeds]
    bank = PlantBank([cfg] * n, seeds)
    for p in plants:
        p.prepare(_DT)
    bank.prepare(_DT)
    t = np.arange(steps)[:, None] * _DT
    volts = 2.0 * np.sin(2.0 * math.pi * t * (1.0 + np.arange(n)))  # (steps, N)
    rows_arr = list(volts)
    rows_list = volts.tolist()

    def scalar() -> None:
        for row in rows_list:
            for plant, v in zip(plants, row, strict=True):
                plant.advance(v, _DT)
                plant.sample()

    def vector() -> None:
        for row in rows_arr:
            bank.advance(row, _DT)
            bank.sample()

    return scalar, vector


def _filter_case(n: int, steps: int) -> tuple[Callable[[], None], Callable[[], None]]:
    fw = FirmwareConfig()
    filters = [HarmonicKalman(fw.ripple, fw.gear_ratio) for _ in range(n)]
    bank = KalmanBank(fw.ripple, fw.gear_ratio, n)
    rng = np.random.default_rng(1)
    t = np.arange(steps)[:, None] * _DT
    angle = 50.0 * t * (1.0 + 0.1 * np.arange(n))
    y = 0.5 * np.sin(2.0 * angle) + 0.05 * rng.standard_normal((steps, n))
    vel = np.full((steps, n), 50.0)
    args_arr = list(zip(y, vel, angle, strict=True))
    args_list = [
        list(zip(*a, strict=True))
        for a in zip(y.tolist(), vel.tolist(), angle.tolist(), strict=True)
    ]

    def scalar() -> None:
        for row in args_list:
            for kf, (yk, vk, ak) in zip(filters, row, strict=True):
                kf.step(yk, vk, ak)

    def vector() -> None:
        for yk, vk, ak in args_arr:
            bank.step(yk, vk, ak)

    return scalar, vector


def joint_scaling(
    ns: Sequence[int] = DEFAULT_JOINTS, steps: int = 200, repeats: int = 9
) -> list[dict[str, Any]]:
    """µs per 1 kHz cycle of N joints, scalar against vectorised, for each N in ``ns``.

    Rows ``{"joints", "plant_scalar_us", "plant_vector_us", "filter_scalar_us",
    "filter_vector_us"}``: each the median over ``repeats`` of the mean over ``steps``
    cycles, the four variants taking turns within each repeat (see the module docstring).
    """
    if steps < 1 or repeats < 1 or not ns or min(ns) < 1:
        raise ValueError(f"need steps, repeats and every N >= 1, got {steps}, {repeats}, {ns}")
    rows = []
    for n in ns:
        plant_s, plant_v = _plant_case(n, steps)
        filt_s, filt_v = _filter_case(n, steps)
        cases = {
            "plant_scalar_us": plant_s,
            "plant_vector_us": plant_v,
            "filter_scalar_us": filt_s,
            "filter_vector_us": filt_v,
        }
        for fn in cases.values():  # warm up: maps, noise blocks, kernels
            fn()
        times: dict[str, list[float]] = {key: [] for key in cases}
        for rep in range(repeats):
            order = list(cases)
            order = order[rep % 4 :] + order[: rep % 4]
            for key in order:
                times[key].append(_median_us(cases[key], steps))
        rows.append({"joints": n, **{k: statistics.median(v) for k, v in times.items()}})
    return rows


def crossover(rows: Sequence[dict[str, Any]], part: str) -> int | None:
    """The smallest N of ``rows`` from which ``{part}_vector_us`` stays below
    ``{part}_scalar_us`` (``part``: ``"plant"`` or ``"filter"``); None if it never does."""
    found = None
    for row in sorted(rows, key=lambda r: r["joints"]):
        if row[f"{part}_vector_us"] < row[f"{part}_scalar_us"]:
            if found is None:
                found = row["joints"]
        else:
            found = None
    return found


def format_joint_scaling(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The rows as a Markdown table, then the crossover of plant and filter."""
    table = markdown_table(
        ["joints", "plant scalar µs", "plant vector µs", "filter scalar µs", "filter vector µs"],
        [
            [
                str(r["joints"]),
                *(
                    f"{r[k]:.1f}"
                    for k in (
                        "plant_scalar_us",
                        "plant_vector_us",
                        "filter_scalar_us",
                        "filter_vector_us",
                    )
                ),
            ]
            for r in rows
        ],
        [True] * 5,
    )
    lines = list(table)
    for part in ("plant", "filter"):
        n = crossover(rows, part)
        lines.append(
            f"{part}: vectorised wins from {n} joints"
            if n is not None
            else f"{part}: scalar wins at every N measured"
        )
    return lines
