"""Benchmarks: throughput, compute-time and memory figures, measured in the run itself.

Benchmarks are run here, never as timed unit tests: these machines are shared and
noisy, so every throughput figure is the median of several runs and comes with its
spread, and every per-call time is a median and 99th percentile over many calls.

:func:`run_benchmarks` measures every section (the list is in its docstring), each also
a function of its own (:func:`bench_lockstep_all`, :func:`bench_stages`,
:func:`bench_filter`, :func:`bench_memory`, :func:`bench_realtime`,
:func:`bench_startup`); :func:`format_bench` writes the report ``hdhil bench`` prints.
The report is a plain dict (JSON as it stands).
"""

from __future__ import annotations

import csv
import dataclasses
import gc
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from hdhil.analysis.tables import markdown_table as _table
from hdhil.core.errors import UserError
from hdhil.firmware.config import FirmwareConfig, paper_config
from hdhil.firmware.isr import (
    AdcSample,
    InterruptHandler,
    IsrOutput,
    TorqueControl,
    TorqueFilterChain,
)
from hdhil.firmware.ripple import HarmonicKalman, RippleKalman
from hdhil.firmware.stages import Differentiator, SensorPlausibility, adc_read, calibrate
from hdhil.hostsim.plant import Plant
from hdhil.rig.ostuning import cpu_steal_ns, steal_report
from hdhil.rig.realtime import RealtimeConfig
from hdhil.rig.realtime_stats import PERCENTILE_KEYS, format_steal
from hdhil.rig.request import resolve
from hdhil.rig.runner import run_lockstep
from hdhil.rig.scenario import load_scenario

#: Scenarios of the lockstep section, with the order of their ripple model.
LOCKSTEP_SCENARIOS: tuple[tuple[str, str], ...] = (
    ("free-motion", "4th-order ripple model"),
    ("misalignment", "6th-order ripple model"),
    ("lqg-tracking", "LQG control (JTF1)"),
)


@dataclass(frozen=True)
class BenchSettings:
    """How much to measure.  :meth:`full` is the default, :meth:`quick` the CI version."""

    mode: str
    duration_s: float  # simulated seconds per lockstep run
    repeat: int  # runs per lockstep / filter figure
    virtual_duration_s: float  # the virtual bus is slower: shorter runs
    stage_calls: int  # calls per stage timing
    filter_rows: int  # rows of the generated signal CSV
    memory_duration_s: float  # simulated seconds of the RSS-growth run
    realtime_s: float = 60.0  # seconds of the real-time run (0: no real-time section)
    floor_s: float = 10.0  # seconds of the machine-floor loop after it
    startup_runs: int = 7  # process starts per start-up figure
    whole_duration_s: float = 10.0  # simulated seconds of the whole-command runs
    whole_runs: int = 3  # whole-command processes (and half as many 3x as long)
    reference_cycles: int = 5000  # cycles of the python-can virtual reference

    @classmethod
    def full(
        cls, duration_s: float = 10.0, repeat: int = 3, realtime_s: float = 60.0
    ) -> BenchSettings:
        return cls("full", duration_s, repeat, min(duration_s, 2.0), 20_000, 100_000, 120.0,
                   realtime_s, min(10.0, realtime_s), 7, 10.0, 3, 5000)  # fmt: skip

    @classmethod
    def quick(
        cls, duration_s: float = 0.3, repeat: int = 1, realtime_s: float = 1.5
    ) -> BenchSettings:
        return cls("quick", duration_s, repeat, min(duration_s, 0.2), 1_000, 2_000, 3.0,
                   realtime_s, min(0.5, realtime_s), 2, 1.0, 2, 500)  # fmt: skip


# ------------------------------------------------------------------------ helpers
def _median_spread(values: list[float]) -> dict[str, float]:
    return {
        "median": statistics.median(values),
        "min": min(values),
        "max": max(values),
        "runs": len(values),
    }


def _percentiles_us(ns: Sequence[int]) -> dict[str, float]:
    a = np.asarray(ns, dtype=np.float64) / 1e3
    return {
        "median_us": float(np.median(a)),
        "p99_us": float(np.percentile(a, 99)),
        "calls": len(ns),
    }


def machine_facts() -> dict[str, Any]:
    """CPU model, cores, Python version and platform of this machine."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count() or 1
    return {
        "cpu": cpu,
        "cores": os.cpu_count() or 1,
        "cores_usable": usable,
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "platform": platform.platform(terse=True),
    }


def _rss_bytes() -> int:
    """Resident set size now (``/proc/self/statm``); 0 where there is no procfs."""
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _peak_rss_bytes() -> int:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # Linux: KiB


def _firmware_config(scenario: str) -> FirmwareConfig:
    return load_scenario(scenario).firmware


# ----------------------------------------------------------------------- lockstep
def bench_lockstep(
    scenario: str, duration_s: float, repeat: int, logging: bool, interface: str = "simbus"
) -> dict[str, Any]:
    """Real-time factor of a lockstep run (simulated seconds per wall second)."""
    request = resolve(scenario, duration_s=duration_s)
    factors = []
    steal0, wall0 = cpu_steal_ns(), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeat):
            trace = Path(tmp) / f"bench{i}.blf" if logging else None
            r = run_lockstep(request, trace=trace, interface=interface, evaluate=False)
            factors.append(r.real_time_factor)
            cycles = r.cycles
            frames = r.frames_total
            fw = r.controller
    steal = steal_report(steal0, cpu_steal_ns(), None, time.perf_counter() - wall0)
    stats = _median_spread(factors)
    stats.update(
        steal_share=steal["share"] if steal else None,
        scenario=scenario,
        duration_s=duration_s,
        logging=logging,
        interface=interface,
        cycles=cycles,
        frames=frames,
        frames_per_cycle=frames / cycles if cycles else math.nan,
        filter_mode=fw.get("filter_mode"),
        filter_states=fw.get("filter_states"),
        us_per_cycle=1e6 * duration_s / cycles / stats["median"],
    )
    return stats


def bench_lockstep_all(s: BenchSettings) -> list[dict[str, Any]]:
    rows = []
    for scenario, model in LOCKSTEP_SCENARIOS:
        for logging in (True, False):
            row = bench_lockstep(scenario, s.duration_s, s.repeat, logging)
            row["model"] = model
            rows.append(row)
    # The reference: the same loop and frames on python-can's bare virtual bus.
    row = bench_lockstep("free-motion", s.virtual_duration_s, s.repeat, False, "virtual")
    row["model"] = "reference: python-can virtual bus"
    rows.append(row)
    return rows


# ------------------------------------------------------------------------- stages
@dataclass
class Recording:
    """Inputs recorded from a closed loop (plant + interrupt handler, no bus)."""

    adc: list[tuple[int, int, int, int]]
    plant_ns: list[int]


def record_inputs(scenario: str, n: int) -> Recording:
    """Run the scenario's plant and firmware for ``n`` samples in closed loop (the
    command acts from the next sample, as with ``--actuation next-sync``) and record
    the sensor frames' ADC counts; the plant step (advance + sample) is timed."""
    sc = load_scenario(scenario)
    cfg = sc.firmware
    Ts = cfg.sample_period_s
    plant = Plant(sc.plant, sc.seed)
    isr = InterruptHandler(cfg)
    to_volts = sc.plant.dac.to_volts
    volts = to_volts(isr.startup_dac_counts)
    advance, sample = plant.advance, plant.sample
    clock = time.perf_counter_ns
    adc: list[tuple[int, int, int, int]] = []
    plant_ns: list[int] = []
    for _ in range(n):
        t0 = clock()
        advance(volts, Ts)
        s = sample()
        t1 = clock()
        plant_ns.append(t1 - t0)
        adc.append(s)
        volts = to_volts(isr(AdcSample(*s)).dac_counts)
    return Recording(adc, plant_ns)


def _time_each(fn: Callable[..., Any], args: Sequence[tuple[Any, ...]]) -> list[int]:
    clock = time.perf_counter_ns
    out = []
    append = out.append
    for a in args:
        t0 = clock()
        fn(*a)
        t1 = clock()
        append(t1 - t0)
    return out


def timer_overhead_ns(n: int) -> float:
    """Median of back-to-back ``perf_counter_ns`` pairs: included in every stage time."""
    return float(np.median(_time_each(lambda: None, [()] * n)))


def _chain_signals(cfg: FirmwareConfig, adc: list[tuple[int, int, int, int]]) -> dict[str, list]:
    """The calibrated signals and the chain's intermediate values per recorded sample."""
    chain = TorqueFilterChain(cfg)
    T_meas, vel, enc, delta_T, angle, T_filt = [], [], [], [], [], []
    for torque, tacho, current, encoder in adc:
        T, v, _ = calibrate(*adc_read(torque, tacho, current, cfg.adc), cfg.calibration)
        _, _, dT, Tf, _ = chain.step(T, v, encoder)
        T_meas.append(T)
        vel.append(v)
        enc.append(encoder)
        delta_T.append(dT)
        angle.append(chain.angle)
        T_filt.append(Tf)
    return {"T_meas": T_meas, "vel": vel, "enc": enc, "delta_T": delta_T, "angle": angle,
            "T_filtered": T_filt}  # fmt: skip


def _kalman_row(
    stage: str, scenario: str, cfg: FirmwareConfig, adc: list[tuple[int, int, int, int]]
) -> dict[str, Any]:
    sig = _chain_signals(cfg, adc)
    if cfg.ripple.mode == "paper":
        kf: RippleKalman | HarmonicKalman = RippleKalman(
            cfg.ripple, cfg.sample_period_s, cfg.gear_ratio
        )
        args = list(zip(sig["delta_T"], sig["vel"], strict=True))
    else:
        kf = HarmonicKalman(cfg.ripple, cfg.gear_ratio)
        args = list(zip(sig["delta_T"], sig["vel"], sig["angle"], strict=True))
    row = _percentiles_us(_time_each(kf.step, args))
    states = int(np.asarray(kf.P).shape[0])
    row.update(stage=stage, config=f"{scenario}, {cfg.ripple.mode}, {states} states")
    return row


def bench_stages(s: BenchSettings) -> dict[str, Any]:
    """Per-call compute time of every firmware stage and of the plant step."""
    n = s.stage_calls
    recordings = {name: record_inputs(name, n) for name, _ in LOCKSTEP_SCENARIOS}
    rows: list[dict[str, Any]] = []
    gc.collect()

    fm = _firmware_config("free-motion")
    mis = _firmware_config("misalignment")
    lqg = _firmware_config("lqg-tracking")
    fm_adc = recordings["free-motion"].adc

    # ADC read + calibration
    adc_cfg, cal = fm.adc, fm.calibration

    def adc_cal(torque: int, tacho: int, current: int, _enc: int) -> Any:
        return calibrate(*adc_read(torque, tacho, current, adc_cfg), cal)

    row = _percentiles_us(_time_each(adc_cal, fm_adc))
    row.update(stage="ADC read + calibration", config="free-motion")
    rows.append(row)

    # differentiator
    sig = _chain_signals(fm, fm_adc)
    diff = Differentiator(fm.diff_tau_s, fm.sample_period_s)
    row = _percentiles_us(_time_each(diff.step, [(v,) for v in sig["vel"]]))
    row.update(stage="differentiator", config="free-motion")
    rows.append(row)

    # plausibility check: velocity and encoder increment bounds
    check = SensorPlausibility(
        fm.plausibility, fm.sample_period_s, fm.calibration.encoder_counts_per_rev
    )
    row = _percentiles_us(_time_each(check.step, list(zip(sig["vel"], sig["enc"], strict=True))))
    row.update(stage="plausibility check", config="free-motion")
    rows.append(row)

    # ripple Kalman filters: 4th order (free-motion) and 6th order (misalignment)
    for scenario, cfg, order in (("free-motion", fm, "4th"), ("misalignment", mis, "6th")):
        adc = recordings[scenario].adc
        for variant in (cfg, paper_config(cfg)):
            rows.append(_kalman_row(f"ripple Kalman, {order} order", scenario, variant, adc))

    # LQG control stage on the lqg-tracking inputs
    lqg_adc = recordings["lqg-tracking"].adc
    lqg_sig = _chain_signals(lqg, lqg_adc)
    feedback = lqg_sig["T_filtered" if lqg.control.feedback == "T_filtered" else "T_meas"]
    control = TorqueControl(lqg)
    out = IsrOutput()
    row = _percentiles_us(_time_each(control, [(k, T, out) for k, T in enumerate(feedback)]))
    row.update(stage="LQG control stage", config=f"lqg-tracking, {lqg.control.law.name}")
    rows.append(row)

    # the whole interrupt
    for scenario, cfg in (
        ("free-motion", fm),
        ("free-motion", paper_config(fm)),
        ("misalignment", mis),
        ("misalignment", paper_config(mis)),
        ("lqg-tracking", lqg),
    ):
        samples = [(AdcSample(*a),) for a in recordings[scenario].adc]
        isr = InterruptHandler(cfg)
        row = _percentiles_us(_time_each(isr, samples))
        row.update(stage="whole interrupt", config=f"{scenario}, {cfg.ripple.mode}")
        rows.append(row)

    # the plant step the drive emulator does per cycle
    for scenario, _ in LOCKSTEP_SCENARIOS:
        row = _percentiles_us(recordings[scenario].plant_ns)
        row.update(stage="plant step (advance + sample)", config=scenario)
        rows.append(row)

    return {"timer_overhead_us": timer_overhead_ns(n) / 1e3, "rows": rows}


# ------------------------------------------------------------------------- filter
def write_signal_csv(path: Path, rows: int, seed: int = 0) -> None:
    """A signal CSV like a recorded free-motion run: ~156 rad/s motor velocity, 2x/4x
    ripple, sensor noise, 16-bit encoder count (columns time,T_meas,velocity,encoder)."""
    rng = np.random.default_rng(seed)
    Ts = 1e-3
    t = np.arange(rows) * Ts
    vel_true = 156.0 * (1.0 - np.exp(-t / 0.19))
    theta = np.cumsum(vel_true) * Ts
    vel = vel_true + rng.normal(0.0, 0.05, rows)
    T = (
        0.07
        + 0.6 * np.sin(2 * theta + 0.4)
        + 0.25 * np.sin(4 * theta + 1.3)
        + rng.normal(0.0, 0.02, rows)
    )
    cpr = FirmwareConfig().calibration.encoder_counts_per_rev
    enc = np.floor(theta * cpr / (2 * np.pi)).astype(np.int64) % 65536
    with path.open("w", encoding="utf-8") as fh:
        fh.write("time,T_meas,velocity,encoder\n")
        for row in zip(t.tolist(), T.tolist(), vel.tolist(), enc.tolist(), strict=True):
            fh.write("%r,%r,%r,%d\n" % row)  # noqa: UP031


def bench_filter(s: BenchSettings) -> list[dict[str, Any]]:
    """Samples per second of ``hdhil filter`` on a signal CSV (reading, filtering and
    writing the output CSV), recommended and paper mode."""
    from hdhil.rig.offline import OUTPUT_COLUMNS, filter_signal_csv

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "signal.csv"
        write_signal_csv(src, s.filter_rows)
        modes = (("recommended", FirmwareConfig()), ("paper", paper_config(FirmwareConfig())))
        for mode, cfg in modes:
            rates = []
            for _ in range(s.repeat):
                with (Path(tmp) / "out.csv").open("w", newline="", encoding="utf-8") as fh:
                    writer = csv.writer(fh, lineterminator="\n")
                    writer.writerow(OUTPUT_COLUMNS)
                    t0 = time.perf_counter()
                    summary = filter_signal_csv(src, False, cfg, writer)
                    fh.flush()
                    wall = time.perf_counter() - t0
                rates.append(summary.samples / wall)
            row = _median_spread(rates)
            row.update(mode=mode, rows=summary.samples)
            rows.append(row)
    return rows


# ------------------------------------------------------------------------- memory
#: The shortest run (simulated s) whose memory growth rate (per simulated minute, per
#: hour) the memory section reports.  Over a shorter run, one-off growth (allocator
#: arenas, caches) and page-sized steps are most of what changes, and a rate extrapolated
#: from them is noise magnified: such a run reports its growth in MB only, and the rates
#: as not measured (:func:`growth_not_measured`).
MEMORY_GROWTH_MIN_S = 60.0


def growth_not_measured(min_s: float) -> str:
    """What a report prints instead of a memory growth rate from a run shorter than
    ``min_s`` simulated seconds."""
    return f"not measured (run shorter than {min_s:g} s)"


def bench_memory(s: BenchSettings, scenario: str = "misalignment") -> dict[str, Any]:
    """RSS before, during and after one long lockstep run with BLF logging (after a
    short warm-up run of the same kind).

    The RSS is sampled every simulated second from the run's ``stop_requested`` hook
    (polled once per cycle, outside the cycle's work).  Besides the growth over the
    whole run, the slope over its second half (least squares) is reported: the first
    seconds include one-off growth (allocator arenas, caches) that does not repeat.
    The rates (per simulated minute, extrapolated to an hour) come only from a run of
    :data:`MEMORY_GROWTH_MIN_S` or more; from a shorter one they are None, with
    ``rss_growth_rate_note`` saying why.
    """
    every = 1000  # cycles between RSS samples (1 s at 1 kHz)
    calls = 0
    samples: list[tuple[int, int]] = []

    def sample_rss() -> bool:
        nonlocal calls
        if calls % every == 0:
            samples.append((calls, _rss_bytes()))
        calls += 1
        return False

    with tempfile.TemporaryDirectory() as tmp:
        warm = min(1.0, s.memory_duration_s)
        run_lockstep(
            resolve(scenario, duration_s=warm), trace=Path(tmp) / "warm.blf", evaluate=False
        )
        gc.collect()
        before = _rss_bytes()
        r = run_lockstep(
            resolve(scenario, duration_s=s.memory_duration_s),
            trace=Path(tmp) / "mem.blf",
            evaluate=False,
            stop_requested=sample_rss,
        )
        if r.interrupted:  # the hook never asks to stop: Ctrl-C ended the run; end the bench
            raise KeyboardInterrupt
        gc.collect()
        after = _rss_bytes()
        trace_bytes = (Path(tmp) / "mem.blf").stat().st_size
    growth = (after - before) / 2**20
    minutes = r.simulated_s / 60.0
    Ts = r.sample_period_s
    half = [(k * Ts / 60.0, b / 2**20) for k, b in samples if k >= len(samples) * every / 2]
    per_minute: float | None = None
    slope: float | None = None
    note = None
    if r.simulated_s >= MEMORY_GROWTH_MIN_S:
        per_minute = growth / minutes
        slope = (float(np.polyfit([m for m, _ in half], [b for _, b in half], 1)[0])
                 if len(half) >= 3 else per_minute)  # fmt: skip
    else:
        note = growth_not_measured(MEMORY_GROWTH_MIN_S)
    return {
        "scenario": scenario,
        "logging": "blf",
        "simulated_s": r.simulated_s,
        "wall_s": r.wall_s,
        "real_time_factor": r.real_time_factor,
        "frames": r.frames_total,
        "trace_MB": trace_bytes / 2**20,
        "rss_before_MB": before / 2**20,
        "rss_after_MB": after / 2**20,
        "rss_growth_MB": growth,
        "rss_growth_MB_per_sim_minute": per_minute,
        "rss_slope_second_half_MB_per_sim_minute": slope,
        "rss_growth_MB_per_sim_hour_extrapolated": None if slope is None else 60.0 * slope,
        "rss_growth_rate_note": note,
        "rss_samples": len(samples),
    }


# ---------------------------------------------------------------------- real time
#: The issue's real-time goals: SYNC jitter p99 and p99.9 (µs), misses per 100 000 cycles.
REALTIME_GOALS = {"p99_us": 100.0, "p99.9_us": 500.0, "misses_per_100k": 1.0}


def bench_realtime(s: BenchSettings, scenario: str = "free-motion") -> dict[str, Any]:
    """One ``--realtime`` run of ``s.realtime_s`` seconds without logging, then the
    machine floor for ``s.floor_s`` seconds (same spin window and process state)."""
    r = run_lockstep(
        resolve(scenario, duration_s=s.realtime_s),
        trace=None,
        evaluate=False,
        realtime=True,
        realtime_config=RealtimeConfig(floor_s=s.floor_s),
    )
    rt = dict(r.realtime or {})
    rt.pop("jitter_histogram", None)
    jitter = rt["jitter_us"]
    goals = REALTIME_GOALS
    rt["goals"] = {
        "p99_us": {"goal": goals["p99_us"], "met": jitter["p99"] <= goals["p99_us"]},
        "p99.9_us": {"goal": goals["p99.9_us"], "met": jitter["p99.9"] <= goals["p99.9_us"]},
        "misses_per_100k": {
            "goal": goals["misses_per_100k"],
            "met": rt["misses_per_100k"] <= goals["misses_per_100k"],
        },
    }
    rt.update(scenario=scenario, duration_s=s.realtime_s, logging=False, wall_s=r.wall_s)
    return rt


# ------------------------------------------------------------------------- report
# ------------------------------------------------------------------------ start-up
#: The start-up goals: help within this factor of python-can's ``can.logger --help``,
#: the first cycle of ``hdhil run`` within this many seconds of the process start.
HELP_GOAL_FACTOR = 2.0
FIRST_CYCLE_GOAL_S = 0.3


def _process_s(argv: Sequence[str]) -> tuple[float, str]:
    """Wall time of one process from spawn to exit, and its stderr."""
    t0 = time.perf_counter()
    proc = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          timeout=120, check=False)  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise UserError(f"bench start-up: {' '.join(argv[1:3])} failed: {proc.stderr.strip()}")
    return wall, proc.stderr


def bench_startup(s: BenchSettings) -> dict[str, Any]:
    """Whole-process start-up times, each the median of ``startup_runs`` process starts,
    taken in turns (one of each per round, so a slow moment of the machine hits every
    figure alike), with the ratio to ``python -c 'import can'`` measured in the same
    rounds: ``hdhil --help``, ``hdhil dump --help``, python-can's ``can.logger --help``
    (the help goal's reference), and ``hdhil run`` of one sample with its default BLF
    trace: the time from the process's spawn to the end of its first cycle, and to its
    exit."""
    from hdhil.analysis.speed import STAGES_CHILD, timed_process

    py = sys.executable
    figures: dict[str, list[float]] = {
        "import_can": [], "can_logger_help": [], "hdhil_help": [], "dump_help": [],
        "run_first_cycle": [], "run_whole": [],
    }  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        trace = str(Path(tmp) / "startup.blf")
        run_args = ["run", "--duration", "0.001", "--trace", trace, "--no-evaluate"]
        for _ in range(s.startup_runs):
            figures["import_can"].append(_process_s([py, "-c", "import can"])[0])
            figures["can_logger_help"].append(_process_s([py, "-m", "can.logger", "--help"])[0])
            figures["hdhil_help"].append(_process_s([py, "-m", "hdhil", "--help"])[0])
            figures["dump_help"].append(_process_s([py, "-m", "hdhil", "dump", "--help"])[0])
            # hdhil run with its first cycle stamped (the speed section's child)
            run = timed_process([py, "-c", STAGES_CHILD, *run_args])
            if "first_cycle" not in run["stamps"]:
                raise UserError("bench start-up: hdhil run reported no first cycle")
            figures["run_first_cycle"].append(run["stamps"]["first_cycle"] - run["spawned"])
            figures["run_whole"].append(run["wall_s"])
    ref = statistics.median(figures["import_can"])
    logger = statistics.median(figures["can_logger_help"])
    labels = {
        "import_can": "python -c 'import can' (reference)",
        "can_logger_help": "python -m can.logger --help",
        "hdhil_help": "hdhil --help",
        "dump_help": "hdhil dump --help",
        "run_first_cycle": "hdhil run: spawn to the end of the first cycle",
        "run_whole": "hdhil run of one sample, whole process",
    }
    rows = []
    for key, values in figures.items():
        med = statistics.median(values)
        row = {"figure": key, "label": labels[key], **_median_spread(values),
               "to_import_can": med / ref}  # fmt: skip
        if key in ("hdhil_help", "dump_help"):
            row["to_can_logger_help"] = med / logger
            row["goal_met"] = med <= HELP_GOAL_FACTOR * logger
        elif key == "run_first_cycle":
            row["goal_met"] = med <= FIRST_CYCLE_GOAL_S
        rows.append(row)
    return {"runs": s.startup_runs, "rows": rows, "help_goal_factor": HELP_GOAL_FACTOR,
            "first_cycle_goal_s": FIRST_CYCLE_GOAL_S}  # fmt: skip


def format_startup_section(st: dict[str, Any]) -> list[str]:
    lines = [
        f"Start-up (whole processes, median of {st['runs']} starts each, in turns; goals: "
        f"help within {st['help_goal_factor']:g}x can.logger --help, first cycle within "
        f"{st['first_cycle_goal_s']:g} s)"
    ]
    rows = []
    for r in st["rows"]:
        goal = "" if "goal_met" not in r else ("met" if r["goal_met"] else "NOT met")
        to_logger = f"{r['to_can_logger_help']:.2f}x" if "to_can_logger_help" in r else ""
        rows.append([r["label"], f"{r['median']:.3f}", f"{r['min']:.3f}-{r['max']:.3f}",
                     f"{r['to_import_can']:.2f}x", to_logger, goal])  # fmt: skip
    lines += _table(
        ["figure", "median s", "min-max s", "/ import can", "/ can.logger", "goal"],
        rows,
        [False, True, True, True, True, False],
    )
    return lines


def run_benchmarks(
    duration_s: float = 10.0,
    repeat: int = 3,
    quick: bool = False,
    realtime_s: float | None = None,
    startup_runs: int | None = None,
    on_section: Callable[[str], object] | None = None,
) -> dict[str, Any]:
    """Every section; ``quick`` shrinks them (``duration_s`` / ``repeat`` still apply).
    ``realtime_s``: seconds of the real-time run (default 60, quick 1.5; 0 leaves the
    section out).  ``startup_runs``: process starts per start-up figure (default 7,
    quick 2).  ``on_section(name)`` is called as each section starts (progress).

    - **lockstep**: real-time factor (simulated seconds per wall second) of
      :func:`hdhil.rig.runner.run_lockstep` for free-motion (4th-order ripple model),
      misalignment (6th order) and lqg-tracking, each with BLF logging on and off, plus
      the reference: the same free-motion loop (same frames) on python-can's bare
      ``virtual`` bus instead of ``simbus``;
    - **stages**: firmware compute time per call of each interrupt stage
      (``time.perf_counter_ns`` around every call, on inputs recorded from a closed-loop
      run of the plant and the interrupt handler without a bus), the whole interrupt,
      and the plant step (advance + sample) the drive emulator does per cycle;
    - **filter**: offline throughput of ``hdhil filter``'s signal-CSV code path
      (:func:`hdhil.rig.offline.filter_signal_csv`) on a generated CSV;
    - **memory**: peak RSS of the process (``ru_maxrss``) and the resident-memory growth
      over one long lockstep run with logging, per simulated minute (from runs of
      :data:`MEMORY_GROWTH_MIN_S` or more; ``quick`` reports it as not measured);
    - **real time**: one free-motion real-time run of ``realtime_s`` seconds, no logging
      (:mod:`hdhil.rig.realtime`): SYNC jitter p50/p99/p99.9/max, deadline misses (and
      per 100 000 cycles), sensor-to-command latency, compute per interrupt stage, each
      against :data:`REALTIME_GOALS`, and the machine floor: the bare sleep+spin loop in
      the same process state;
    - **campaign**: ``hdhil campaign`` on the local process pool: variants per minute on
      1 and N workers (N = the machine's cores), the speed-up, and the campaign
      machinery's overhead per variant (:mod:`hdhil.rig.campaign_bench`);
    - **start-up**: whole-process times of ``hdhil --help``, ``hdhil dump --help``,
      python-can's ``can.logger --help`` and the time from spawning ``hdhil run`` to the
      end of its first cycle (and to its exit), each the median of ``startup_runs``
      starts taken in turns, with the ratio to ``python -c 'import can'`` of the same
      rounds and the start-up goals (:data:`HELP_GOAL_FACTOR`,
      :data:`FIRST_CYCLE_GOAL_S`);
    - **speed**: the main job as a whole process by stage, python-can's ``virtual`` bus
      carrying the same frames as the loop's reference, the cost model (CPU per cycle as
      fixed + per joint + per frame) and the speed goals' verdicts
      (:mod:`hdhil.analysis.speed`);
    - **joints**: the lockstep loop's CPU and wall time per cycle and per joint for 1, 2,
      4 and 7 joints of independent plants (and the shipped rigs with the arm's plant),
      whether it grows no faster than linearly, and ``hdhil run`` of ``rehabexos`` and
      ``arm7`` as whole processes against their speed goals
      (:mod:`hdhil.analysis.rig_speed`; ``hdhil bench --only joints`` runs it alone).

    ``quick`` shrinks every section (CI and the tests); the default takes about six
    minutes on a 2-core machine, one of them the real-time run.
    """
    if quick:
        s = BenchSettings.quick(duration_s, repeat, 1.5 if realtime_s is None else realtime_s)
    else:
        s = BenchSettings.full(duration_s, repeat, 60.0 if realtime_s is None else realtime_s)
    if startup_runs is not None:
        s = dataclasses.replace(s, startup_runs=startup_runs)
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    wall0 = time.perf_counter()

    def section(name: str) -> None:
        if on_section is not None:
            on_section(name)

    section("lockstep")
    lockstep = bench_lockstep_all(s)
    section("stages")
    stages = bench_stages(s)
    section("filter")
    filt = bench_filter(s)
    section("memory")
    memory = bench_memory(s)
    memory["peak_rss_MB"] = _peak_rss_bytes() / 2**20
    section("real time")
    rt = bench_realtime(s) if s.realtime_s > 0 else None
    section("campaign")
    from hdhil.rig.campaign_bench import bench_campaign

    if s.mode == "quick":
        campaign = bench_campaign(variants=4, duration_s=0.5, repeat=1)
    else:
        campaign = bench_campaign(variants=16, duration_s=2.0, repeat=s.repeat)
    section("start-up")
    with threadpool_limits(limits=1):  # no idle BLAS worker spinning beside the children
        startup = bench_startup(s)
    section("speed")
    from hdhil.analysis.speed import bench_speed, speed_goals

    speed = bench_speed(s.whole_duration_s, s.whole_runs, s.duration_s, s.repeat,
                        s.reference_cycles, 50 if s.mode == "quick" else 300)  # fmt: skip
    loop_row = next((r for r in lockstep if r["scenario"] == "free-motion" and r["logging"]
                     and r["interface"] == "simbus"), None)  # fmt: skip
    first = next(r for r in startup["rows"] if r["figure"] == "run_first_cycle")
    goals = speed_goals(speed["whole"], loop_row, speed["reference"], first["median"])
    section("joints")
    joints = bench_joints_section(s)
    section("done")
    return {
        "started": started,
        "mode": s.mode,
        "machine": machine_facts(),
        "settings": {
            "duration_s": s.duration_s,
            "repeat": s.repeat,
            "virtual_duration_s": s.virtual_duration_s,
            "stage_calls": s.stage_calls,
            "filter_rows": s.filter_rows,
            "memory_duration_s": s.memory_duration_s,
            "realtime_s": s.realtime_s,
            "floor_s": s.floor_s,
            "startup_runs": s.startup_runs,
        },
        "lockstep": lockstep,
        "stages": stages,
        "filter": filt,
        "memory": memory,
        "realtime": rt,
        "campaign": campaign,
        "startup": startup,
        "speed": speed,
        "goals": goals,
        "joints": joints,
        "wall_s": time.perf_counter() - wall0,
    }


def format_bench(report: dict[str, Any]) -> str:
    m, st = report["machine"], report["settings"]
    lines = [
        f"hdhil bench ({report['mode']} run, {report['started']}, {report['wall_s']:.0f} s)",
        f"machine: {m['cpu']}, {m['cores']} cores ({m['cores_usable']} usable), "
        f"{m['implementation']} {m['python']}, {m['platform']}",
        "",
        f"Lockstep real-time factor (simulated s per wall s; median of {st['repeat']} runs of "
        f"{st['duration_s']:g} s, virtual bus {st['virtual_duration_s']:g} s)",
    ]
    rows = [
        [
            r["scenario"],
            r["model"],
            f"{r['filter_mode']} ({r['filter_states']} st.)",
            "BLF" if r["logging"] else "off",
            r["interface"],
            f"{r['median']:.1f}x",
            f"{r['min']:.1f}-{r['max']:.1f}x",
            f"{r['us_per_cycle']:.0f}",
            f"{r['frames_per_cycle']:.1f}",
            "n/a" if r.get("steal_share") is None else f"{r['steal_share']:.1%}",
        ]
        for r in report["lockstep"]
    ]
    lines += _table(
        ["scenario", "model", "filter", "log", "bus", "RTF", "min-max", "us/cycle",
         "frames/cycle", "steal"],
        rows,
        [False] * 5 + [True] * 5,
    )  # fmt: skip
    lines.append(
        "(steal: the hypervisor's steal time over the figure's runs, all CPUs; wall time "
        "lost to it slows the runs on a shared machine)"
    )
    stg = report["stages"]
    lines += [
        "",
        f"Firmware compute per call ({st['stage_calls']} calls on recorded closed-loop "
        f"inputs; includes {stg['timer_overhead_us'] * 1e3:.0f} ns timer overhead)",
    ]
    rows = [
        [r["stage"], r["config"], f"{r['median_us']:.2f}", f"{r['p99_us']:.2f}"]
        for r in stg["rows"]
    ]
    lines += _table(["stage", "config", "median us", "p99 us"], rows, [False, False, True, True])
    lines += [
        "",
        f"Offline `hdhil filter` (signal CSV, {st['filter_rows']} rows, read + filter + write)",
    ]
    rows = [
        [r["mode"], f"{r['median']:,.0f}", f"{r['min']:,.0f}-{r['max']:,.0f}", str(r["runs"])]
        for r in report["filter"]
    ]
    lines += _table(["mode", "samples/s", "min-max", "runs"], rows, [False, True, True, True])
    lines += ["", *format_memory_section(report["memory"])]
    if report.get("realtime"):
        lines += ["", *format_realtime_section(report["realtime"])]
    if report.get("campaign"):
        from hdhil.rig.campaign_bench import format_campaign_section

        lines += ["", *format_campaign_section(report["campaign"])]
    if report.get("startup"):
        lines += ["", *format_startup_section(report["startup"])]
    if report.get("speed"):
        from hdhil.analysis.speed import format_speed_section

        lines += ["", *format_speed_section(report["speed"], report["goals"])]
    if report.get("joints"):
        from hdhil.analysis.rig_speed import format_joints_section

        lines += ["", *format_joints_section(report["joints"])]
    return "\n".join(lines)


def bench_joints_section(s: BenchSettings) -> dict[str, Any]:
    """The joints section (:mod:`hdhil.analysis.rig_speed`): the loop's cost for 1, 2, 4
    and 7 joints in runs of at most 2 s, and the rigs' whole command for the speed
    section's ``whole_duration_s``, ``whole_runs`` times (once in the quick version)."""
    from hdhil.analysis.rig_speed import bench_joints

    runs = 1 if s.mode == "quick" else s.whole_runs
    return bench_joints(min(s.duration_s, 2.0), s.repeat, s.whole_duration_s, runs)


def run_joints_only(
    duration_s: float = 10.0, repeat: int = 3, quick: bool = False
) -> dict[str, Any]:
    """The joints section alone (``hdhil bench --only joints``): a report with the
    machine, the settings and ``joints``, which :func:`format_joints_only` prints."""
    s = BenchSettings.quick(duration_s, repeat) if quick else BenchSettings.full(duration_s, repeat)
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    wall0 = time.perf_counter()
    joints = bench_joints_section(s)
    return {"started": started, "mode": s.mode, "only": "joints", "machine": machine_facts(),
            "settings": {"duration_s": s.duration_s, "repeat": s.repeat,
                         "whole_duration_s": s.whole_duration_s, "whole_runs": s.whole_runs},
            "joints": joints, "wall_s": time.perf_counter() - wall0}  # fmt: skip


def format_joints_only(report: dict[str, Any]) -> str:
    """The text report of :func:`run_joints_only`."""
    from hdhil.analysis.rig_speed import format_joints_section

    m = report["machine"]
    return "\n".join([
        f"hdhil bench --only joints ({report['mode']} run, {report['started']}, "
        f"{report['wall_s']:.0f} s)",
        f"machine: {m['cpu']}, {m['cores']} cores ({m['cores_usable']} usable), "
        f"{m['implementation']} {m['python']}, {m['platform']}",
        "",
        *format_joints_section(report["joints"]),
    ])  # fmt: skip


def format_memory_section(mem: dict[str, Any]) -> list[str]:
    """The memory section of the text report: growth rates only from a run of
    :data:`MEMORY_GROWTH_MIN_S` or more, "not measured" otherwise."""
    rows = [
        ["peak RSS (ru_maxrss, whole benchmark)", f"{mem['peak_rss_MB']:.1f} MB"],
        [
            f"RSS growth over a {mem['simulated_s']:g} s {mem['scenario']} run, BLF logging "
            f"({mem['frames']} frames, {mem['trace_MB']:.1f} MB trace, "
            f"{mem['real_time_factor']:.1f}x)",
            f"{mem['rss_growth_MB']:+.2f} MB ({mem['rss_before_MB']:.1f} -> "
            f"{mem['rss_after_MB']:.1f} MB)",
        ],
        ["  per simulated minute, whole run",
         _rate(mem, "rss_growth_MB_per_sim_minute", ".2f")],
        ["  per simulated minute, second half (least squares)",
         _rate(mem, "rss_slope_second_half_MB_per_sim_minute", ".2f")],
        ["  second-half slope extrapolated to 1 h (goal < 20 MB)",
         _rate(mem, "rss_growth_MB_per_sim_hour_extrapolated", ".1f")],
    ]  # fmt: skip
    return ["Memory", *_table(["figure", "value"], rows, [False, True])]


def _rate(mem: dict[str, Any], key: str, spec: str) -> str:
    """A memory growth rate of the memory section, or why it was not measured."""
    value = mem.get(key)
    if value is None:
        return mem.get("rss_growth_rate_note") or growth_not_measured(MEMORY_GROWTH_MIN_S)
    return f"{value:+{spec}} MB"


def _pct_cells(p: dict[str, float]) -> list[str]:
    return [f"{p[q]:.1f}" for q in PERCENTILE_KEYS]


def format_realtime_section(rt: dict[str, Any]) -> list[str]:
    """The real-time section of the text report."""
    pace = rt["pacing"]
    lines = [
        f"Real-time mode ({rt['scenario']}, {rt['duration_s']:g} s paced at "
        f"{rt['sample_period_s'] * 1e3:g} ms, no logging; spin window {pace['spin_us']:.0f} µs, "
        f"loop CPU share {pace['cpu_share']:.0%} of an RT limit of "
        f"{pace['rt_share_limit']:.0%})",
        f"applied: {'; '.join(rt['applied']) or 'nothing'}",
    ]
    if rt["refused"]:
        lines.append(f"refused: {'; '.join(rt['refused'])}")
    if rt.get("steal"):
        lines.append(format_steal(rt["steal"]))
    rows = [
        ["SYNC jitter (late)", *_pct_cells(rt["jitter_us"])],
        ["sensor frame -> command", *_pct_cells(rt["latency_us"])],
        ["cycle work (frames, nodes)", *_pct_cells(rt["cycle_work_us"])],
        ["sleep overshoot", *_pct_cells(rt["sleep_overshoot_us"])],
        ["interrupt compute", *_pct_cells(rt["isr_us"])],
        *([f"  {st['label']}", *_pct_cells(st)] for st in rt["stages_us"].values()),
    ]
    floor = rt.get("floor")
    if floor:
        rows += [
            [f"machine floor: start jitter ({floor['duration_s']:g} s)",
             *_pct_cells(floor["jitter_us"])],
            ["machine floor: sleep overshoot", *_pct_cells(floor["sleep_overshoot_us"])],
        ]  # fmt: skip
    lines += _table(["µs", *PERCENTILE_KEYS], rows, [False] + [True] * len(PERCENTILE_KEYS))
    g = rt["goals"]

    def verdict(key: str) -> str:
        return "met" if g[key]["met"] else "NOT met"

    lines.append(
        f"deadline misses: {rt['deadline_misses']} in {rt['cycles']} cycles "
        f"({rt['misses_per_100k']:.1f} per 100 000; goal <= {g['misses_per_100k']['goal']:g}: "
        f"{verdict('misses_per_100k')}); jitter p99 goal <= {g['p99_us']['goal']:g} µs: "
        f"{verdict('p99_us')}, p99.9 goal <= {g['p99.9_us']['goal']:g} µs: {verdict('p99.9_us')}"
    )
    if floor:
        lines.append(
            f"machine floor: {floor['deadline_misses']} misses in {floor['cycles']} cycles "
            f"({floor['misses_per_100k']:.1f} per 100 000) with {floor['work_us']:.0f} µs busy "
            f"work per cycle and no hdhil code; sleep woke past the spin window "
            f"{floor['late_wakeups']} times (run: {rt['late_wakeups']} times in "
            f"{rt['cycles']} cycles)"
            + (f"; {format_steal(floor['steal'])}" if floor.get("steal") else "")
        )
    return lines
