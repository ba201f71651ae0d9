"""Soak runs: a long lockstep run with a trace, checked block by block.

:func:`run_soak` is :func:`hdhil.rig.runner.run_lockstep` with a trace (without the
side-by-side evaluation, which records every cycle) and a monitor that closes a
:class:`Block` every ``block_s`` simulated seconds: the errors against truth scored from
the buses, the firmware filter's health read at the block boundary (host side: the
firmware itself never reads truth nor runs these checks) and the process's resources.
At the end :func:`verdicts` judges the blocks (run completed, no non-finite value,
covariance SPD, error stationary, memory growth) against :class:`SoakLimits`, and
:func:`format_report` writes the report ``hdhil soak`` prints.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
from scipy import stats

from hdhil.can.traces.writer import WriterError, file_in_progress
from hdhil.core.dataconf import ConfigError
from hdhil.firmware.config import Law
from hdhil.firmware.controller import ControllerNode
from hdhil.rig.request import RunRequest
from hdhil.rig.result import RunResult
from hdhil.rig.runner import run_lockstep
from hdhil.rig.score import TorqueScore, TorqueScorer, TrackingScore, TrackingScorer
from hdhil.rig.verdict import format_verdict

MB = 2.0**20


@dataclass(frozen=True)
class SoakLimits:
    """What the verdicts compare with.

    - ``settle_s``: blocks that start before this simulated time are left out of the
      stationarity test (the filter and the observer converge there).
    - ``tolerance``: the stationarity test (:func:`stationarity`) passes when the 95 %
      confidence interval of the per-block RMS's fitted change over the tested blocks
      lies within ±``tolerance`` x their mean.
    - ``rss_growth_MB``: the limit on resident-memory growth from the end of the first
      block to the end of the run (issue: < 20 MB over one simulated hour).
    - ``asymmetry_rel``: max|P − Pᵀ| allowed, relative to max|P|.
    """

    settle_s: float = 0.0
    tolerance: float = 0.10
    rss_growth_MB: float = 20.0
    asymmetry_rel: float = 1e-9

    def __post_init__(self) -> None:
        if not (math.isfinite(self.settle_s) and self.settle_s >= 0):
            raise ConfigError(f"settle time must be >= 0 s, got {self.settle_s}")
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise ConfigError(f"tolerance must be > 0, got {self.tolerance}")
        if not (math.isfinite(self.rss_growth_MB) and self.rss_growth_MB > 0):
            raise ConfigError(f"memory growth limit must be > 0 MB, got {self.rss_growth_MB}")


@dataclass(frozen=True)
class FilterHealth:
    """The firmware's filter and controller state at a block boundary, as a host reads it."""

    covariance_asymmetry: float  # max|P − Pᵀ| (NaN if P is not finite)
    covariance_scale: float  # max|P|
    covariance_min_eigenvalue: float  # smallest eigenvalue of (P + Pᵀ)/2
    nonfinite: dict[str, int]  # quantity -> number of non-finite values in it
    covariance_resets: int  # the filter's counter since start-up
    skipped: int  # the filter's counter since start-up


@dataclass(frozen=True)
class Block:
    """One block of the soak: bus scores, filter health at its end, resources.

    - torque: RMS error of the telemetry's filtered torque against the emulator's true
      torque (``CTRL_TPDO1.T_filtered``, the LQG's estimate τ̂s when a control law runs),
      and of the raw measurement (:class:`hdhil.rig.score.TorqueScorer`);
    - tracking: RMS and max |e| of the control law, e = T_true − T_D
      (:class:`hdhil.rig.score.TrackingScorer`, with a control law only);
    - filter health (:func:`filter_health`): max|P − Pᵀ| and the smallest eigenvalue of
      the ripple filter's covariance P, the non-finite values in its state x, in P, in
      the LQG's estimate and in the interrupt's outputs, and the filter's own counters
      of covariance resets and skipped (non-finite) samples;
    - resources: resident memory (``/proc/self/statm``), trace file size, wall time.
    """

    index: int  # 1-based
    start_s: float  # simulated time of the first and after the last sample of the block
    end_s: float
    samples: int  # telemetry samples scored against truth
    rms_error_filtered: float
    rms_error_raw: float
    max_error_filtered: float
    tracking_rms: float | None
    tracking_max: float | None
    covariance_asymmetry: float
    covariance_min_eigenvalue: float
    covariance_symmetric: bool
    nonfinite: dict[str, int]
    covariance_resets: int  # in this block
    skipped_samples: int  # in this block
    rss_MB: float
    trace_MB: float | None
    wall_s: float

    @property
    def covariance_spd(self) -> bool:
        return self.covariance_symmetric and self.covariance_min_eigenvalue > 0.0


@dataclass(frozen=True)
class Verdict:
    name: str
    passed: bool
    detail: str
    values: dict[str, Any] = field(default_factory=dict)


@dataclass
class SoakReport:
    scenario: str
    seed: int
    duration_s: float
    sample_period_s: float
    block_s: float
    limits: SoakLimits
    trace: str | None
    blocks: list[Block]
    verdicts: list[Verdict]
    samples_expected: int
    samples_done: int
    wall_s: float
    interrupted: bool
    aborted: str | None  # the error that ended the run early, if any
    run: dict[str, Any] | None  # the run's own totals (hdhil run --json, abridged)

    @property
    def passed(self) -> bool:
        return all(v.passed for v in self.verdicts)

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["passed"] = self.passed
        d["real_time_factor"] = self.real_time_factor
        return d

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall second over the whole soak (start-up included)."""
        simulated = self.samples_done * self.sample_period_s
        return simulated / self.wall_s if self.wall_s > 0 else math.nan


def resident_MB() -> float:
    """Resident set size of this process now (``/proc/self/statm``), NaN without procfs."""
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            pages = int(fh.read().split()[1])
    except (OSError, ValueError, IndexError):
        return math.nan
    return pages * os.sysconf("SC_PAGE_SIZE") / MB


class BlockScorer(can.Listener):
    """Bus scores of the current block: a :class:`TorqueScorer` and, with a control law,
    a :class:`TrackingScorer`, replaced by fresh ones at every :meth:`take`.

    Taken at a cycle boundary, nothing is lost between blocks: within a cycle the drive
    sends the truth frames before the controller's telemetry of the same sample, so the
    fresh scorers have their truth before the first telemetry they score.
    """

    def __init__(self, jl_over_jm: float | None) -> None:
        self._jl_over_jm = jl_over_jm
        self.taken_samples = 0
        self._fresh()

    def _fresh(self) -> None:
        self.torque = TorqueScorer(block_s=math.inf)
        self.tracking = TrackingScorer(self._jl_over_jm) if self._jl_over_jm is not None else None

    def on_message_received(self, msg: can.Message) -> None:
        self.torque.on_message_received(msg)
        if self.tracking is not None:
            self.tracking.on_message_received(msg)

    @property
    def scored_samples(self) -> int:
        """Telemetry samples scored since the start, in closed blocks and the open one."""
        return self.taken_samples + self.torque.n

    def take(self) -> tuple[TorqueScore, TrackingScore | None]:
        """The open block's scores; the next block starts empty."""
        torque = self.torque.result()
        tracking = self.tracking.result() if self.tracking is not None else None
        self.taken_samples += torque.samples
        self._fresh()
        return torque, tracking


def _count_nonfinite(values: Any) -> int:
    return int(np.count_nonzero(~np.isfinite(np.asarray(values, dtype=np.float64))))


def filter_health(controller: ControllerNode) -> FilterHealth:
    """Read the firmware's ripple filter (x, P, counters), the LQG's estimate and the
    interrupt's last outputs, and check them (host side)."""
    isr = controller.isr
    kalman = isr.chain.kalman
    P = np.asarray(kalman.P, dtype=np.float64)
    quantities: dict[str, Any] = {"filter state x": kalman.x, "filter covariance P": P}
    if isr.control is not None:
        quantities["LQG estimate"] = isr.control.controller.estimate
    out = isr.output
    quantities["interrupt outputs"] = [float(getattr(out, f.name)) for f in dataclasses.fields(out)]
    nonfinite = {name: n for name, v in quantities.items() if (n := _count_nonfinite(v))}
    if np.all(np.isfinite(P)):
        asymmetry = float(np.abs(P - P.T).max())
        scale = float(np.abs(P).max())
        min_eig = float(np.linalg.eigvalsh((P + P.T) / 2.0).min())
    else:
        asymmetry = scale = min_eig = math.nan
    return FilterHealth(
        covariance_asymmetry=asymmetry,
        covariance_scale=scale,
        covariance_min_eigenvalue=min_eig,
        nonfinite=nonfinite,
        covariance_resets=int(getattr(kalman, "covariance_resets", 0)),
        skipped=int(kalman.skipped),
    )


class _BlockRecorder:
    """The ``monitor`` of :func:`run_lockstep`: closes a block at each call."""

    def __init__(
        self,
        scorer: BlockScorer,
        sample_period_s: float,
        trace: Path | None,
        limits: SoakLimits,
        after_block: Callable[[ControllerNode, Block], None] | None,
    ) -> None:
        self.scorer = scorer
        self.Ts = sample_period_s
        self.trace = trace
        self.limits = limits
        self.after_block = after_block
        self.blocks: list[Block] = []
        self.controller: ControllerNode | None = None
        self._start_sample = 0
        self._resets = 0
        self._skipped = 0
        self._wall = time.perf_counter()

    def __call__(self, controller: ControllerNode) -> None:
        self.controller = controller
        block = self.close(controller)
        if self.after_block is not None:
            self.after_block(controller, block)

    def close(self, controller: ControllerNode) -> Block:
        now = time.perf_counter()
        end_sample = controller.isr.samplecount
        torque, tracking = self.scorer.take()
        health = filter_health(controller)
        growing = file_in_progress(self.trace) if self.trace is not None else None
        trace_MB = growing.stat().st_size / MB if growing is not None and growing.exists() else None
        symmetric = (
            math.isfinite(health.covariance_asymmetry)
            and health.covariance_asymmetry <= self.limits.asymmetry_rel * health.covariance_scale
        )
        block = Block(
            index=len(self.blocks) + 1,
            start_s=self._start_sample * self.Ts,
            end_s=end_sample * self.Ts,
            samples=torque.samples,
            rms_error_filtered=torque.rms_error_filtered,
            rms_error_raw=torque.rms_error_raw,
            max_error_filtered=torque.max_error_filtered,
            tracking_rms=tracking.rms_error if tracking is not None else None,
            tracking_max=tracking.max_abs_error if tracking is not None else None,
            covariance_asymmetry=health.covariance_asymmetry,
            covariance_min_eigenvalue=health.covariance_min_eigenvalue,
            covariance_symmetric=symmetric,
            nonfinite=health.nonfinite,
            covariance_resets=health.covariance_resets - self._resets,
            skipped_samples=health.skipped - self._skipped,
            rss_MB=resident_MB(),
            trace_MB=trace_MB,
            wall_s=now - self._wall,
        )
        self.blocks.append(block)
        self._start_sample = end_sample
        self._resets, self._skipped = health.covariance_resets, health.skipped
        self._wall = now
        return block

    @property
    def open_samples(self) -> int:
        """Samples handled since the last block closed."""
        c = self.controller
        return c.isr.samplecount - self._start_sample if c is not None else 0


# -------------------------------------------------------------------------- verdicts
#: Blocks the stationarity test needs at least (a slope and its confidence interval).
MIN_STATIONARITY_BLOCKS = 3


def _slope(times_h: list[float], values: list[float]) -> tuple[float, float]:
    """Least-squares slope of ``values`` over ``times_h`` and the half-width of its 95 %
    confidence interval (Student t, n − 2 degrees of freedom); NaN below 3 points."""
    n = len(values)
    if n < 3:
        return math.nan, math.nan
    result = stats.linregress(times_h, values)
    half_width = float(stats.t.ppf(0.975, n - 2) * result.stderr)
    return float(result.slope), half_width


def trend(times_s: list[float], values: list[float]) -> dict[str, float]:
    """The least-squares trend of ``values`` (at ``times_s``): the slope per hour with the
    half-width of its 95 % confidence interval, and the change the line fits over the
    span from the first to the last time, relative to the mean of ``values``, with its
    95 % half-width (the slope's, times the span, over the mean).  A series of zeros has
    no relative change (0); below 3 values everything is NaN."""
    slope, ci = _slope([t / 3600.0 for t in times_s], values)
    span_h = (times_s[-1] - times_s[0]) / 3600.0 if times_s else math.nan
    mean = float(np.mean(values)) if values else math.nan
    if mean > 0:
        rel_slope, rel_ci = slope / mean, ci / mean
    elif mean == 0 and math.isfinite(slope):  # all zero: nothing changes
        rel_slope = rel_ci = 0.0
    else:
        rel_slope = rel_ci = math.nan
    return {
        "mean": mean,
        "span_s": span_h * 3600.0,
        "slope_per_hour": slope,
        "slope_ci95_per_hour": ci,
        "relative_slope_per_hour": rel_slope,
        "relative_slope_ci95_per_hour": rel_ci,
        "relative_change": rel_slope * span_h,
        "relative_change_ci95": rel_ci * span_h,
    }


def stationarity(
    name: str, blocks: list[Block], values: list[float], limits: SoakLimits
) -> Verdict:
    """Is the per-block RMS ``values`` stationary after ``limits.settle_s``?  One test,
    the one whose figures the verdict prints: over the blocks that start at or after the
    settling time, the least-squares line through the per-block RMS (at each block's
    middle, :func:`trend`) gives the change over the span from the first block's middle
    to the last one's, relative to their mean, with its 95 % confidence interval.  The
    error is stationary when that whole interval lies within ±:attr:`SoakLimits.tolerance`:
    a real trend larger than the tolerance fails, and so does a series the line fits too
    badly to show it (a step, a jump).  Needs :data:`MIN_STATIONARITY_BLOCKS` blocks."""
    kept = [(b, v) for b, v in zip(blocks, values, strict=True) if b.start_s >= limits.settle_s]
    if len(kept) < MIN_STATIONARITY_BLOCKS:
        return Verdict(
            name, False,
            f"needs at least {MIN_STATIONARITY_BLOCKS} blocks starting at or after "
            f"{limits.settle_s:g} s, got {len(kept)}",
        )  # fmt: skip
    series = [v for _, v in kept]
    if not all(math.isfinite(v) for v in series):
        return Verdict(name, False, "a block has no finite RMS value (no scored sample)")
    fit = trend([(b.start_s + b.end_s) / 2.0 for b, _ in kept], series)
    change, ci = fit["relative_change"], fit["relative_change_ci95"]
    passed = abs(change) + ci <= limits.tolerance  # False when NaN
    detail = (
        f"{len(kept)} blocks from {kept[0][0].start_s:g} s, mean {fit['mean']:.4g} Nm: "
        f"the fitted line changes by {change:+.1%} ± {ci:.1%} (95 %) of the mean over the "
        f"{fit['span_s']:g} s between the first and the last block's middle "
        f"({'within' if passed else 'not within'} ±{limits.tolerance:.0%})"
    )
    return Verdict(name, passed, detail, {"blocks": len(kept), **fit})


def verdicts(
    blocks: list[Block],
    limits: SoakLimits,
    samples_expected: int,
    samples_done: int,
    aborted: str | None,
) -> list[Verdict]:
    """The soak's verdicts, each computed from the blocks:

    - *run completed*: every sample of the duration was handled (no stop, no abort);
    - *no non-finite value*: none at any block end, and no skipped sample;
    - *covariance SPD*: in every block P is finite, symmetric to within
      :attr:`SoakLimits.asymmetry_rel` of its largest element, with its smallest
      eigenvalue > 0, and the filter never had to reset it;
    - *error stationary* (torque, and tracking with a control law):
      :func:`stationarity` over the blocks that start at or after the settling time;
    - *memory*: the resident memory grows by less than :attr:`SoakLimits.rss_growth_MB`
      from the end of the first block to the end of the run (the growth measured, in
      MB; no rate is extrapolated from it).
    """
    out = []
    complete = samples_done >= samples_expected and aborted is None
    out.append(
        Verdict(
            "run completed",
            complete,
            f"{samples_done} of {samples_expected} samples"
            + (f"; aborted: {aborted}" if aborted else ""),
            {"samples_done": samples_done, "samples_expected": samples_expected},
        )
    )
    bad_blocks = [b.index for b in blocks if b.nonfinite]
    skipped = sum(b.skipped_samples for b in blocks)
    out.append(
        Verdict(
            "no non-finite value",
            bool(blocks) and not bad_blocks and skipped == 0,
            f"non-finite values at {len(bad_blocks)} of {len(blocks)} block ends"
            + (
                f" (first: block {bad_blocks[0]}, {blocks[bad_blocks[0] - 1].nonfinite})"
                if bad_blocks
                else ""
            )
            + f"; {skipped} skipped samples",
            {"blocks_with_nonfinite": bad_blocks, "skipped_samples": skipped},
        )
    )
    not_spd = [b.index for b in blocks if not b.covariance_spd]
    resets = sum(b.covariance_resets for b in blocks)
    eigs = [b.covariance_min_eigenvalue for b in blocks]
    asym = [b.covariance_asymmetry for b in blocks]
    lowest = min(eigs) if eigs and all(math.isfinite(e) for e in eigs) else math.nan
    worst_asym = max(asym) if asym and all(math.isfinite(a) for a in asym) else math.nan
    out.append(
        Verdict(
            "covariance SPD",
            bool(blocks) and not not_spd and resets == 0,
            f"P symmetric positive definite at {len(blocks) - len(not_spd)} of {len(blocks)} "
            f"block ends (max|P-Pᵀ| {worst_asym:.3g}, smallest eigenvalue {lowest:.3g}); "
            f"{resets} covariance resets",
            {
                "blocks_not_spd": not_spd,
                "covariance_resets": resets,
                "min_eigenvalue": lowest,
                "max_asymmetry": worst_asym,
            },
        )
    )
    out.append(
        stationarity(
            "torque error stationary", blocks, [b.rms_error_filtered for b in blocks], limits
        )
    )
    if blocks and blocks[0].tracking_rms is not None:
        out.append(
            stationarity(
                "tracking error stationary",
                blocks,
                [b.tracking_rms if b.tracking_rms is not None else math.nan for b in blocks],
                limits,
            )
        )
    out.append(memory_verdict(blocks, limits))
    return out


def memory_verdict(blocks: list[Block], limits: SoakLimits) -> Verdict:
    name = "memory growth"
    if len(blocks) < 2 or not math.isfinite(blocks[0].rss_MB - blocks[-1].rss_MB):
        return Verdict(name, False, "needs at least 2 blocks and a readable /proc/self/statm")
    growth = blocks[-1].rss_MB - blocks[0].rss_MB
    span = blocks[-1].end_s - blocks[0].end_s
    return Verdict(
        name,
        growth < limits.rss_growth_MB,
        f"RSS {blocks[0].rss_MB:.1f} MB at the end of block 1, {blocks[-1].rss_MB:.1f} MB "
        f"at the end, {span:g} s later: {growth:+.1f} MB (limit {limits.rss_growth_MB:g} MB)",
        {"rss_first_block_MB": blocks[0].rss_MB, "rss_end_MB": blocks[-1].rss_MB,
         "growth_MB": growth, "span_s": span},
    )  # fmt: skip


# ------------------------------------------------------------------------------- run
def _run_summary(r: RunResult) -> dict[str, Any]:
    return {
        "cycles": r.cycles,
        "simulated_s": r.simulated_s,
        "wall_s": r.wall_s,
        "real_time_factor": r.real_time_factor,
        "frames_total": r.frames_total,
        "torque": {k: v for k, v in r.torque.items() if k != "rms_filtered_per_minute"},
        "tracking": r.tracking,
        "controller": r.controller,
        "verdict": r.verdict,
    }


#: Blocks a default soak puts after the settling time, at least, for its stationarity test.
STATIONARITY_BLOCKS = 4
#: The default block length of long soaks (s).
DEFAULT_BLOCK_S = 60.0


def default_block_s(duration_s: float, limits: SoakLimits) -> float:
    """The block length when ``--every`` is not given: 60 s, or shorter (whole seconds,
    at least 1 s) so that :data:`STATIONARITY_BLOCKS` blocks start at or after the
    settling time; e.g. 20 s blocks for ``--duration 120`` with 40 s of settling."""
    after = duration_s - limits.settle_s
    if not (math.isfinite(after) and after > 0):
        return DEFAULT_BLOCK_S
    return min(DEFAULT_BLOCK_S, max(1.0, math.floor(after / STATIONARITY_BLOCKS)))


def run_soak(
    request: RunRequest,
    block_s: float = 60.0,
    trace: Path | None = None,
    limits: SoakLimits | None = None,
    stop_requested: Callable[[], bool] | None = None,
    after_block: Callable[[ControllerNode, Block], None] | None = None,
    fault_log: Path | None = None,
) -> SoakReport:
    """Run ``request`` in lockstep (trace to ``trace``, with its sidecar) and check it
    every ``block_s``.  ``after_block(controller, block)`` is called after each block is
    recorded (e.g. to inject a fault into the firmware).  ``limits`` defaults to
    :class:`SoakLimits` with the request's evaluation start as settling time."""
    if not isinstance(request, RunRequest):
        raise TypeError(f"run_soak takes a RunRequest, got {type(request).__name__}")
    limits = limits if limits is not None else SoakLimits(settle_s=request.evaluate_from_s)
    # The blocks partition the whole run, so the run's own figures are the whole run's
    # too; the settling time is the limits' (the stationarity test leaves it out).
    request = dataclasses.replace(request, evaluate_from_s=0.0)
    scenario = request.scenario
    duration_s = request.duration_s
    if not (math.isfinite(block_s) and block_s > 0):
        raise ConfigError(f"block length (--every) must be > 0 s, got {block_s}")
    fw = scenario.firmware
    Ts = fw.sample_period_s
    expected = round(duration_s / Ts)
    if fw.num_samples:
        expected = min(expected, fw.num_samples)
    if expected < 1:
        raise ConfigError(f"duration {duration_s:g} s is shorter than one sample ({Ts:g} s)")
    block_samples = min(max(1, round(block_s / Ts)), expected)
    if abs(block_samples * Ts - block_s) > 1e-9 * max(1.0, block_s) and block_samples < expected:
        raise ConfigError(
            f"block length (--every) {block_s:g} s is not a whole number of {Ts:g} s samples"
        )
    control = fw.control
    scorer = BlockScorer(control.joint.Jl / control.joint.Jm if control.law != Law.NONE else None)
    recorder = _BlockRecorder(scorer, Ts, trace, limits, after_block)
    wall0 = time.perf_counter()
    result: RunResult | None = None
    aborted: str | None = None
    try:
        result = run_lockstep(
            request,
            trace=trace,
            fault_log=fault_log,
            stop_requested=stop_requested,
            evaluate=False,
            extra_listeners=[scorer],
            monitor=recorder,
            monitor_every=block_samples,
        )
    except WriterError:
        raise  # the trace could not be written: an error, not a verdict on the run
    except ValueError as exc:
        if scorer.scored_samples == 0 and not recorder.blocks:
            raise  # nothing ran: a configuration error, reported as such
        aborted = str(exc)  # e.g. a non-finite value the telemetry cannot encode
    if result is not None and result.verdict is not None:
        aborted = format_verdict(result.verdict)  # a fault reaction ended the run early
    wall = time.perf_counter() - wall0
    if recorder.controller is not None and recorder.open_samples > 0:
        recorder.close(recorder.controller)  # the last, shorter block
    done = result.cycles if result is not None else sum(b.samples for b in recorder.blocks)
    return SoakReport(
        scenario=scenario.name,
        seed=request.seed,
        duration_s=duration_s,
        sample_period_s=Ts,
        block_s=block_samples * Ts,
        limits=limits,
        trace=str(trace) if trace is not None else None,
        blocks=recorder.blocks,
        verdicts=verdicts(recorder.blocks, limits, expected, done, aborted),
        samples_expected=expected,
        samples_done=done,
        wall_s=wall,
        interrupted=bool(result is not None and result.interrupted),
        aborted=aborted,
        run=_run_summary(result) if result is not None else None,
    )


# ---------------------------------------------------------------------------- output
def _fmt(value: float | None, spec: str) -> str:
    """``value`` formatted by ``spec`` (e.g. ``"8.4f"``), '-' for none, 'nan', same width."""
    if value is not None and math.isfinite(value):
        return format(value, spec)
    width = spec.split(".")[0]
    return format("-" if value is None else "nan", f">{width}")


def format_report(r: SoakReport) -> str:
    lines = [
        f"hdhil soak: scenario {r.scenario}, seed {r.seed}, {r.samples_done} of "
        f"{r.samples_expected} samples in blocks of {r.block_s:g} s, wall {r.wall_s:.1f} s"
        + (f", trace {r.trace}" if r.trace else ", no trace")
        + ("  [INTERRUPTED]" if r.interrupted else ""),
        "  errors against truth, from the buses: T_filtered (τ̂s with a control law) and "
        "raw T_meas RMS; tracking e = T_true − T_D",
        f"  {'block':>5} {'end/s':>7} {'T err':>8} {'raw':>7} {'track':>7} {'max|e|':>7} "
        f"{'|P-Pᵀ|':>7} {'λmin(P)':>8} {'nonfin':>6} {'resets':>6} {'skip':>5} "
        f"{'RSS/MB':>7} {'trace/MB':>8} {'RTF':>5}",
    ]
    for b in r.blocks:
        rtf = (b.end_s - b.start_s) / b.wall_s if b.wall_s > 0 else math.nan
        lines.append(
            f"  {b.index:>5} {b.end_s:7.1f} {_fmt(b.rms_error_filtered, '8.4f')} "
            f"{_fmt(b.rms_error_raw, '7.4f')} {_fmt(b.tracking_rms, '7.4f')} "
            f"{_fmt(b.tracking_max, '7.3f')} {_fmt(b.covariance_asymmetry, '7.1g')} "
            f"{_fmt(b.covariance_min_eigenvalue, '8.2e')} {sum(b.nonfinite.values()):>6} "
            f"{b.covariance_resets:>6} {b.skipped_samples:>5} {_fmt(b.rss_MB, '7.1f')} "
            f"{_fmt(b.trace_MB, '8.1f')} {_fmt(rtf, '5.1f')}"
        )
    lines.append("  (errors in Nm; nonfin: non-finite values in the filter state, P, the LQG "
                 "estimate and the interrupt outputs at the block end)")  # fmt: skip
    if r.run is not None:
        lines.append(
            f"  whole run: {r.run['frames_total']} frames, real-time factor "
            f"{r.run['real_time_factor']:.1f}x"
        )
    lines.append("  verdicts")
    width = max(len(v.name) for v in r.verdicts)
    for v in r.verdicts:
        lines.append(f"    {v.name:<{width}}  {'pass' if v.passed else 'FAIL'}  {v.detail}")
    passed = sum(v.passed for v in r.verdicts)
    lines.append(
        f"  result: {'PASS' if r.passed else 'FAIL'} ({passed} of {len(r.verdicts)} verdicts)"
    )
    return "\n".join(lines)
