"""``hdhil run --realtime``: the lockstep run paced by the wall clock at the sample period.

Pacing
------
Cycle k's SYNC is due at ``t0 + k·Ts`` on the monotonic clock (:func:`time.perf_counter_ns`).
The runner sleeps until a *spin window* before the deadline, then busy-waits to it.  The
schedule is absolute: a cycle that overruns is not skipped, the next SYNC goes out at
once and the following ones catch up, as a hardware timer would keep its phase.

The spin window absorbs late wake-ups of ``time.sleep``: a wake-up later than the window
makes SYNC late.  It is sized from the period and the measured work of a cycle
(:class:`SpinPlan`): :data:`SPIN_FRACTION` of the period (600 µs at 1 kHz), but never so
wide that the loop's CPU share (spin + work per period) exceeds the kernel's real-time
throttling limit (``/proc/sys/kernel/sched_rt_runtime_us`` / ``sched_rt_period_us``,
95 % by default) minus :data:`RT_SHARE_MARGIN`.  Under ``SCHED_FIFO`` a loop above that
limit is parked by the kernel for the rest of the throttling period (50 ms every second
at 95 %).  The window is re-sized every second from the mean work of the last second.
``--spin-us`` fixes it instead.

Clock: the simulated bus's clock (:class:`WallClock`) reads wall time since the run
started, so every frame is requested at the moment it was really sent and trace
timestamps are real (the wire time of each frame is still modelled by ``simbus``).  The
drive stays locked to SYNC: it integrates the plant one period per SYNC, whatever the
wall time between two SYNCs was.

Statistics
----------
Per operation cycle, kept in ``array('d')``.  Start-up and stop cycles are not counted,
except the last start-up cycle when the first interrupt already ran in it: the controller
turns operational on the drive's statusword, and in real time the cycle's sensor frame
may arrive after it (frames are requested at wall time, so their order on the wire is
that of the moments they were sent).  So the statistics cover exactly the cycles in
which the interrupt ran.

- **jitter**: when SYNC k was actually handed to the bus minus its deadline;
- **latency**: from the controller receiving ``DRIVE_TPDO1`` (the frame handed to its
  frame handler) to the command ``DRIVE_RPDO1`` being handed to the bus: decode,
  interrupt, encode, send;
- **interrupt compute**: the interrupt body (:class:`firmware.isr.InterruptHandler` call);
- **stages** of the interrupt (:data:`STAGES`), contiguous, so that they add up to the
  interrupt's time in every cycle;
- **cycle work**: from the deadline (or the wake-up, if later) to the end of the cycle's
  frame handling: what the loop computes per period besides spinning;
- **sleep overshoot**: how late ``time.sleep`` returned (the machine's share of the tail);
- **misses**: cycles whose command was not handed to the bus before the next SYNC's
  deadline (or never).

Instrumentation, for the run only (the firmware's code is unchanged and runs as before
outside real-time mode): the controller bus's ``send`` and the controller's frame
handler ``on_message`` are wrapped (instance attributes), and the interrupt handler and
its stage objects (the filter chain, its plausibility stage, differentiator and Kalman
filter, the control law or the reference generator) get a timed subclass of their own
class (:class:`StageTimer`) whose one overridden method takes ``perf_counter_ns`` time
stamps around the original.  A stage object the controller swaps in at run time (new
parameters over SDO) is timed from the next interrupt on.  Everything is restored at the
end.  The time stamps cost about 2.2 µs per interrupt, counted in its compute time
(free-motion, medians of 20 000 calls on recorded inputs: 3.1 µs plain, 5.3 µs timed).

Machine floor
-------------
:meth:`RealtimeLoop.measure_floor` (``--floor-s``) runs the bare loop after the run, in the
same process state (same spin window, affinity, priority, no collector) and with the
run's median cycle work as busy-waiting, but no hdhil code: the jitter and misses it
shows are the machine's (scheduler, timer, hypervisor), and bound what the run can reach.

Determinism
-----------
Each of these is applied where permitted and reported in ``applied`` / ``refused``, and
undone when the loop ends:

- ``gc``: ``gc.collect()`` before the loop and ``gc.disable()`` during it.  A generation-2
  collection in the middle of a cycle costs milliseconds once the heap holds the
  scenario, the DBC and the CANopen object dictionaries.  The loop itself allocates
  little, so memory stays flat over minutes without the collector (reference counting
  frees everything that is not cyclic).
- ``affinity``: :func:`os.sched_setaffinity` to one CPU: no migrations, warm caches.  The
  CPU is the last allowed one that runs no other user-space real-time task
  (:func:`rt_tasks_per_cpu`): two ``SCHED_FIFO`` loops on one CPU take turns and together
  exceed the RT throttling limit, which parks both for tens of milliseconds.
- ``timer slack``: ``prctl(PR_SET_TIMERSLACK, 1)`` (Linux, via :mod:`ctypes`): the kernel
  may otherwise delay a sleeping task's wake-up by up to 50 µs to batch timers.  Linux
  gives real-time tasks no slack at all, so it only matters when ``SCHED_FIFO`` is refused.
- ``SCHED_FIFO``: :func:`os.sched_setscheduler` with real-time priority 50 (root or
  CAP_SYS_NICE only).  It keeps other processes from preempting the loop and bounds the
  tail on a loaded machine; the kernel's RT throttling still guarantees others a share.
  With ``SCHED_RESET_ON_FORK``: a thread or process started during the loop (a trace
  writer, say) runs under the normal policy; inheriting ``SCHED_FIFO`` and the loop's
  CPU, it could only run while the loop sleeps, and a loop waiting for it would spin
  forever.
- ``mlockall`` (``--mlock``, off by default): ``mlockall(MCL_CURRENT | MCL_FUTURE |
  MCL_ONFAULT)`` (Linux, via :mod:`ctypes`; root, CAP_IPC_LOCK or a large enough
  ``RLIMIT_MEMLOCK``): pages the process touches stay resident, so the loop never waits
  for a page to come back from swap.  ``MCL_ONFAULT`` locks pages as they are touched
  instead of faulting in every mapping at once (which costs about 0.4 s and 220 MB for
  this process).

Measured, each change against the previous state (60 s free-motion runs without
logging, as root, on the shared 2-core VM, runs of the compared settings interleaved and
only while no other real-time task was running, before the plausibility stage was added;
medians; SYNC jitter p99.9 and deadline misses in 60 000 cycles):

- spin window 200 µs -> 600 µs (3 runs each): p99.9 391 -> 72 µs, misses 28 -> 4; the
  cycles whose sleep woke later than the window 106 -> 23;
- timer slack 1 ns: nothing to measure under ``SCHED_FIFO``, where the kernel gives the
  task no slack; without ``SCHED_FIFO`` (3 runs each) p99.9 798 -> 404 µs, misses 54 -> 35;
- ``mlockall`` (6 runs each): p99.9 76 -> 82 µs, misses 16 -> 10.5, within the spread of
  the runs (this VM has no swap and 22 GB free), hence off by default.

The misses left are stalls of 1-5 ms in which the loop does not run at all.  The machine
floor shows them too (medians per 60 s, README: sleeps woken past the window 30 in the
run against 25 in the bare loop, misses 20 against 11; the rate follows the machine's
load, 15 minutes earlier 7 against 1).  Within a run they recur
at a fixed phase of a 100 ms rhythm that is not the run's own (its heartbeats fall on
other cycles).  Not done here: a ``PREEMPT_RT`` kernel (this VM's is ``PREEMPT_NONE``),
isolated CPUs (``isolcpus``, ``nohz_full``), interrupts steered away from the loop's CPU
(here the block device's go to CPU 1): the next steps on a dedicated bench PC.

Other interfaces
----------------
``--interface virtual`` (and any real python-can interface) works too: pacing and
statistics are the same, only the clock is the monotonic clock the non-simulated path
already uses.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import gc
import math
import os
import sys
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can

from hdhil.can.simbus import SimClock
from hdhil.core.dataconf import ConfigError
from hdhil.dbc import frame_id

#: Spin window by default, as a fraction of the sample period (600 µs at 1 kHz).
SPIN_FRACTION = 0.6

#: The loop's CPU share (spin + work per period) stays this far below the kernel's RT
#: throttling limit.
RT_SHARE_MARGIN = 0.15

#: The kernel's default RT throttling limit (950 000 µs per 1 000 000 µs), assumed when
#: ``/proc/sys/kernel/sched_rt_*`` cannot be read.
RT_SHARE_DEFAULT = 0.95

#: The spin window is re-sized after every this many seconds of cycles.
RESIZE_EVERY_S = 1.0

#: SCHED_FIFO priority asked for (1..99); 50 is below the kernel's IRQ threads.
FIFO_PRIORITY = 50

#: Timer slack asked for with ``prctl(PR_SET_TIMERSLACK)`` (ns; 0 would mean "default").
TIMER_SLACK_NS = 1

#: Jitter histogram bin edges in µs (1-2-5 log spacing); below the first edge (early or
#: under 1 µs late) is the first bin, from the last edge on the last.
HISTOGRAM_EDGES_US = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000)

#: The interrupt's stages as timed in real-time mode (key, label), in execution order
#: (``InterruptHandler.__call__``).  Sensor plausibility, the differentiator and the
#: ripple Kalman filter are timed around their ``step``; "model torque, error, angle" is
#: the rest of the filter chain (``T_mod``, ``Delta_T``, the encoder angle,
#: ``Torque_f``); "control / reference"
#: is the LQG law (it also converts its command to DAC counts) or
#: ``reference_generation``; "DAC write, outputs" is ``write_dac0`` and the output copies.
STAGES: tuple[tuple[str, str], ...] = (
    ("adc_calibration", "ADC read + calibration"),
    ("plausibility", "sensor plausibility"),
    ("differentiator", "differentiator"),
    ("ripple_kalman", "ripple Kalman"),
    ("torque_model", "model torque, error, angle"),
    ("control_reference", "control / reference"),
    ("dac_output", "DAC write, outputs"),
)

_now_ns = time.perf_counter_ns
_sleep = time.sleep

# Linux prctl options and mlockall flags (<linux/prctl.h>, <asm-generic/mman-common.h>;
# powerpc and sparc use other mlockall values: mlockall is not attempted there).
PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4


@dataclass(frozen=True)
class RealtimeConfig:
    """How ``--realtime`` paces the loop and what it applies (each where permitted).

    ``spin_us``: the spin window before each deadline in µs; None sizes it from the
    period and the measured work (:class:`SpinPlan`).  ``floor_s``: seconds of the
    machine-floor loop after the run (0: none).  The switches turn one measure each on or
    off (for comparisons); ``mlock`` is off by default (``--mlock``), the others on.
    """

    spin_us: float | None = None
    floor_s: float = 0.0
    affinity: bool = True
    timer_slack: bool = True
    fifo: bool = True
    mlock: bool = False
    gc_off: bool = True

    def check(self, sample_period_s: float) -> None:
        """One-line :class:`ConfigError` for values that cannot work at this period."""
        period_us = sample_period_s * 1e6
        if self.spin_us is not None and not (
            math.isfinite(self.spin_us) and 0 <= self.spin_us < period_us
        ):
            raise ConfigError(
                f"--spin-us must be >= 0 and below the sample period ({period_us:g} µs), "
                f"got {self.spin_us:g}"
            )
        if not (math.isfinite(self.floor_s) and self.floor_s >= 0):
            raise ConfigError(f"--floor-s must be >= 0 seconds, got {self.floor_s:g}")


def rt_share_limit(sysctl_dir: str = "/proc/sys/kernel") -> tuple[float, str]:
    """The kernel's RT throttling limit as a CPU share, and where it came from.

    ``sched_rt_runtime_us = -1`` means no throttling (share 1.0)."""
    try:
        with open(os.path.join(sysctl_dir, "sched_rt_runtime_us"), encoding="ascii") as fh:
            runtime = int(fh.read())
        with open(os.path.join(sysctl_dir, "sched_rt_period_us"), encoding="ascii") as fh:
            period = int(fh.read())
    except (OSError, ValueError):
        return RT_SHARE_DEFAULT, "kernel default (sched_rt_* not readable)"
    if runtime < 0 or period <= 0:
        return 1.0, "sched_rt_runtime_us = -1 (no throttling)"
    source = f"sched_rt_runtime_us {runtime} / sched_rt_period_us {period}"
    return min(1.0, runtime / period), source


@dataclass
class SpinPlan:
    """The spin window: :data:`SPIN_FRACTION` of the period, capped so that spin + mean
    cycle work stays below the RT throttling limit minus :data:`RT_SHARE_MARGIN`; or a
    fixed window (``--spin-us``)."""

    period_ns: int
    share_limit: float
    fixed_ns: int | None = None

    @property
    def budget_ns(self) -> int:
        """CPU time per period the loop may use (spin + work)."""
        return round((self.share_limit - RT_SHARE_MARGIN) * self.period_ns)

    def spin_ns(self, mean_work_ns: float) -> int:
        if self.fixed_ns is not None:
            return self.fixed_ns
        wanted = round(SPIN_FRACTION * self.period_ns)
        return max(0, min(wanted, round(self.budget_ns - mean_work_ns)))


class WallClock(SimClock):
    """A :class:`SimClock` whose time is wall time (perf counter) since ``start``."""

    __slots__ = ("t0_ns",)

    def __init__(self) -> None:
        self.t0_ns = _now_ns()

    @property  # type: ignore[override]
    def now(self) -> float:  # type: ignore[override]
        return (_now_ns() - self.t0_ns) * 1e-9

    def restart(self, t0_ns: int) -> None:
        self.t0_ns = t0_ns


# ------------------------------------------------------------------ instrumentation
def _timed_methods(kind: str, base: type, loop: RealtimeLoop) -> dict[str, Any]:
    """The one method a stage object's timed class overrides, per stage ``kind``: it calls
    ``base``'s and leaves time stamps in ``loop``."""
    now = _now_ns
    if kind == "isr":
        base_call = base.__call__

        def __call__(self: Any, sample: Any) -> Any:
            loop._time_stages_of(self)
            loop._chain_in = loop._chain_out = loop._control_out = 0
            loop._plaus_ns = loop._diff_ns = loop._kalman_ns = 0
            t0 = now()
            out = base_call(self, sample)
            loop._isr_done(t0, now())
            return out

        return {"__call__": __call__}
    if kind == "chain":
        base_step = base.step

        def step(self: Any, T_meas: float, velocity: float, encoder: int | None = None) -> Any:
            loop._chain_in = now()
            out = base_step(self, T_meas, velocity, encoder)
            loop._chain_out = now()
            return out

        return {"step": step}
    if kind == "plausibility":
        base_step = base.step

        def plausibility_step(self: Any, velocity: float, encoder: int | None) -> Any:
            t = now()
            out = base_step(self, velocity, encoder)
            loop._plaus_ns += now() - t
            return out

        return {"step": plausibility_step}
    if kind == "differentiator":
        base_step = base.step

        def differentiator_step(self: Any, v: float) -> float:
            t = now()
            out = base_step(self, v)
            loop._diff_ns += now() - t
            return out

        return {"step": differentiator_step}
    if kind == "kalman":
        base_step = base.step

        def kalman_step(self: Any, *args: float) -> float:
            t = now()
            out = base_step(self, *args)
            loop._kalman_ns += now() - t
            return out

        return {"step": kalman_step}
    if kind == "control":
        base_call = base.__call__

        def control_call(self: Any, k: int, T: float, out: Any) -> None:
            base_call(self, k, T, out)
            loop._control_out = now()

        return {"__call__": control_call}
    if kind == "reference":
        base_value = base.value

        def value(self: Any, k: int) -> float:
            out = base_value(self, k)
            loop._control_out = now()
            return out

        return {"value": value}
    raise ValueError(f"unknown stage kind {kind!r}")


class StageTimer:
    """Times the interrupt's stages for one run by giving each stage object a subclass of
    its own class (``obj.__class__`` swapped) that overrides the one method the handler
    calls with a timed version (:func:`_timed_methods`).  The subclass adds no attributes
    (``__slots__ = ()``), so every other attribute and method is the object's own, at full
    speed; :meth:`restore` puts the original classes back."""

    def __init__(self, loop: RealtimeLoop) -> None:
        self.loop = loop
        self._classes: dict[tuple[type, str], type] = {}
        self.timed_types: set[type] = set()
        self._swapped: list[tuple[Any, type]] = []

    def time(self, obj: Any, kind: str) -> None:
        """Swap ``obj``'s class for its timed subclass (once)."""
        cls = type(obj)
        if cls in self.timed_types:
            return
        sub = self._classes.get((cls, kind))
        if sub is None:
            namespace = {"__slots__": (), "__module__": cls.__module__,
                         "__qualname__": cls.__qualname__,
                         **_timed_methods(kind, cls, self.loop)}  # fmt: skip
            sub = type(cls.__name__, (cls,), namespace)
            self._classes[(cls, kind)] = sub
            self.timed_types.add(sub)
        obj.__class__ = sub
        self._swapped.append((obj, cls))

    def restore(self) -> None:
        """Every object back to its own class."""
        while self._swapped:
            obj, cls = self._swapped.pop()
            if type(obj) in self.timed_types:
                obj.__class__ = cls


# ------------------------------------------------------------------ statistics
def percentiles(values: array) -> dict[str, float]:
    """p50, p99, p99.9, max (nearest rank) and mean of ``values``; NaN when empty."""
    n = len(values)
    if not n:
        return dict.fromkeys(("p50", "p99", "p99.9", "max", "mean"), math.nan)
    s = sorted(values)

    def rank(p: float) -> float:
        return s[min(n - 1, max(0, math.ceil(p * n) - 1))]

    return {"p50": rank(0.50), "p99": rank(0.99), "p99.9": rank(0.999), "max": s[-1],
            "mean": math.fsum(s) / n}  # fmt: skip


def histogram(values_us: array) -> list[dict[str, Any]]:
    """Counts per log-spaced bin (:data:`HISTOGRAM_EDGES_US`); they sum to ``len(values)``."""
    edges = HISTOGRAM_EDGES_US
    counts = [0] * (len(edges) + 1)
    for v in values_us:
        i = 0
        while i < len(edges) and v >= edges[i]:
            i += 1
        counts[i] += 1
    bins = []
    for i, n in enumerate(counts):
        lo = None if i == 0 else edges[i - 1]
        hi = None if i == len(edges) else edges[i]
        label = f"< {hi} µs" if lo is None else f">= {lo} µs" if hi is None else f"{lo}-{hi} µs"
        bins.append({"bin": label, "low_us": lo, "high_us": hi, "count": n})
    return bins


def _finite(values: array) -> array:
    return array("d", (v for v in values if not math.isnan(v)))


def per_100k(events: int, cycles: int) -> float:
    return 1e5 * events / cycles if cycles else math.nan


# ------------------------------------------------------------------ privileges
def _libc() -> Any:
    """The C library with errno kept (Linux only); None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def _os_error(what: str) -> OSError:
    code = ctypes.get_errno()
    return OSError(code, f"{what}: {os.strerror(code)}")


def set_timer_slack(ns: int) -> int:
    """``prctl(PR_SET_TIMERSLACK, ns)``; returns the previous slack (ns)."""
    libc = _libc()
    if libc is None or not hasattr(libc, "prctl"):
        raise OSError(errno.ENOSYS, "prctl not available on this platform")
    previous = libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
    if previous < 0 or libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0) != 0:
        raise _os_error("prctl(PR_SET_TIMERSLACK)")
    return int(previous)


def get_timer_slack() -> int:
    libc = _libc()
    return int(libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)) if libc is not None else -1


def lock_memory() -> None:
    """``mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)``."""
    import platform

    libc = _libc()
    if libc is None or not hasattr(libc, "mlockall"):
        raise OSError(errno.ENOSYS, "mlockall not available on this platform")
    if platform.machine().startswith(("ppc", "powerpc", "sparc", "alpha")):
        raise OSError(errno.ENOSYS, "mlockall flags of this architecture not known")
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) != 0:
        raise _os_error("mlockall")


def unlock_memory() -> None:
    libc = _libc()
    if libc is not None:
        libc.munlockall()


#: ``task->flags`` bit of kernel threads (<linux/sched.h>).
PF_KTHREAD = 0x00200000


def rt_tasks_per_cpu(proc: str = "/proc") -> dict[int, int]:
    """User-space threads of other processes under ``SCHED_FIFO`` or ``SCHED_RR``, per
    CPU: the CPU they are pinned to, else the one they last ran on (``/proc/PID/task/TID/
    stat`` fields 9 flags, 39 processor, 41 policy).  Empty where there is no procfs."""
    counts: dict[int, int] = {}
    me = str(os.getpid())
    try:
        pids = [p for p in os.listdir(proc) if p.isdigit() and p != me]
    except OSError:
        return counts
    for pid in pids:
        try:
            tids = os.listdir(os.path.join(proc, pid, "task"))
        except OSError:
            continue
        for tid in tids:
            try:
                with open(os.path.join(proc, pid, "task", tid, "stat"), encoding="ascii",
                          errors="replace") as fh:  # fmt: skip
                    stat = fh.read()
                fields = stat[stat.rindex(")") + 2 :].split()  # from field 3 (state) on
                flags, cpu, policy = int(fields[6]), int(fields[36]), int(fields[38])
            except (OSError, ValueError, IndexError):
                continue
            if flags & PF_KTHREAD or policy not in (1, 2):  # SCHED_FIFO, SCHED_RR
                continue
            with contextlib.suppress(OSError, ValueError):
                pinned = os.sched_getaffinity(int(tid))
                if len(pinned) == 1:
                    cpu = next(iter(pinned))
            counts[cpu] = counts.get(cpu, 0) + 1
    return counts


def cpu_steal_ns(cpu: int | None = None, proc: str = "/proc") -> int | None:
    """Time the hypervisor ran something else while this machine's ``cpu`` (all CPUs for
    None) wanted to run: the ``steal`` column of ``/proc/stat`` (8th value of the
    ``cpuN`` line, in USER_HZ ticks), in ns.  None where there is no such column (no
    procfs, not Linux, a kernel without steal accounting).  A guest cannot see or avoid
    these stalls; it can only count them."""
    label = "cpu" if cpu is None else f"cpu{cpu}"
    try:
        with open(os.path.join(proc, "stat"), encoding="ascii", errors="replace") as fh:
            for line in fh:
                fields = line.split()
                if fields and fields[0] == label:
                    ticks = int(fields[8])
                    return ticks * 1_000_000_000 // os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    return None


def steal_report(before: int | None, after: int | None, cpu: int | None,
                 duration_s: float) -> dict[str, Any] | None:  # fmt: skip
    """Steal time between two :func:`cpu_steal_ns` readings, as a report entry."""
    if before is None or after is None:
        return None
    ms = (after - before) * 1e-6
    cpus = 1 if cpu is not None else (os.cpu_count() or 1)
    return {
        "cpu": "all" if cpu is None else cpu,
        "ms": ms,
        "share": ms * 1e-3 / (duration_s * cpus) if duration_s > 0 else math.nan,
    }


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc)


# ------------------------------------------------------------------ the loop
class RealtimeLoop:
    """Paces the cycles, instruments the controller, collects the statistics."""

    def __init__(self, sample_period_s: float, config: RealtimeConfig | None = None, *,
                 sync_id: int | None = None, sensor_id: int | None = None,
                 command_id: int | None = None) -> None:  # fmt: skip
        self.config = config = config or RealtimeConfig()
        config.check(sample_period_s)
        self.period_ns = round(sample_period_s * 1e9)
        # Default identifiers from control.dbc (SYNC, the drive's sensor TPDO, its RPDO).
        self.sync_id = frame_id("control", "SYNC") if sync_id is None else sync_id
        self.sensor_id = frame_id("control", "DRIVE_TPDO1") if sensor_id is None else sensor_id
        self.command_id = frame_id("control", "DRIVE_RPDO1") if command_id is None else command_id
        share, source = rt_share_limit()
        self.plan = SpinPlan(
            self.period_ns,
            share,
            None if config.spin_us is None else round(config.spin_us * 1e3),
        )
        self.rt_limit_source = source
        self._spin_ns = self.plan.spin_ns(0.0)
        self.spin_range_ns = [self._spin_ns, self._spin_ns]  # during recording
        self.t0_ns = 0
        self.recording = False
        self.jitter_us = array("d")
        self.latency_us = array("d")
        self.isr_us = array("d")
        self.work_us = array("d")
        self.overshoot_us = array("d")  # NaN: no sleep that cycle
        self.stage_us = {key: array("d") for key, _ in STAGES}
        self.misses = 0
        self.cycles = 0
        self.late_starts = 0
        self.late_wakeups = 0
        self.busy_ns = 0
        self.floor: dict[str, Any] | None = None
        #: The CPU the loop is pinned to (None: not pinned), for its steal time.
        self.cpu: int | None = None
        self.steal: dict[str, Any] | None = None
        self._steal0: int | None = None
        self._recording_t0_ns = 0
        self.applied: list[str] = []
        self.refused: list[str] = []
        self._deadline = 0
        self._wake_ns = 0
        self._started_late = False
        self._overshoot_ns = -1
        self._sync_ns = 0
        self._sensor_ns = 0
        self._command_ns = 0
        self._window_cycles = max(1, round(RESIZE_EVERY_S * 1e9 / self.period_ns))
        self._window_n = 0
        self._window_work_ns = 0
        # time stamps the stage proxies leave for the current interrupt
        self._chain_in = self._chain_out = self._control_out = 0
        self._plaus_ns = self._diff_ns = self._kalman_ns = 0
        # the current cycle's interrupt, kept by _isr_done until end_cycle records it
        self._stage_ns = [0] * len(STAGES)
        self._stage_arrays = [self.stage_us[key] for key, _ in STAGES]
        self._isr_ns = 0
        self._isr_ran = False
        self._end_ns = 0
        self._stages = StageTimer(self)
        self._timed_types = self._stages.timed_types
        self._restore: list[Callable[[], None]] = []

    # ------------------------------------------------------------ instrumentation

    def instrument(self, controller: Any) -> None:
        """Wrap the controller's bus send, its frame handler, its interrupt and the
        interrupt's stage objects (for this run only; :meth:`exit` unwraps them)."""
        bus: can.BusABC = controller.bus
        send, on_message = bus.send, controller.on_message
        own_send, own_on_message = vars(bus).get("send"), vars(controller).get("on_message")
        sync_id, sensor_id, command_id = self.sync_id, self.sensor_id, self.command_id

        def timed_send(msg: can.Message, timeout: float | None = None) -> None:
            t = _now_ns()
            ident = msg.arbitration_id
            if ident == command_id:
                self._command_ns = t
            elif ident == sync_id:
                self._sync_ns = t
            send(msg, timeout)

        def timed_on_message(msg: can.Message) -> None:
            if msg.arbitration_id == sensor_id:
                self._sensor_ns = _now_ns()  # received: handed to the controller
            on_message(msg)

        bus.send = timed_send  # type: ignore[method-assign]
        controller.on_message = timed_on_message
        self._stages.time(controller.isr, "isr")

        def uninstrument() -> None:
            if own_send is not None:  # the bus's own instance attribute, as it was
                bus.send = own_send  # type: ignore[method-assign]
            else:
                with contextlib.suppress(AttributeError):
                    delattr(bus, "send")
            if own_on_message is not None:
                controller.on_message = own_on_message
            else:
                with contextlib.suppress(AttributeError):
                    delattr(controller, "on_message")
            self._stages.restore()

        self._restore.append(uninstrument)

    def _time_stages_of(self, isr: Any) -> None:
        """Give the handler's stage objects their timed classes: at the first interrupt,
        and again for an object the controller swapped in (new parameters over SDO)."""
        timed = self._timed_types
        chain = isr.chain
        if (
            type(chain) not in timed
            or type(chain.plausibility) not in timed
            or type(chain.differentiator) not in timed
            or type(chain.kalman) not in timed
            or type(isr.reference) not in timed
            or (isr.control is not None and type(isr.control) not in timed)
        ):
            stages = self._stages
            stages.time(chain, "chain")
            for name in ("plausibility", "differentiator", "kalman"):
                stages.time(getattr(chain, name), name)
            if isr.control is not None:
                stages.time(isr.control, "control")
            stages.time(isr.reference, "reference")

    def _isr_done(self, t0: int, t4: int) -> None:
        """Keep the interrupt's time and its stages (contiguous: they sum to it) for
        :meth:`end_cycle`."""
        chain_in = self._chain_in or t0
        chain_out = self._chain_out or chain_in
        control_out = self._control_out or chain_out
        plaus, diff, kalman = self._plaus_ns, self._diff_ns, self._kalman_ns
        ns = self._stage_ns  # in STAGES order
        ns[0] = chain_in - t0
        ns[1] = plaus
        ns[2] = diff
        ns[3] = kalman
        ns[4] = chain_out - chain_in - plaus - diff - kalman
        ns[5] = control_out - chain_out
        ns[6] = t4 - control_out
        self._isr_ns = t4 - t0
        self._isr_ran = True

    # ------------------------------------------------------------ determinism

    def enter(self) -> None:
        """Apply what improves determinism and is permitted; note what was refused."""
        cfg = self.config
        if cfg.affinity:
            self._apply_affinity()
        if cfg.timer_slack:  # before SCHED_FIFO: Linux ignores the call for RT tasks
            self._apply_timer_slack()
        if cfg.fifo:
            self._apply_fifo()
        if cfg.mlock:
            self._apply_mlock()
        if cfg.gc_off:
            gc.collect()
            if gc.isenabled():
                gc.disable()
                self._restore.append(gc.enable)
            self.applied.append("gc disabled during the loop (collected before)")

    def _apply_affinity(self) -> None:
        if not hasattr(os, "sched_setaffinity"):
            self.refused.append("affinity: not supported on this platform")
            return
        try:
            before = os.sched_getaffinity(0)
            busy = rt_tasks_per_cpu()
            cpu = min(before, key=lambda c: (busy.get(c, 0), -c))
            os.sched_setaffinity(0, {cpu})
        except OSError as exc:
            self.refused.append(f"affinity: {_why(exc)}")
            return
        self.cpu = cpu
        others = ", ".join(f"{n} on CPU {c}" for c, n in sorted(busy.items()) if c in before)
        note = f" (other real-time tasks: {others})" if others else ""
        self.applied.append(f"affinity: CPU {cpu}{note}")
        self._restore.append(lambda: os.sched_setaffinity(0, before))

    def _apply_timer_slack(self) -> None:
        try:
            previous = set_timer_slack(TIMER_SLACK_NS)
        except OSError as exc:
            self.refused.append(f"timer slack: {_why(exc)}")
            return
        self.applied.append(f"timer slack {TIMER_SLACK_NS} ns (was {previous} ns)")
        self._restore.append(lambda: set_timer_slack(previous))

    def _apply_fifo(self) -> None:
        if not hasattr(os, "sched_setscheduler"):
            self.refused.append("SCHED_FIFO: not supported on this platform")
            return
        try:
            policy = os.sched_getscheduler(0)
            param = os.sched_getparam(0)
            fifo = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
            os.sched_setscheduler(0, fifo, os.sched_param(FIFO_PRIORITY))
        except OSError as exc:
            self.refused.append(f"SCHED_FIFO: {_why(exc)} (needs root/CAP_SYS_NICE)")
            return
        what = f"SCHED_FIFO priority {FIFO_PRIORITY}"
        if fifo != os.SCHED_FIFO:
            what += ", reset on fork"
        if self.config.timer_slack and get_timer_slack() == 0:
            what += " (timer slack 0 for RT tasks)"
        self.applied.append(what)
        self._restore.append(lambda: os.sched_setscheduler(0, policy, param))

    def _apply_mlock(self) -> None:
        try:
            lock_memory()
        except OSError as exc:
            self.refused.append(
                f"mlockall: {_why(exc)} (needs root/CAP_IPC_LOCK or RLIMIT_MEMLOCK)"
            )
            return
        self.applied.append("mlockall (current and future pages, as touched)")
        self._restore.append(unlock_memory)

    def exit(self) -> None:
        """Undo :meth:`enter` and :meth:`instrument` (in reverse order)."""
        while self._restore:
            with contextlib.suppress(OSError):  # best effort
                self._restore.pop()()

    # ------------------------------------------------------------ pacing

    def start(self, t0_ns: int | None = None) -> int:
        """Cycle 0 is due now (or at ``t0_ns``)."""
        self.t0_ns = _now_ns() if t0_ns is None else t0_ns
        return self.t0_ns

    def wait(self, k: int) -> None:
        """Sleep until the spin window, then spin, until cycle ``k``'s deadline."""
        deadline = self.t0_ns + k * self.period_ns
        self._deadline = deadline
        self._sync_ns = self._sensor_ns = self._command_ns = 0
        self._isr_ran = False
        wake, self._overshoot_ns = sleep_then_spin(deadline, self._spin_ns)
        self._wake_ns = wake
        self._started_late = self._overshoot_ns < 0 and wake >= deadline

    def cycle_end_s(self) -> float:
        """The next cycle's deadline in seconds on :func:`time.perf_counter`."""
        return (self._deadline + self.period_ns) * 1e-9

    def end_cycle(self) -> None:
        """After the cycle's frames are handled: account its work, re-size the spin window
        every second, record the cycle (while recording)."""
        t = self._end_ns = _now_ns()
        deadline = self._deadline
        wake = self._wake_ns
        self._window_work_ns += t - (wake if wake > deadline else deadline)
        self._window_n += 1
        if self._window_n >= self._window_cycles:
            self._resize_spin()
        if self.recording:
            self._record()

    def _record(self) -> None:
        """Append the cycle that just ended to the statistics."""
        t = self._end_ns
        deadline = self._deadline
        wake = self._wake_ns
        work = t - (wake if wake > deadline else deadline)
        self.cycles += 1
        self.busy_ns += t - wake
        self.work_us.append(work * 1e-3)
        over = self._overshoot_ns
        self.overshoot_us.append(over * 1e-3 if over >= 0 else math.nan)
        if over > self._spin_ns:
            self.late_wakeups += 1
        if self._started_late:
            self.late_starts += 1
        sync = self._sync_ns
        self.jitter_us.append((sync - deadline) * 1e-3 if sync else math.nan)
        command = self._command_ns
        if command and self._sensor_ns:
            self.latency_us.append((command - self._sensor_ns) * 1e-3)
        if not command or command >= deadline + self.period_ns:
            self.misses += 1
        if self._isr_ran:
            for a, ns in zip(self._stage_arrays, self._stage_ns, strict=True):
                a.append(ns * 1e-3)
            self.isr_us.append(self._isr_ns * 1e-3)

    def _resize_spin(self) -> None:
        mean_work = self._window_work_ns / self._window_n
        self._window_n = self._window_work_ns = 0
        self._spin_ns = spin = self.plan.spin_ns(mean_work)
        if self.recording:
            r = self.spin_range_ns
            r[0], r[1] = min(r[0], spin), max(r[1], spin)

    def begin_recording(self) -> None:
        """Statistics from the next cycle on (the run's operation phase), and from the
        cycle that just ended if the interrupt already ran in it: the controller turns
        operational on the drive's statusword, and in real time the cycle's sensor frame
        may come after it (module docstring)."""
        self.recording = True
        self.spin_range_ns = [self._spin_ns, self._spin_ns]
        self._steal0 = cpu_steal_ns(self.cpu)
        self._recording_t0_ns = _now_ns()
        if self._isr_ran:
            self._record()

    def end_recording(self) -> None:
        """Statistics end here (the run's operation phase is over): the steal time on the
        loop's CPU over the recorded cycles."""
        if not self.recording:
            return
        self.recording = False
        elapsed_s = (_now_ns() - self._recording_t0_ns) * 1e-9
        self.steal = steal_report(self._steal0, cpu_steal_ns(self.cpu), self.cpu, elapsed_s)

    # ------------------------------------------------------------ machine floor

    def measure_floor(self, duration_s: float | None = None) -> dict[str, Any] | None:
        """The bare loop: same spin window and process state, the run's median cycle
        work as busy-waiting, no hdhil code (module docstring).  Call it after the run,
        before :meth:`exit`."""
        duration = self.config.floor_s if duration_s is None else duration_s
        if not duration > 0:
            return None
        self.floor = measure_floor(
            self.period_ns,
            self._spin_ns,
            round(percentiles(self.work_us)["p50"] * 1e3) if self.work_us else 0,
            duration,
            self.cpu,
        )
        return self.floor

    # ------------------------------------------------------------ report

    def result(self) -> dict[str, Any]:
        jitter = _finite(self.jitter_us)
        overshoot = _finite(self.overshoot_us)  # the cycles that slept
        stages = {}
        for key, label in STAGES:
            stages[key] = {"label": label, **percentiles(self.stage_us[key])}
        period_ns = self.period_ns
        share = self.busy_ns / (self.cycles * period_ns) if self.cycles else math.nan
        fixed = self.plan.fixed_ns is not None
        return {
            "cycles": self.cycles,
            "sample_period_s": period_ns * 1e-9,
            "deadline_misses": self.misses,
            "misses_per_100k": per_100k(self.misses, self.cycles),
            "jitter_us": percentiles(jitter),
            "latency_us": percentiles(self.latency_us),
            "interrupts": len(self.isr_us),
            "isr_us": percentiles(self.isr_us),
            "stages_us": stages,
            "cycle_work_us": percentiles(self.work_us),
            "sleep_overshoot_us": percentiles(overshoot),
            "sleeps": len(overshoot),
            "jitter_histogram": histogram(jitter),
            "syncs_missing": self.cycles - len(jitter),
            "late_starts": self.late_starts,
            "late_wakeups": self.late_wakeups,
            "pacing": {
                "spin_us": self._spin_ns * 1e-3,
                "spin_us_range": [v * 1e-3 for v in self.spin_range_ns],
                "spin_source": "fixed (--spin-us)"
                if fixed
                else f"{SPIN_FRACTION:.0%} of the period, within the RT budget",
                "rt_share_limit": self.plan.share_limit,
                "rt_share_limit_source": self.rt_limit_source,
                "rt_share_budget": self.plan.share_limit - RT_SHARE_MARGIN,
                "cpu_share": share,
            },
            "applied": list(self.applied),
            "refused": list(self.refused),
            "steal": self.steal,
            "floor": self.floor,
        }


def sleep_then_spin(deadline_ns: int, spin_ns: int) -> tuple[int, int]:
    """Sleep until ``spin_ns`` before the deadline, then spin to it (the pacing of both
    the run and the machine floor).  Returns when the loop woke (or started, if there
    was no time to sleep) and how late the sleep woke, -1 if it did not sleep."""
    target = deadline_ns - spin_ns
    t = _now_ns()
    if target > t:
        _sleep((target - t) * 1e-9)
        wake = _now_ns()
        over = wake - target
    else:
        wake, over = t, -1
    while _now_ns() < deadline_ns:
        pass
    return wake, over


def measure_floor(period_ns: int, spin_ns: int, work_ns: int, duration_s: float,
                  cpu: int | None = None) -> dict[str, Any]:  # fmt: skip
    """Sleep-then-spin pacing with ``work_ns`` of busy-waiting per cycle and nothing else,
    for ``duration_s`` (the caller sets up affinity, priority, collector).  Jitter is the
    lateness of the loop's start of work; a miss is work that ends after the next
    deadline.  ``steal``: the hypervisor's steal time on ``cpu`` (the loop's; None: all
    CPUs) meanwhile."""
    n = max(1, round(duration_s * 1e9 / period_ns))
    jitter_us = array("d")
    overshoot_us = array("d")
    misses = late_wakeups = 0
    now = _now_ns
    steal0 = cpu_steal_ns(cpu)
    t0 = now() + period_ns
    for k in range(n):
        deadline = t0 + k * period_ns
        _, over = sleep_then_spin(deadline, spin_ns)
        if over >= 0:
            overshoot_us.append(over * 1e-3)
            if over > spin_ns:
                late_wakeups += 1
        start = now()
        jitter_us.append((start - deadline) * 1e-3)
        end = start + work_ns
        while now() < end:
            pass
        if now() >= deadline + period_ns:
            misses += 1
    return {
        "duration_s": n * period_ns * 1e-9,
        "cycles": n,
        "spin_us": spin_ns * 1e-3,
        "work_us": work_ns * 1e-3,
        "jitter_us": percentiles(jitter_us),
        "sleep_overshoot_us": percentiles(overshoot_us),
        "jitter_histogram": histogram(jitter_us),
        "deadline_misses": misses,
        "misses_per_100k": per_100k(misses, n),
        "late_wakeups": late_wakeups,
        "steal": steal_report(steal0, cpu_steal_ns(cpu), cpu, n * period_ns * 1e-9),
    }


# ------------------------------------------------------------------ text
def _row(label: str, p: dict[str, float]) -> str:
    return f"    {label:<30} {p['p50']:9.1f} {p['p99']:9.1f} {p['p99.9']:9.1f} {p['max']:9.1f}"


def _histogram_lines(bins: list[dict[str, Any]]) -> list[str]:
    top = max((b["count"] for b in bins), default=0) or 1
    return [
        f"      {b['bin']:>14} {b['count']:>8}  {'#' * max(1, round(40 * b['count'] / top))}"
        for b in bins
        if b["count"]
    ]


def format_steal(steal: dict[str, Any]) -> str:
    """One phrase: the hypervisor's steal time (:func:`steal_report`)."""
    where = "all CPUs" if steal["cpu"] == "all" else f"the loop's CPU {steal['cpu']}"
    return (
        f"hypervisor steal time on {where}: {steal['ms']:.0f} ms "
        f"({steal['share']:.2%} of the time; stalls the machine cannot avoid)"
    )


def format_realtime(rt: dict[str, Any]) -> str:
    """The statistics as text: percentile tables, the jitter histogram, the floor."""
    pace = rt["pacing"]
    lo, hi = pace["spin_us_range"]
    spin = f"{pace['spin_us']:.0f} µs" if lo == hi else f"{lo:.0f}-{hi:.0f} µs"
    lines = [
        f"  real time          {rt['cycles']} cycles paced at "
        f"{rt['sample_period_s'] * 1e3:g} ms; deadline misses {rt['deadline_misses']} "
        f"({rt['misses_per_100k']:.1f} per 100 000)",
        f"    pacing: spin window {spin} ({pace['spin_source']}); loop CPU share "
        f"{pace['cpu_share']:.0%}, RT throttling limit {pace['rt_share_limit']:.0%}",
    ]
    if pace["cpu_share"] > pace["rt_share_limit"]:
        lines.append("    WARNING: the loop's CPU share is above the RT throttling limit: "
                     "the kernel parks it for the rest of each throttling period")  # fmt: skip
    lines.append(
        f"    sleep woke later than the spin window in {rt['late_wakeups']} cycles; "
        f"{rt['late_starts']} cycles started late (the previous one overran)"
    )
    if rt.get("steal"):
        lines.append(f"    {format_steal(rt['steal'])}")
    lines.append(f"    applied: {'; '.join(rt['applied']) or 'nothing'}")
    if rt["refused"]:
        lines.append(f"    refused: {'; '.join(rt['refused'])}")
    lines.append(f"    {'µs':<30} {'p50':>9} {'p99':>9} {'p99.9':>9} {'max':>9}")
    for key, label in (("jitter_us", "SYNC jitter (late)"),
                       ("latency_us", "sensor frame -> command"),
                       ("cycle_work_us", "cycle work (frames, nodes)"),
                       ("sleep_overshoot_us", "sleep overshoot"),
                       ("isr_us", "interrupt compute")):  # fmt: skip
        lines.append(_row(label, rt[key]))
    for stage in rt["stages_us"].values():
        lines.append(_row(f"  {stage['label']}", stage))
    lines.append("    SYNC jitter histogram:")
    lines += _histogram_lines(rt["jitter_histogram"])
    floor = rt.get("floor")
    if floor:
        lines += [
            f"  machine floor      bare sleep+spin loop, {floor['cycles']} cycles, same spin "
            f"window and process state, {floor['work_us']:.0f} µs busy work per cycle, no "
            f"hdhil code: misses {floor['deadline_misses']} "
            f"({floor['misses_per_100k']:.1f} per 100 000), late wake-ups "
            f"{floor['late_wakeups']}"
            + (f"; {format_steal(floor['steal'])}" if floor.get("steal") else ""),
            _row("start jitter (late)", floor["jitter_us"]),
            _row("sleep overshoot", floor["sleep_overshoot_us"]),
        ]
    return "\n".join(lines)
