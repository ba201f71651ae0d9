"""``hdhil run --realtime``: the lockstep run paced by the wall clock at the sample period.

Pacing: cycle k's SYNC is due at ``t0 + k·Ts`` on the monotonic clock
(:func:`time.perf_counter_ns`).  The runner sleeps until about :data:`SPIN_NS` before the
deadline (``time.sleep`` wakes late by 50-100 µs on a loaded Linux VM), then spins to it.
The schedule is absolute: a cycle that overruns is not skipped, the next SYNC goes out at
once and the following ones catch up, as a hardware timer would keep its phase.

Clock: the simulated bus's clock (:class:`WallClock`) reads wall time since the run
started, so every frame is requested at the moment it was really sent and trace
timestamps are real (the wire time of each frame is still modelled by ``simbus``).  The
drive stays locked to SYNC: it integrates the plant one period per SYNC, whatever the
wall time between two SYNCs was.

Statistics, per operation cycle (start-up and stop cycles are not counted), kept in
``array('d')`` (nothing else is allocated per cycle):

- **jitter**: when SYNC k was actually handed to the bus minus its deadline;
- **latency**: from the controller receiving ``DRIVE_TPDO1`` (its bus's ``recv``
  returning it) to the command ``DRIVE_RPDO1`` being handed to the bus: decode,
  interrupt, encode, send;
- **isr**: compute time of the interrupt body alone (:class:`firmware.isr.InterruptHandler`
  call);
- **misses**: cycles whose command was not handed to the bus before the next SYNC's
  deadline (or never).

The bus's ``send``/``recv`` and the controller's interrupt are wrapped for the run only
(instance attributes, the firmware is unchanged); each wrapper costs one or two
``perf_counter_ns`` calls.

Determinism, each applied where permitted and reported in ``applied`` / ``refused``:

- ``gc``: ``gc.collect()`` before the loop and ``gc.disable()`` during it.  This helps
  most: a generation-2 collection in the middle of a cycle costs milliseconds once the
  heap holds the scenario, the DBC and the CANopen object dictionaries.  The loop itself
  allocates little, so memory stays flat over minutes without the collector (reference
  counting frees everything that is not cyclic).
- ``affinity``: :func:`os.sched_setaffinity` to one CPU (the last one allowed), which
  avoids migrations and keeps the caches warm; on a 2-core shared VM it helps little.
- ``SCHED_FIFO``: :func:`os.sched_setscheduler` with real-time priority 50 (root or
  CAP_SYS_NICE only).  It keeps other processes from preempting the loop and is what
  bounds the tail (p99.9, max) on a loaded machine; the kernel's RT throttling (95 % by
  default) still guarantees others a share.  Without the privilege it is reported as
  refused and the run goes on.

All three are undone when the loop ends.

Measured (20 s runs, free-motion, shared 2-core EPYC VM, as root; SYNC jitter p50 /
p99.9 / max, deadline misses): all three applied 4 / 415 / 2 274 µs, 5 misses; without
SCHED_FIFO 4 / 14 258 / 31 876 µs, 55 misses; with gc disabled only 4 / 36 783 /
54 569 µs, 122 misses.  Pure spinning (no sleep) under SCHED_FIFO is much worse: the
kernel's RT throttling parks the task for 50 ms every second (p99 41 ms, 1 022 misses in
20 000 cycles), so the loop must sleep most of each period.  The remaining tail (p99.9
0.4-1 ms) is late wake-ups of ``time.sleep`` on the VM, not compute: the sensor-to-command
latency stays under 0.3 ms at its maximum.  Not done here: ``mlockall`` (not in :mod:`os`),
isolated CPUs (``isolcpus``/``nohz_full``), disabling frequency scaling: those are the
next steps on a dedicated bench PC.

``--interface virtual`` (and any real python-can interface) works too: pacing and
statistics are the same, only the clock is the monotonic clock the non-simulated path
already uses.  There the statistics cover the cycles paced in operation; the first
sample may already be handled in the last start-up cycle (the statusword and the sensor
frame can arrive in either order), so they may count one cycle fewer than the run.
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import time
from array import array
from collections.abc import Callable
from typing import Any

import can

from hdhil.simbus import SimClock

#: Spin (busy-wait) for the last this many nanoseconds before a deadline.
SPIN_NS = 200_000

#: SCHED_FIFO priority asked for (1..99); 50 is below the kernel's IRQ threads.
FIFO_PRIORITY = 50

#: Jitter histogram bin edges in µs (1-2-5 log spacing); below the first edge (early or
#: under 1 µs late) is the first bin, from the last edge on the last.
HISTOGRAM_EDGES_US = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000)

_now_ns = time.perf_counter_ns


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


class _TimedIsr:
    """Forwards everything to the interrupt handler; times its call."""

    __slots__ = ("_isr", "_sink")

    def __init__(self, isr: Any, sink: Callable[[int], None]) -> None:
        object.__setattr__(self, "_isr", isr)
        object.__setattr__(self, "_sink", sink)

    def __call__(self, sample: Any) -> Any:
        t = _now_ns()
        out = self._isr(sample)
        self._sink(_now_ns() - t)
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self._isr, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._isr, name, value)


def percentiles(values: array) -> dict[str, float]:
    """p50, p99, p99.9 and max (nearest rank) of ``values``; NaN when empty."""
    n = len(values)
    if not n:
        return {"p50": math.nan, "p99": math.nan, "p99.9": math.nan, "max": math.nan}
    s = sorted(values)

    def rank(p: float) -> float:
        return s[min(n - 1, max(0, math.ceil(p * n) - 1))]

    return {"p50": rank(0.50), "p99": rank(0.99), "p99.9": rank(0.999), "max": s[-1]}


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


class RealtimeLoop:
    """Paces the cycles, instruments the controller, collects the statistics."""

    def __init__(self, sample_period_s: float, *, sync_id: int = 0x080,
                 sensor_id: int = 0x182, command_id: int = 0x202) -> None:  # fmt: skip
        self.period_ns = round(sample_period_s * 1e9)
        self.sync_id = sync_id
        self.sensor_id = sensor_id
        self.command_id = command_id
        self.t0_ns = 0
        self.recording = False
        self.jitter_us = array("d")
        self.latency_us = array("d")
        self.isr_us = array("d")
        self.misses = 0
        self.cycles = 0
        self.applied: list[str] = []
        self.refused: list[str] = []
        self._deadline = 0
        self._sync_ns = 0
        self._sensor_ns = 0
        self._command_ns = 0
        self._restore: list[Callable[[], None]] = []

    # ------------------------------------------------------------ instrumentation

    def instrument(self, controller: Any) -> None:
        """Wrap the controller's bus send/recv and its interrupt (for this run only)."""
        bus: can.BusABC = controller.bus
        send, recv = bus.send, bus.recv
        sync_id, sensor_id, command_id = self.sync_id, self.sensor_id, self.command_id

        def timed_send(msg: can.Message, timeout: float | None = None) -> None:
            t = _now_ns()
            ident = msg.arbitration_id
            if ident == command_id:
                self._command_ns = t
            elif ident == sync_id:
                self._sync_ns = t
            send(msg, timeout)

        def timed_recv(timeout: float | None = None) -> can.Message | None:
            msg = recv(timeout)
            if msg is not None and msg.arbitration_id == sensor_id:
                self._sensor_ns = _now_ns()
            return msg

        bus.send = timed_send  # type: ignore[method-assign]
        bus.recv = timed_recv  # type: ignore[method-assign]
        controller.isr = _TimedIsr(controller.isr, self._isr_done)

    def _isr_done(self, ns: int) -> None:
        if self.recording:
            self.isr_us.append(ns * 1e-3)

    # ------------------------------------------------------------ determinism

    def enter(self) -> None:
        """Apply what improves determinism and is permitted; note what was refused."""
        if hasattr(os, "sched_setaffinity"):
            try:
                before = os.sched_getaffinity(0)
                cpu = max(before)
                os.sched_setaffinity(0, {cpu})
                self.applied.append(f"affinity: CPU {cpu}")
                self._restore.append(lambda: os.sched_setaffinity(0, before))
            except OSError as exc:
                self.refused.append(f"affinity: {exc.strerror or exc}")
        else:
            self.refused.append("affinity: not supported on this platform")
        if hasattr(os, "sched_setscheduler"):
            try:
                policy = os.sched_getscheduler(0)
                param = os.sched_getparam(0)
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
                self.applied.append(f"SCHED_FIFO priority {FIFO_PRIORITY}")
                self._restore.append(lambda: os.sched_setscheduler(0, policy, param))
            except OSError as exc:
                self.refused.append(f"SCHED_FIFO: {exc.strerror or exc} (needs root/CAP_SYS_NICE)")
        else:
            self.refused.append("SCHED_FIFO: not supported on this platform")
        gc.collect()
        if gc.isenabled():
            gc.disable()
            self._restore.append(gc.enable)
        self.applied.append("gc disabled during the loop (collected before)")

    def exit(self) -> None:
        """Undo :meth:`enter` (in reverse order)."""
        while self._restore:
            with contextlib.suppress(OSError):  # best effort
                self._restore.pop()()

    # ------------------------------------------------------------ pacing

    def start(self, t0_ns: int | None = None) -> int:
        """Cycle 0 is due now (or at ``t0_ns``)."""
        self.t0_ns = _now_ns() if t0_ns is None else t0_ns
        return self.t0_ns

    def wait(self, k: int) -> None:
        """Sleep, then spin, until cycle ``k``'s deadline."""
        deadline = self.t0_ns + k * self.period_ns
        self._deadline = deadline
        self._sync_ns = self._sensor_ns = self._command_ns = 0
        remaining = deadline - _now_ns()
        if remaining > SPIN_NS:
            time.sleep((remaining - SPIN_NS) * 1e-9)
        while _now_ns() < deadline:
            pass

    def end_cycle(self) -> None:
        """After the cycle's frames are handled: record it (while recording)."""
        if not self.recording:
            return
        self.cycles += 1
        deadline = self._deadline
        sync = self._sync_ns
        self.jitter_us.append((sync - deadline) * 1e-3 if sync else math.nan)
        command = self._command_ns
        if command and self._sensor_ns:
            self.latency_us.append((command - self._sensor_ns) * 1e-3)
        if not command or command >= deadline + self.period_ns:
            self.misses += 1

    # ------------------------------------------------------------ report

    def result(self) -> dict[str, Any]:
        jitter = array("d", (v for v in self.jitter_us if not math.isnan(v)))
        return {
            "cycles": self.cycles,
            "sample_period_s": self.period_ns * 1e-9,
            "deadline_misses": self.misses,
            "jitter_us": percentiles(jitter),
            "latency_us": percentiles(self.latency_us),
            "isr_us": percentiles(self.isr_us),
            "jitter_histogram": histogram(jitter),
            "syncs_missing": self.cycles - len(jitter),
            "applied": list(self.applied),
            "refused": list(self.refused),
            "spin_us": SPIN_NS * 1e-3,
        }


def format_realtime(rt: dict[str, Any]) -> str:
    """The statistics as text: a percentile table and the jitter histogram."""
    lines = [
        f"  real time          {rt['cycles']} cycles paced at "
        f"{rt['sample_period_s'] * 1e3:g} ms; deadline misses {rt['deadline_misses']}",
        f"    applied: {'; '.join(rt['applied']) or 'nothing'}",
    ]
    if rt["refused"]:
        lines.append(f"    refused: {'; '.join(rt['refused'])}")
    lines.append(f"    {'µs':<28} {'p50':>9} {'p99':>9} {'p99.9':>9} {'max':>9}")
    for key, label in (("jitter_us", "SYNC jitter (late)"),
                       ("latency_us", "sensor frame -> command"),
                       ("isr_us", "interrupt compute")):  # fmt: skip
        p = rt[key]
        lines.append(
            f"    {label:<28} {p['p50']:9.1f} {p['p99']:9.1f} {p['p99.9']:9.1f} {p['max']:9.1f}"
        )
    lines.append("    SYNC jitter histogram:")
    bins = rt["jitter_histogram"]
    top = max((b["count"] for b in bins), default=0) or 1
    for b in bins:
        if b["count"]:
            bar = "#" * max(1, round(40 * b["count"] / top))
            lines.append(f"      {b['bin']:>14} {b['count']:>8}  {bar}")
    return "\n".join(lines)
