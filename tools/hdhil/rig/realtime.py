"""``hdhil run --realtime``: the lockstep run paced by the wall clock at the sample period.

Cycle k's SYNC is due at ``t0 + k·Ts`` on the monotonic clock (:func:`time.perf_counter_ns`):
:class:`RealtimeLoop` sleeps until a spin window before the deadline, then busy-waits to
it.  The schedule is absolute: a cycle that overruns is not skipped, the next SYNC goes
out at once and the following ones catch up, as a hardware timer keeps its phase.  The
loop also applies what makes the process more deterministic (:mod:`hdhil.rig.ostuning`),
gives the controller its probe (:class:`hdhil.rig.realtime_stats.CycleStamps`), records
the cycles of the operation phase (:class:`hdhil.rig.realtime_stats.CycleStats`) and can
measure the machine's own floor after the run.

Clock: the simulated bus's clock (:class:`WallClock`) reads wall time since the run
started, so every frame is requested at the moment it was really sent and trace
timestamps are real (the wire time of each frame is still modelled by ``simbus``).  The
drive stays locked to SYNC: it integrates the plant one period per SYNC, whatever the
wall time between two SYNCs was.  On ``--interface virtual`` (and any real python-can
interface) pacing and statistics are the same, on the monotonic clock.
"""

from __future__ import annotations

import contextlib
import math
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hdhil.can.simbus import SimClock
from hdhil.core.dataconf import ConfigError
from hdhil.rig.ostuning import ProcessTuning, cpu_steal_ns, rt_share_limit, steal_report
from hdhil.rig.realtime_stats import CycleStamps, CycleStats, histogram, per_100k, percentiles

__all__ = [
    "RESIZE_EVERY_S",
    "RT_SHARE_MARGIN",
    "SPIN_FRACTION",
    "RealtimeConfig",
    "RealtimeLoop",
    "SpinPlan",
    "WallClock",
    "measure_floor",
    "sleep_then_spin",
]

#: Spin window by default, as a fraction of the sample period (600 µs at 1 kHz).
SPIN_FRACTION = 0.6

#: The loop's CPU share (spin + work per period) stays this far below the kernel's RT
#: throttling limit.
RT_SHARE_MARGIN = 0.15


#: The spin window is re-sized after every this many seconds of cycles.
RESIZE_EVERY_S = 1.0

_now_ns = time.perf_counter_ns
_sleep = time.sleep


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


@dataclass
class SpinPlan:
    """The spin window: :data:`SPIN_FRACTION` of the period, capped so that spin + mean
    cycle work stays below the RT throttling limit minus :data:`RT_SHARE_MARGIN`; or a
    fixed window (``--spin-us``).

    The window absorbs late wake-ups of ``time.sleep``: a wake-up later than the window
    makes SYNC late.  Under ``SCHED_FIFO`` a loop above the kernel's real-time throttling
    limit (``/proc/sys/kernel/sched_rt_runtime_us`` / ``sched_rt_period_us``, 95 % by
    default) is parked for the rest of the throttling period (50 ms every second at
    95 %), hence the cap.  The loop re-sizes the window every :data:`RESIZE_EVERY_S` from
    the mean work of the last second.
    """

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
        #: The end of the current cycle on this clock, set by the node loop: a delayed
        #: frame due later waits for its cycle, as in lockstep.
        self.horizon = math.inf

    @property  # type: ignore[override]
    def now(self) -> float:  # type: ignore[override]
        return (_now_ns() - self.t0_ns) * 1e-9

    def restart(self, t0_ns: int) -> None:
        self.t0_ns = t0_ns


# ------------------------------------------------------------------ the loop
class RealtimeLoop:
    """Paces the cycles, instruments the controller, collects the statistics.

    Statistics (:class:`hdhil.rig.realtime_stats.CycleStats`, ``stats``) cover the
    operation cycles only.  Start-up and stop cycles are not counted, except the last
    start-up cycle when the first interrupt already ran in it: the controller turns
    operational on the drive's statusword, and in real time the cycle's sensor frame may
    arrive after it (frames are requested at wall time, so their order on the wire is
    that of the moments they were sent).  So the statistics cover exactly the cycles in
    which the interrupt ran.
    """

    def __init__(self, sample_period_s: float, config: RealtimeConfig | None = None) -> None:
        self.config = config = config or RealtimeConfig()
        config.check(sample_period_s)
        self.period_ns = round(sample_period_s * 1e9)
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
        #: The probe the controller time-stamps its cycle's events with.
        self.stamps = CycleStamps()
        #: The recorded cycles' statistics.
        self.stats = CycleStats(self.period_ns)
        self.floor: dict[str, Any] | None = None
        #: The CPU the loop is pinned to (None: not pinned), for its steal time.
        self.cpu: int | None = None
        self.steal: dict[str, Any] | None = None
        self._steal0: int | None = None
        self._recording_t0_ns = 0
        self._tuning = ProcessTuning(
            affinity=config.affinity,
            timer_slack=config.timer_slack,
            fifo=config.fifo,
            mlock=config.mlock,
            gc_off=config.gc_off,
        )
        self._deadline = 0
        self._wake_ns = 0
        self._started_late = False
        self._overshoot_ns = -1
        self._window_cycles = max(1, round(RESIZE_EVERY_S * 1e9 / self.period_ns))
        self._window_n = 0
        self._window_work_ns = 0
        self._end_ns = 0
        self._restore: list[Callable[[], None]] = []

    # ------------------------------------------------------------ instrumentation

    def instrument(self, controller: Any) -> None:
        """Give the controller the probe (``controller.probe``,
        :class:`hdhil.firmware.controller.CycleProbe`) and the firmware's interrupt
        handler its stage hook, for this run only (:meth:`exit` takes both back)."""
        stamps = self.stamps
        previous = getattr(controller, "probe", None)
        controller.probe = stamps
        isr = controller.isr
        staged = stamps.staged = hasattr(isr, "stage_hook")
        if staged:
            isr.stage_hook = stamps.stage_hook()

        def uninstrument() -> None:
            controller.probe = previous
            if staged:
                isr.stage_hook = None

        self._restore.append(uninstrument)

    # ------------------------------------------------------------ determinism

    def enter(self) -> None:
        """Apply what improves determinism and is permitted
        (:class:`hdhil.rig.ostuning.ProcessTuning`: collector off, affinity, timer slack,
        ``SCHED_FIFO``, optionally ``mlockall``); what was applied and refused goes into
        the report.  The misses left are stalls in which the loop does not run at all; the
        machine floor shows them too."""
        tuning = self._tuning
        tuning.enter()
        self.cpu = tuning.cpu
        self._restore.append(tuning.exit)

    @property
    def applied(self) -> list[str]:
        return self._tuning.applied

    @property
    def refused(self) -> list[str]:
        return self._tuning.refused

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
        self.stamps.clear()
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
        self.stats.record(self._deadline, self._wake_ns, self._end_ns, self._overshoot_ns,
                          self._spin_ns, self._started_late, self.stamps)  # fmt: skip

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
        may come after it (class docstring)."""
        self.recording = True
        self.spin_range_ns = [self._spin_ns, self._spin_ns]
        self._steal0 = cpu_steal_ns(self.cpu)
        self._recording_t0_ns = _now_ns()
        if self.stamps.isr_ran:
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
        """The bare loop (:func:`measure_floor`) with the run's spin window and median
        cycle work, in the same process state.  Call it after the run, before
        :meth:`exit`."""
        duration = self.config.floor_s if duration_s is None else duration_s
        if not duration > 0:
            return None
        work = self.stats.work_us
        self.floor = measure_floor(
            self.period_ns,
            self._spin_ns,
            round(percentiles(work)["p50"] * 1e3) if work else 0,
            duration,
            self.cpu,
        )
        return self.floor

    # ------------------------------------------------------------ report

    def result(self) -> dict[str, Any]:
        """The statistics, the pacing and the process settings, as the run reports them."""
        fixed = self.plan.fixed_ns is not None
        return {
            **self.stats.summary(),
            "pacing": {
                "spin_us": self._spin_ns * 1e-3,
                "spin_us_range": [v * 1e-3 for v in self.spin_range_ns],
                "spin_source": "fixed (--spin-us)"
                if fixed
                else f"{SPIN_FRACTION:.0%} of the period, within the RT budget",
                "rt_share_limit": self.plan.share_limit,
                "rt_share_limit_source": self.rt_limit_source,
                "rt_share_budget": self.plan.share_limit - RT_SHARE_MARGIN,
                "cpu_share": self.stats.cpu_share,
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
    """The machine floor (``--floor-s``): sleep-then-spin pacing with ``work_ns`` of
    busy-waiting per cycle and no hdhil code, for ``duration_s`` (the caller sets up
    affinity, priority, collector).  The jitter and misses it shows are the machine's
    (scheduler, timer, hypervisor), and bound what the run can reach.  Jitter is the
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
