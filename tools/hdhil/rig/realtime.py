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
- **stages** of the interrupt (:data:`firmware.isr.STAGES`), contiguous, so that they
  add up to the interrupt's time in every cycle;
- **cycle work**: from the deadline (or the wake-up, if later) to the end of the cycle's
  frame handling: what the loop computes per period besides spinning;
- **sleep overshoot**: how late ``time.sleep`` returned (the machine's share of the tail);
- **misses**: cycles whose command was not handed to the bus before the next SYNC's
  deadline (or never).

Instrumentation, for the run only: the controller bus's ``send`` and the controller's
frame handler ``on_message`` are wrapped (instance attributes, removed at the end), and
the firmware's interrupt handler gets a stage hook (:data:`firmware.interrupt.StageHook`,
``InterruptHandler.stage_hook``): the handler calls it at every stage boundary, the hook
takes a ``perf_counter_ns`` time stamp.  The handler's code and classes stay as they are;
a stage object the controller swaps in at run time (new parameters over SDO) is timed
like the one before, since the handler, not the stage, calls the hook.  The time stamps'
own cost is counted in the interrupt's compute time (README, figures).  An interrupt
handler of the user's own without ``stage_hook`` is timed as a whole only.

Machine floor
-------------
:meth:`RealtimeLoop.measure_floor` (``--floor-s``) runs the bare loop after the run, in the
same process state (same spin window, affinity, priority, no collector) and with the
run's median cycle work as busy-waiting, but no hdhil code: the jitter and misses it
shows are the machine's (scheduler, timer, hypervisor), and bound what the run can reach.

Determinism
-----------
The process settings (collector off, affinity, timer slack, ``SCHED_FIFO``, optionally
``mlockall``) are applied where permitted by :class:`hdhil.rig.ostuning.ProcessTuning`,
reported as ``applied`` / ``refused``, and undone when the loop ends.  The misses left
are stalls in which the loop does not run at all; the machine floor shows them too.
What each setting changed on a measured machine is in the README's figures section.

Other interfaces
----------------
``--interface virtual`` (and any real python-can interface) works too: pacing and
statistics are the same, only the clock is the monotonic clock the non-simulated path
already uses.
"""

from __future__ import annotations

import contextlib
import math
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can

from hdhil.can.simbus import SimClock
from hdhil.core.dataconf import ConfigError
from hdhil.dbc import frame_id
from hdhil.firmware.isr import STAGES
from hdhil.rig.ostuning import ProcessTuning, cpu_steal_ns, rt_share_limit, steal_report

#: Spin window by default, as a fraction of the sample period (600 µs at 1 kHz).
SPIN_FRACTION = 0.6

#: The loop's CPU share (spin + work per period) stays this far below the kernel's RT
#: throttling limit.
RT_SHARE_MARGIN = 0.15


#: The spin window is re-sized after every this many seconds of cycles.
RESIZE_EVERY_S = 1.0


#: Jitter histogram bin edges in µs (1-2-5 log spacing); below the first edge (early or
#: under 1 µs late) is the first bin, from the last edge on the last.
HISTOGRAM_EDGES_US = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000)

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
        #: The end of the current cycle on this clock, set by the node loop: a delayed
        #: frame due later waits for its cycle, as in lockstep.
        self.horizon = math.inf

    @property  # type: ignore[override]
    def now(self) -> float:  # type: ignore[override]
        return (_now_ns() - self.t0_ns) * 1e-9

    def restart(self, t0_ns: int) -> None:
        self.t0_ns = t0_ns


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
        self._sync_ns = 0
        self._sensor_ns = 0
        self._command_ns = 0
        self._window_cycles = max(1, round(RESIZE_EVERY_S * 1e9 / self.period_ns))
        self._window_n = 0
        self._window_work_ns = 0
        # the current cycle's interrupt, kept by _isr_done until end_cycle records it
        self._stage_ns = [0] * len(STAGES)
        self._stage_arrays = [self.stage_us[key] for key, _ in STAGES]
        self._isr_ns = 0
        self._isr_ran = False
        self._staged = False  # the handler reports its stages (stage hook)
        self._end_ns = 0
        self._restore: list[Callable[[], None]] = []

    # ------------------------------------------------------------ instrumentation

    def instrument(self, controller: Any) -> None:
        """Wrap the controller's bus send and its frame handler, and set the interrupt
        handler's stage hook (for this run only; :meth:`exit` undoes all three)."""
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
        isr = controller.isr
        timed_handler = self._staged = hasattr(isr, "stage_hook")
        if timed_handler:
            isr.stage_hook = self._stage_hook()
        else:  # a handler of the user's own: timed as a whole
            controller.isr = self._timed_whole(isr)

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
            if timed_handler:
                isr.stage_hook = None
            else:
                controller.isr = isr

        self._restore.append(uninstrument)

    def _stage_hook(self) -> Callable[[int], None]:
        """The stage hook: a time stamp per stage boundary; at the last, the interrupt's
        stage times (successive differences, so they add up to the whole) are kept for
        :meth:`end_cycle`."""
        stamps = [0] * (len(STAGES) + 1)
        last = len(STAGES)
        now = _now_ns
        ns = self._stage_ns

        def stamp(i: int) -> None:
            t = stamps[i] = now()
            if i == last:
                for j in range(last):
                    ns[j] = stamps[j + 1] - stamps[j]
                self._isr_ns = t - stamps[0]
                self._isr_ran = True

        return stamp

    def _timed_whole(self, isr: Any) -> Any:
        """A handler without stage hook, timed around its call (no stage breakdown)."""
        loop = self

        class Timed:
            def __getattr__(self, name: str) -> Any:
                return getattr(isr, name)

            def __call__(self, sample: Any) -> Any:
                t0 = _now_ns()
                out = isr(sample)
                loop._isr_ns = _now_ns() - t0
                loop._isr_ran = True
                return out

        return Timed()

    # ------------------------------------------------------------ determinism

    def enter(self) -> None:
        """Apply what improves determinism and is permitted (:class:`hdhil.rig.ostuning.
        ProcessTuning`); what was applied and refused goes into the report."""
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
            if self._staged:
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
