"""Maximum-likelihood tuning of the recommended ripple filter's Q and R on recorded data.

[Taghirad97] chooses Q = 1e3·I and R = 1 for its filter (§4, text under Eq. 10, Fig. 9)
and 5e-2 for the misalignment block (§5, listing A.2) without saying how.  This module
estimates them from a recording instead, using only what the firmware itself sees (the
drive's raw sensor frames through the firmware's own stages; never telemetry or ground
truth), so it works on a real drive's traces.

:func:`tune_recording` / :func:`tune_signals` run the search (the objective and the
optimiser are described there); :func:`ripple_toml` writes the result as a scenario's
``[firmware.ripple]`` table and :func:`format_result` the report of ``hdhil tune``.
The paper filter (listing A.1, :class:`firmware.ripple.RippleKalman`), the recommended
filter with its default tuning and the tuned one are compared by log-likelihood per
sample: all three are one-step-ahead predictive densities of the same measurements, so
their difference is a likelihood ratio per sample.  With ground truth in the trace the
RMS error of each against the true torque is a check the tuner did not use.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize

from hdhil.core.errors import UserError
from hdhil.firmware.config import (
    FirmwareConfig,
    Oscillator,
    RippleFilterConfig,
    paper_config,
    recommended_config,
)
from hdhil.firmware.isr import TorqueFilterChain
from hdhil.firmware.ripple import HarmonicKalman

__all__ = [
    "DEFAULT_MAX_EVALS",
    "LOG10_BOUNDS",
    "MAX_TUNED_HARMONICS",
    "MAX_WINDOW_SAMPLES",
    "MIN_WINDOW_SAMPLES",
    "SKIP_S",
    "FilterInputs",
    "TuneResult",
    "filter_inputs",
    "format_result",
    "innovation_stats",
    "mean_nll",
    "paper_innovations",
    "parameter_names",
    "recommended_innovations",
    "ripple_toml",
    "tune_recording",
    "tune_signals",
    "tuning_of",
    "with_tuning",
]

#: The likelihood window starts after this many seconds (filter initialisation transient).
SKIP_S = 0.2
#: At most this many samples in the likelihood window (the first ones after the skip).
MAX_WINDOW_SAMPLES = 30_000
#: Fewer samples than this in the likelihood window is an error.
MIN_WINDOW_SAMPLES = 200
#: Default budget of likelihood evaluations.
DEFAULT_MAX_EVALS = 150
#: Most harmonics (oscillators) of a filter the tuner takes.  Every likelihood
#: evaluation runs the recommended filter over the whole window (up to
#: :data:`MAX_WINDOW_SAMPLES` samples), and a step of that filter updates its
#: (2 h + 1)² covariance in generated straight-line code, so the tuner's work grows with
#: the square of the harmonics h (and the step's code with it): the default budget runs
#: 4.5 million filter steps, of 17 states at 8 harmonics; 32 harmonics make each step
#: about 15 times the work of 8, and the 255 the object dictionary can count about 900.
MAX_TUNED_HARMONICS = 8
#: Search range of each parameter, as log10 of its value (Nm² per step, Nm² for r).
LOG10_BOUNDS: dict[str, tuple[float, float]] = {
    "q_motor": (-12.0, -1.0),
    "q_output": (-12.0, 0.0),
    "residual_q": (-10.0, 1.0),
    "r": (-8.0, 1.0),
}
#: Display names of the parameters.
LABELS = {"q_motor": "q motor", "q_output": "q output", "residual_q": "residual_q", "r": "r"}
#: Nelder-Mead stops when the simplex is this small (decades) and the objective this flat
#: (nats per sample).
XATOL_DECADES = 0.01
FATOL_NATS = 1e-7


# ------------------------------------------------------------------------ filter runs
@dataclass(frozen=True)
class FilterInputs:
    """What the ripple filter is fed at each sample, computed by the firmware's stages:
    ``delta_T`` = y = T_meas − T_exp (Nm, [Taghirad97] §4), ``velocity`` (rad/s, tachometer)
    and ``angle``, the motor angle the recommended filter takes its phase from (rad)."""

    delta_T: np.ndarray
    velocity: np.ndarray
    angle: np.ndarray

    def __len__(self) -> int:
        return len(self.delta_T)


def _gaps(missed: np.ndarray | None, n: int) -> list[int]:
    return [0] * n if missed is None else missed[:n].astype(np.int64).tolist()


def filter_inputs(
    T_meas: np.ndarray,
    velocity: np.ndarray,
    encoder: np.ndarray,
    cfg: FirmwareConfig,
    missed: np.ndarray | None = None,
) -> FilterInputs:
    """Run the firmware's :class:`~firmware.isr.TorqueFilterChain` (recommended mode) over
    calibrated samples and collect the ripple filter's inputs.  They do not depend on the
    filter's tuning, so they are computed once per trace.  ``missed[k]``: periods without
    a sample before sample k (told to the chain, as the firmware's was)."""
    chain = TorqueFilterChain(recommended_config(cfg))
    n = len(T_meas)
    delta_T = np.empty(n)
    angle = np.empty(n)
    step = chain.step
    for k, (T, v, count, gap) in enumerate(
        zip(
            T_meas.tolist(),
            velocity.tolist(),
            encoder.astype(np.int64).tolist(),
            _gaps(missed, n),
            strict=True,
        )
    ):
        for _ in range(gap):
            chain.sample_missed()
        delta_T[k] = step(T, v, count)[2]
        angle[k] = chain.angle
    return FilterInputs(delta_T, np.asarray(velocity, dtype=np.float64).copy(), angle)


def recommended_innovations(
    inputs: FilterInputs, ripple: RippleFilterConfig, gear_ratio: float, stop: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Innovations e_k and their variances S_k of the firmware's recommended filter
    (:class:`firmware.ripple.HarmonicKalman`) with tuning ``ripple``, over the first
    ``stop`` samples (all by default).  NaN where the filter skipped a sample."""
    kf = HarmonicKalman(ripple, gear_ratio)
    step = kf.step
    n = len(inputs) if stop is None else min(stop, len(inputs))
    e: list[float] = []
    S: list[float] = []
    for y, v, a in zip(
        inputs.delta_T[:n].tolist(),
        inputs.velocity[:n].tolist(),
        inputs.angle[:n].tolist(),
        strict=True,
    ):
        step(y, v, a)
        e.append(kf.innovation)
        S.append(kf.innovation_variance)
    return np.array(e), np.array(S)


def paper_innovations(
    T_meas: np.ndarray,
    velocity: np.ndarray,
    cfg: FirmwareConfig,
    stop: int | None = None,
    missed: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Innovations and their variances S = R + C P Cᵀ of the paper filter ([Taghirad97]
    Eqs. 8-10, listing A.1 :class:`firmware.ripple.RippleKalman`) with the seed's tuning,
    run inside the firmware's chain (``cfg`` in paper mode, :func:`paper_config`)."""
    chain = TorqueFilterChain(paper_config(cfg))
    kf = chain.kalman
    n = len(T_meas) if stop is None else min(stop, len(T_meas))
    e: list[float] = []
    S: list[float] = []
    for T, v, gap in zip(T_meas[:n].tolist(), velocity[:n].tolist(), _gaps(missed, n), strict=True):
        for _ in range(gap):
            chain.sample_missed()
        chain.step(T, v)
        e.append(kf.innovation)
        S.append(kf.innovation_variance)
    return np.array(e), np.array(S)


def mean_nll(e: np.ndarray, S: np.ndarray, start: int = 0, stop: int | None = None) -> float:
    """Mean over samples ``start:stop`` of ½ (log 2π S_k + e_k² / S_k) (nats per sample),
    leaving out samples without an innovation (NaN); ``inf`` if S is not positive."""
    e = e[start:stop]
    S = S[start:stop]
    ok = np.isfinite(e) & np.isfinite(S)
    if not ok.any():
        return math.inf
    e, S = e[ok], S[ok]
    if np.any(S <= 0.0):
        return math.inf
    return float(np.mean(0.5 * (np.log(2.0 * math.pi * S) + e * e / S)))


def innovation_stats(e: np.ndarray, S: np.ndarray, start: int, stop: int) -> dict[str, float]:
    """Diagnostics over samples ``start:stop``: the innovations' RMS (Nm) and their mean
    normalised square e²/S, which is 1 for a filter whose S matches its actual errors
    (> 1: overconfident, << 1: the filter claims far more uncertainty than it has)."""
    e, S = e[start:stop], S[start:stop]
    ok = np.isfinite(e) & np.isfinite(S) & (S > 0)
    if not ok.any():
        return {"rms": math.nan, "nis": math.nan}
    return {
        "rms": float(np.sqrt(np.mean(e[ok] ** 2))),
        "nis": float(np.mean(e[ok] ** 2 / S[ok])),
    }


# ------------------------------------------------------------------------- parameters
def parameter_names(ripple: RippleFilterConfig) -> tuple[str, ...]:
    """The tuned parameters for this harmonic set, in search order."""
    sources = {o.source for o in ripple.oscillators}
    names = []
    if "motor" in sources:
        names.append("q_motor")
    if "output" in sources:
        names.append("q_output")
    return (*names, "residual_q", "r")


def tuning_of(ripple: RippleFilterConfig) -> dict[str, float]:
    """The tuned parameters' values in a recommended-mode ``ripple`` (for a harmonic group
    whose oscillators differ, the geometric mean of their q)."""
    out: dict[str, float] = {}
    for name, source in (("q_motor", "motor"), ("q_output", "output")):
        qs = [float(o.q) for o in ripple.oscillators if o.source == source]  # type: ignore[arg-type]
        if qs:
            out[name] = float(np.exp(np.mean(np.log(np.maximum(qs, 1e-300)))))
    out["residual_q"] = float(ripple.residual_q)
    out["r"] = float(ripple.r)  # type: ignore[arg-type]
    return out


def with_tuning(ripple: RippleFilterConfig, values: dict[str, float]) -> RippleFilterConfig:
    """``ripple`` in recommended mode with the given parameter values (missing ones kept)."""
    oscillators = tuple(
        Oscillator(o.source, o.multiple, values.get(f"q_{o.source}", o.q))
        for o in ripple.oscillators
    )
    return dataclasses.replace(
        ripple,
        oscillators=oscillators,
        residual_q=values.get("residual_q", ripple.residual_q),
        r=values.get("r", ripple.r),
    )


# ---------------------------------------------------------------------------- tuning
@dataclass
class TuneResult:
    """The outcome of a tuning run; ``loglik_*`` are log-likelihoods per sample (nats),
    the window is samples ``window[0]:window[1]``; ``innovations`` holds
    :func:`innovation_stats` of paper / default / tuned; ``rms`` the RMS error vs truth
    (Nm) of raw / paper / default / tuned when the trace has truth, else None."""

    parameters: tuple[str, ...]
    default: dict[str, float]
    tuned: dict[str, float]
    paper: dict[str, float]
    tuned_ripple: RippleFilterConfig
    loglik_paper: float
    loglik_default: float
    loglik_tuned: float
    window: tuple[int, int]
    sample_period_s: float
    evaluations: int
    wall_s: float
    converged: bool
    message: str
    innovations: dict[str, dict[str, float]]
    rms: dict[str, float] | None = None

    @property
    def samples(self) -> int:
        return self.window[1] - self.window[0]

    def to_json(self) -> dict[str, Any]:
        return {
            "parameters": list(self.parameters),
            "default": self.default,
            "tuned": self.tuned,
            "paper": self.paper,
            "loglik_per_sample": {
                "paper": self.loglik_paper,
                "default": self.loglik_default,
                "tuned": self.loglik_tuned,
            },
            "innovations": self.innovations,
            "improvement_over_paper": self.loglik_tuned - self.loglik_paper,
            "improvement_over_default": self.loglik_tuned - self.loglik_default,
            "window_samples": list(self.window),
            "window_s": [k * self.sample_period_s for k in self.window],
            "samples": self.samples,
            "evaluations": self.evaluations,
            "wall_s": self.wall_s,
            "converged": self.converged,
            "message": self.message,
            "rms_vs_truth": self.rms,
        }


def _window(n: int, sample_period_s: float, skip_s: float, max_window: int) -> tuple[int, int]:
    k0 = round(skip_s / sample_period_s)
    k1 = min(n, k0 + max_window)
    if k1 - k0 < MIN_WINDOW_SAMPLES:
        raise UserError(
            f"too few samples to tune: {max(0, k1 - k0)} after the first {skip_s:g} s "
            f"(need at least {MIN_WINDOW_SAMPLES})"
        )
    return k0, k1


def _initial_simplex(x0: np.ndarray, bounds: Sequence[tuple[float, float]]) -> np.ndarray:
    """x0 and one vertex per parameter one decade away (downwards if up leaves the box)."""
    simplex = [x0]
    for i, (lo, hi) in enumerate(bounds):
        v = x0.copy()
        v[i] = x0[i] + 1.0 if x0[i] + 1.0 <= hi else max(lo, x0[i] - 1.0)
        simplex.append(v)
    return np.array(simplex)


def tune_signals(
    T_meas: np.ndarray,
    velocity: np.ndarray,
    encoder: np.ndarray,
    cfg: FirmwareConfig,
    *,
    skip_s: float = SKIP_S,
    max_evals: int = DEFAULT_MAX_EVALS,
    max_window: int = MAX_WINDOW_SAMPLES,
    on_evaluation: Callable[[int], object] | None = None,
    missed: np.ndarray | None = None,
) -> TuneResult:
    """Tune the recommended filter on calibrated samples (T_meas in Nm, velocity in rad/s,
    raw 16-bit encoder counts), starting from ``cfg``'s recommended tuning.
    ``on_evaluation(n)`` is called after the n-th likelihood evaluation (progress);
    ``missed[k]`` is the number of sample periods without a sample before sample k (a
    lossy trace).

    - **Inputs**: y = T_meas − T_exp, velocity and motor angle from the firmware's own
      :class:`firmware.isr.TorqueFilterChain` (:func:`filter_inputs`, once per trace).
    - **Parameters** (searched as log10, within :data:`LOG10_BOUNDS`): one q shared by
      the motor-locked harmonics ([Taghirad97] §4, 2x/4x motor angle), one q for the
      output-locked harmonics if any are configured (§5, misalignment), ``residual_q``
      and ``r``.  The harmonics, ``p0``, ``phase_source`` and ``standstill_radps`` are
      held at the configuration's values.
    - **Objective**: the negative log-likelihood of the innovations,
      Σ_k ½ (log 2π S_k + e_k² / S_k) (:func:`mean_nll`), with e_k and S_k read from
      the firmware's own filter (:attr:`firmware.ripple.HarmonicKalman.innovation` and
      ``innovation_variance``) after each step: the one-step-ahead prediction error
      decomposition of the Gaussian likelihood.  The sum runs over the likelihood
      window: from ``skip_s`` (the filter's initialisation, where r = y(0) makes e = 0,
      and the differentiator's start transient) for at most ``max_window`` samples; the
      filter runs from sample 0.  Samples the filter skipped (non-finite inputs) are
      left out.
    - **Optimiser**: :func:`scipy.optimize.minimize`, Nelder-Mead on the log10
      parameters, started at the recommended tuning with a simplex one decade wide, at
      most ``max_evals`` likelihood evaluations; never reports worse than the start.
    - **Bound**: a filter of more than :data:`MAX_TUNED_HARMONICS` harmonics is refused
      (:class:`UserError`) before any work.
    """
    t_start = time.perf_counter()
    harmonics = len(cfg.ripple.oscillators)
    if harmonics > MAX_TUNED_HARMONICS:
        raise UserError(
            f"the filter has {harmonics} harmonics; hdhil tune takes at most "
            f"{MAX_TUNED_HARMONICS} (every likelihood evaluation runs the filter over the "
            f"window, at a cost growing with the square of the harmonics)"
        )
    Ts = cfg.sample_period_s
    k0, k1 = _window(len(T_meas), Ts, skip_s, max_window)
    start_cfg = recommended_config(cfg)
    ripple0 = start_cfg.ripple
    gear = cfg.gear_ratio
    inputs = filter_inputs(T_meas[:k1], velocity[:k1], encoder[:k1], cfg, missed)
    names = parameter_names(ripple0)
    default = tuning_of(ripple0)
    bounds = [LOG10_BOUNDS[name] for name in names]
    x0 = np.array(
        [min(max(math.log10(max(default[name], 1e-300)), lo), hi)
         for name, (lo, hi) in zip(names, bounds, strict=True)]
    )  # fmt: skip

    def values_of(x: np.ndarray) -> dict[str, float]:
        return {name: float(10.0**v) for name, v in zip(names, x, strict=True)}

    evaluations = 0

    def objective(x: np.ndarray) -> float:
        nonlocal evaluations
        evaluations += 1
        e, S = recommended_innovations(inputs, with_tuning(ripple0, values_of(x)), gear, k1)
        value = mean_nll(e, S, k0, k1)
        if on_evaluation is not None:
            on_evaluation(evaluations)
        return value if math.isfinite(value) else 1e300

    e_default, S_default = recommended_innovations(inputs, ripple0, gear, k1)
    nll_default = mean_nll(e_default, S_default, k0, k1)
    result = minimize(
        objective,
        x0,
        method="Nelder-Mead",
        bounds=bounds,
        options={
            "maxfev": max_evals,
            "initial_simplex": _initial_simplex(x0, bounds),
            "xatol": XATOL_DECADES,
            "fatol": FATOL_NATS,
        },
    )
    x_best = np.asarray(result.x, dtype=np.float64)
    nll_best = float(result.fun)
    if not nll_best <= nll_default:  # never report worse than the start
        x_best, nll_best = x0, nll_default
    tuned = values_of(x_best)
    tuned_ripple = with_tuning(ripple0, tuned)

    paper = paper_config(cfg).ripple
    paper_values = {
        "q_motor" if o.source == "motor" else "q_output": float(o.q)  # type: ignore[arg-type]
        for o in paper.oscillators
    }
    paper_values["r"] = float(paper.r)  # type: ignore[arg-type]
    e_paper, S_paper = paper_innovations(T_meas, velocity, cfg, k1, missed)
    nll_paper = mean_nll(e_paper, S_paper, k0, k1)
    e_tuned, S_tuned = recommended_innovations(inputs, tuned_ripple, gear, k1)
    innovations = {
        "paper": innovation_stats(e_paper, S_paper, k0, k1),
        "default": innovation_stats(e_default, S_default, k0, k1),
        "tuned": innovation_stats(e_tuned, S_tuned, k0, k1),
    }

    return TuneResult(
        parameters=names,
        default=default,
        tuned=tuned,
        paper=paper_values,
        tuned_ripple=tuned_ripple,
        loglik_paper=-nll_paper,
        loglik_default=-nll_default,
        loglik_tuned=-nll_best,
        window=(k0, k1),
        sample_period_s=Ts,
        evaluations=evaluations,
        wall_s=time.perf_counter() - t_start,
        converged=bool(result.success),
        message=str(result.message),
        innovations=innovations,
    )


def tune_recording(
    rec: Any,
    cfg: FirmwareConfig,
    *,
    skip_s: float = SKIP_S,
    max_evals: int = DEFAULT_MAX_EVALS,
    max_window: int = MAX_WINDOW_SAMPLES,
    on_evaluation: Callable[[int], object] | None = None,
) -> TuneResult:
    """Tune on a :class:`hdhil.rig.evaluate.Recording` (its ``DRIVE_TPDO1`` columns only);
    then, if it has ground truth, add the RMS check (:attr:`TuneResult.rms`)."""
    from hdhil.rig.evaluate import calibrated_signals, offline_chain

    if len(rec) == 0:
        raise UserError("no DRIVE_TPDO1 frames (drive sensor frames) in the trace: nothing to tune")
    T_meas, velocity = calibrated_signals(rec, cfg)
    encoder = rec.column("encoder")
    missed = rec.column("missed")  # the periods the firmware had no sample (a lossy trace)
    result = tune_signals(
        T_meas,
        velocity,
        encoder,
        cfg,
        skip_s=skip_s,
        max_evals=max_evals,
        max_window=max_window,
        on_evaluation=on_evaluation,
        missed=missed,
    )
    T_true = rec.column("T_true")
    k0, k1 = result.window
    truth = np.isfinite(T_true[k0:k1])
    if truth.any():
        tuned_cfg = dataclasses.replace(recommended_config(cfg), ripple=result.tuned_ripple)
        candidates = {
            "raw": T_meas,
            "paper": offline_chain(paper_config(cfg), T_meas, velocity, encoder, missed),
            "default": offline_chain(recommended_config(cfg), T_meas, velocity, encoder, missed),
            "tuned": offline_chain(tuned_cfg, T_meas, velocity, encoder, missed),
        }
        result.rms = {
            name: float(np.sqrt(np.mean((x[k0:k1] - T_true[k0:k1])[truth] ** 2)))
            for name, x in candidates.items()
        }
    return result


# ------------------------------------------------------------------------------ output
def _toml_float(value: float) -> str:
    """A TOML float with 4 significant digits (always with '.' or an exponent)."""
    return repr(float(f"{value:.4g}"))


def ripple_toml(ripple: RippleFilterConfig, comments: Sequence[str] = ()) -> str:
    """``ripple`` as a scenario-file ``[firmware.ripple]`` table; parses to
    ``{"firmware": {"ripple": {...}}}`` for ``load_scenario(..., overrides=...)``.

    The tuned values and the ones held fixed while tuning are all written, so merging the
    file over any scenario with the same harmonics gives exactly the tuned filter."""
    rows: list[tuple[str, str]] = [
        ("", ""),
        ("[firmware.ripple]", ""),
        (f'mode = "{ripple.mode}"', ""),
        (f"r = {_toml_float(ripple.r)}", "tuned"),  # type: ignore[arg-type]
        (f"residual_q = {_toml_float(ripple.residual_q)}", "tuned"),
        (f"p0 = {_toml_float(ripple.p0)}", "held fixed"),  # type: ignore[arg-type]
        (f'phase_source = "{ripple.phase_source}"', "held fixed"),
        (f"standstill_radps = {_toml_float(ripple.standstill_radps)}", "held fixed"),
    ]
    for o in ripple.oscillators:
        rows += [
            ("", ""),
            ("[[firmware.ripple.oscillators]]", ""),
            (f'source = "{o.source}"', ""),
            (f"multiple = {_toml_float(o.multiple)}", ""),
            (f"q = {_toml_float(o.q)}", "tuned"),  # type: ignore[arg-type]
        ]
    width = max(len(code) for code, note in rows if note)
    lines = [f"# {line}".rstrip() for text in comments for line in text.splitlines()]
    lines += [f"{code:<{width}}  # {note}" if note else code for code, note in rows]
    return "\n".join(lines) + "\n"


def _g(value: float | None) -> str:
    return "—" if value is None else f"{value:.3g}"


def format_result(res: TuneResult, label: str) -> str:
    """The human-readable report."""
    Ts = res.sample_period_s
    k0, k1 = res.window
    names = ("q_motor", "q_output", "residual_q", "r")
    shown = [n for n in names if n in res.parameters or (n in res.paper and n != "residual_q")]
    head = "".join(f"{LABELS[n]:>11}" for n in shown)
    rms_head = "  RMS vs truth/Nm" if res.rms else ""
    status = "converged" if res.converged else "budget used up before convergence"
    lines = [
        f"hdhil tune: {label}",
        f"  likelihood window  {res.samples} samples, {k0 * Ts:.3f}-{k1 * Ts:.3f} s "
        f"(the first {k0 * Ts:g} s skipped: filter start-up)",
        f"  optimiser          Nelder-Mead on log10 parameters: {res.evaluations} "
        f"evaluations, {res.wall_s:.1f} s wall ({status})",
        "",
        f"  {'tuning':<8}{head}  {'loglik/sample':>13}  {'e RMS/Nm':>8}  {'e²/S':>8}{rms_head}",
    ]
    rows = (
        ("paper", res.paper, res.loglik_paper),
        ("default", res.default, res.loglik_default),
        ("tuned", res.tuned, res.loglik_tuned),
    )
    for name, values, ll in rows:
        cells = "".join(f"{_g(values.get(n)):>11}" for n in shown)
        inn = res.innovations[name]
        rms = f"  {res.rms[name]:16.4f}" if res.rms else ""
        lines.append(f"  {name:<8}{cells}  {ll:13.4f}  {inn['rms']:8.4f}  {inn['nis']:8.3g}{rms}")
    lines += [
        "  (q: random-walk variance per step, Nm²; r: measurement variance, Nm²;",
        "   paper: the listing A.1 filter's Q and R, its own innovations, S = R + C P Cᵀ;",
        "   e RMS: innovation RMS; e²/S: mean normalised innovation square, 1 when S is right)",
        "",
        f"  improvement over the paper's tuning   {res.loglik_tuned - res.loglik_paper:+.4f} "
        f"nats/sample ({(res.loglik_tuned - res.loglik_paper) * res.samples:+.1f} in total)",
        f"  improvement over the default tuning   {res.loglik_tuned - res.loglik_default:+.4f} "
        f"nats/sample ({(res.loglik_tuned - res.loglik_default) * res.samples:+.1f} in total)",
    ]
    if res.rms:
        r = res.rms
        lines.append(
            "  check vs ground truth (NOT used by the tuner), RMS error over the window:\n"
            f"    raw {r['raw']:.4f}, paper {r['paper']:.4f}, default {r['default']:.4f}, "
            f"tuned {r['tuned']:.4f} Nm"
        )
    else:
        lines.append("  (no ground truth in the trace: no RMS check)")
    return "\n".join(lines)
