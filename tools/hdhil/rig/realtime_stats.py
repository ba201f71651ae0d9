"""``hdhil run --realtime``'s measurements: what a paced cycle's events cost, and the report.

:class:`CycleStamps` is the probe the pacer gives the controller
(:class:`hdhil.firmware.controller.CycleProbe`, plus the interrupt handler's stage hook):
time stamps of one cycle's events.  :class:`CycleStats` turns each recorded cycle into
the statistics (arrays of ``array('d')``, percentiles, histogram), and
:func:`format_realtime` into text.  Kept apart from the pacing
(:mod:`hdhil.rig.realtime`), which decides when a cycle starts and which cycles count.
"""

from __future__ import annotations

import math
import time
from array import array
from collections.abc import Callable, Iterable
from typing import Any

from hdhil.firmware.isr import STAGES

__all__ = [
    "HISTOGRAM_EDGES_US",
    "PERCENTILE_KEYS",
    "STAGES",
    "CycleStamps",
    "CycleStats",
    "format_realtime",
    "format_steal",
    "histogram",
    "per_100k",
    "percentiles",
]

#: Jitter histogram bin edges in µs (1-2-5 log spacing); below the first edge (early or
#: under 1 µs late) is the first bin, from the last edge on the last.
HISTOGRAM_EDGES_US = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000)

_now_ns = time.perf_counter_ns


# ------------------------------------------------------------------ the probe
class CycleStamps:
    """The time stamps of one cycle: the controller's probe
    (:class:`hdhil.firmware.controller.CycleProbe`) and the interrupt's stage hook.

    The controller calls the probe as the events happen: SYNC handed to the bus, sensor
    frame handed to its handler, interrupt run, command handed to the bus.  The firmware's
    interrupt handler also gets :meth:`stage_hook` (:data:`firmware.interrupt.StageHook`,
    ``InterruptHandler.stage_hook``) when it has one: it calls the hook at every stage
    boundary, the hook takes a ``perf_counter_ns`` time stamp, so the stages add up to the
    interrupt's time; a stage object the controller swaps in at run time (new parameters
    over SDO) is timed like the one before, since the handler, not the stage, calls the
    hook.  The time stamps' own cost is counted in the interrupt's compute time.  A
    handler of the user's own without ``stage_hook`` is timed as a whole, by the probe's
    ``on_interrupt``.
    """

    __slots__ = ("answer_ns", "command_ns", "isr_ns", "isr_ran", "sensor_ns", "stage_ns",
                 "staged", "sync_ns", "unanswered_ns")  # fmt: skip

    def __init__(self) -> None:
        self.sync_ns = 0
        #: The last command of the cycle (any command: the deadline-miss test).
        self.command_ns = 0
        #: The cycle's latency pair: a command and the sensor frame it answers (the frame
        #: whose handler sent it); 0: no such pair in this cycle.
        self.sensor_ns = 0
        self.answer_ns = 0
        #: The last sensor frame not answered yet (0: none).
        self.unanswered_ns = 0
        #: The cycle's interrupt: its compute time and stage times, kept until recorded.
        self.isr_ns = 0
        self.isr_ran = False
        self.stage_ns = [0] * len(STAGES)
        #: The handler reports its stages (stage hook): ``on_interrupt`` is then ignored.
        self.staged = False

    def clear(self) -> None:
        """A new cycle: no event yet."""
        self.sync_ns = self.sensor_ns = self.answer_ns = self.command_ns = 0
        self.unanswered_ns = 0
        self.isr_ran = False

    def on_sync_sent(self, t_ns: int) -> None:
        self.sync_ns = t_ns

    def on_sensor(self, t_ns: int) -> None:
        # Not the latency's start yet: only a frame that a command answers starts one.  A
        # frame after the cycle's command (this cycle's frame when the previous cycle's
        # came late and was answered, a duplicate, a malformed frame) answers nothing.
        self.unanswered_ns = t_ns

    def on_command_sent(self, t_ns: int) -> None:
        # The controller sends a command from the handler of the frame it answers, so the
        # last unanswered frame is that frame; a command without one pairs with nothing.
        self.command_ns = t_ns
        sensor = self.unanswered_ns
        if sensor:
            self.sensor_ns, self.answer_ns = sensor, t_ns
            self.unanswered_ns = 0

    def on_interrupt(self, start_ns: int, end_ns: int) -> None:
        if not self.staged:
            self.isr_ns = end_ns - start_ns
            self.isr_ran = True

    def stage_hook(self) -> Callable[[int], None]:
        """The stage hook: a time stamp per stage boundary; at the last, the interrupt's
        stage times (successive differences, so they add up to the whole)."""
        stamps = [0] * (len(STAGES) + 1)
        last = len(STAGES)
        now = _now_ns
        ns = self.stage_ns

        def stamp(i: int) -> None:
            t = stamps[i] = now()
            if i == last:
                for j in range(last):
                    ns[j] = stamps[j + 1] - stamps[j]
                self.isr_ns = t - stamps[0]
                self.isr_ran = True

        return stamp


# ------------------------------------------------------------------ statistics
class CycleStats:
    """Per recorded cycle (the pacer records the cycles in which the interrupt ran):
    every figure's min, p50, p99, p99.9, max and mean come from the same samples
    (:func:`percentiles`):

    - **jitter**: when SYNC k was actually handed to the bus minus its deadline;
    - **latency**: from the controller receiving ``DRIVE_TPDO1`` (the frame handed to its
      frame handler) to the command ``DRIVE_RPDO1`` that answers it being handed to the
      bus: decode, interrupt, encode, send.  Each latency pairs a command with the frame
      it answers (:meth:`CycleStamps.on_command_sent`), never with a later frame of the
      same cycle, so it is never negative;
    - **interrupt compute**: the interrupt body (:class:`firmware.isr.InterruptHandler`);
    - **stages** of the interrupt (:data:`firmware.isr.STAGES`), contiguous, so that they
      add up to the interrupt's time in every cycle;
    - **cycle work**: from the deadline (or the wake-up, if later) to the end of the
      cycle's frame handling: what the loop computes per period besides spinning;
    - **sleep overshoot**: how late ``time.sleep`` returned (the machine's share of the
      tail);
    - **misses**: cycles whose command was not handed to the bus before the next SYNC's
      deadline (or never).
    """

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.jitter_us = array("d")
        self.latency_us = array("d")
        self.isr_us = array("d")
        self.work_us = array("d")
        self.overshoot_us = array("d")  # NaN: no sleep that cycle
        self.stage_us = {key: array("d") for key, _ in STAGES}
        self._stage_arrays = [self.stage_us[key] for key, _ in STAGES]
        self.misses = 0
        self.cycles = 0
        self.late_starts = 0
        self.late_wakeups = 0
        self.busy_ns = 0

    def record(self, deadline: int, wake: int, end: int, overshoot: int, spin_ns: int,
               started_late: bool, stamps: CycleStamps) -> None:  # fmt: skip
        """Append one cycle: its deadline, when the loop woke, when its frames were all
        handled, how late the sleep woke (-1: no sleep), the spin window and whether it
        started late (all ns), and its events' time stamps."""
        work = end - (wake if wake > deadline else deadline)
        self.cycles += 1
        self.busy_ns += end - wake
        self.work_us.append(work * 1e-3)
        self.overshoot_us.append(overshoot * 1e-3 if overshoot >= 0 else math.nan)
        if overshoot > spin_ns:
            self.late_wakeups += 1
        if started_late:
            self.late_starts += 1
        sync = stamps.sync_ns
        self.jitter_us.append((sync - deadline) * 1e-3 if sync else math.nan)
        command = stamps.command_ns
        if stamps.answer_ns:
            self.latency_us.append((stamps.answer_ns - stamps.sensor_ns) * 1e-3)
        if not command or command >= deadline + self.period_ns:
            self.misses += 1
        if stamps.isr_ran:
            if stamps.staged:
                for a, ns in zip(self._stage_arrays, stamps.stage_ns, strict=True):
                    a.append(ns * 1e-3)
            self.isr_us.append(stamps.isr_ns * 1e-3)

    def summary(self) -> dict[str, Any]:
        """The statistics, in the report's order (``result()["realtime"]`` up to
        ``late_wakeups``)."""
        jitter = _finite(self.jitter_us)
        overshoot = _finite(self.overshoot_us)  # the cycles that slept
        stages = {}
        for key, label in STAGES:
            stages[key] = {"label": label, **percentiles(self.stage_us[key])}
        return {
            "cycles": self.cycles,
            "sample_period_s": self.period_ns * 1e-9,
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
        }

    @property
    def cpu_share(self) -> float:
        """The loop's share of the recorded periods spent awake (spin and work)."""
        return self.busy_ns / (self.cycles * self.period_ns) if self.cycles else math.nan


#: The keys of :func:`percentiles`, in the report's column order.
PERCENTILE_KEYS = ("min", "p50", "p99", "p99.9", "max", "mean")


def percentiles(values: Iterable[float]) -> dict[str, float]:
    """min, p50, p99, p99.9, max (nearest rank) and mean of the values that are not NaN,
    all from the same samples: min <= p50 <= p99 <= p99.9 <= max and min <= mean <= max
    (the mean is held within the extremes against the division's rounding).  NaN when
    there is no value."""
    s = sorted(v for v in values if not math.isnan(v))
    n = len(s)
    if not n:
        return dict.fromkeys(PERCENTILE_KEYS, math.nan)

    def rank(p: float) -> float:
        return s[min(n - 1, max(0, math.ceil(p * n) - 1))]

    lo, hi = s[0], s[-1]
    mean = math.fsum(s) / n
    return {"min": lo, "p50": rank(0.50), "p99": rank(0.99), "p99.9": rank(0.999), "max": hi,
            "mean": min(hi, max(lo, mean))}  # fmt: skip


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


# ------------------------------------------------------------------ text
def _row(label: str, p: dict[str, float]) -> str:
    return f"    {label:<30}" + "".join(f" {p[key]:9.1f}" for key in PERCENTILE_KEYS)


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
    lines.append(f"    {'µs':<30}" + "".join(f" {key:>9}" for key in PERCENTILE_KEYS))
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
