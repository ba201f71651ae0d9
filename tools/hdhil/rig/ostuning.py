"""Operating-system settings for a real-time loop, and what the kernel tells about it.

:class:`ProcessTuning` applies, where permitted, what makes a periodic loop on a
general-purpose Linux more deterministic, reports each setting as applied or refused
with the reason, and undoes everything when the loop ends: the garbage collector off
during the loop, the process pinned to one CPU with no other real-time task,
``PR_SET_TIMERSLACK`` of 1 ns, ``SCHED_FIFO`` (with ``SCHED_RESET_ON_FORK``, so a trace
writer started during the loop runs under the normal policy) and, on request,
``mlockall``. The readers of ``/proc`` give the kernel's RT throttling limit
(:func:`rt_share_limit`), the real-time tasks per CPU (:func:`rt_tasks_per_cpu`) and
the hypervisor's steal time (:func:`cpu_steal_ns`). Why each setting matters is in
``docs/design.md``, "Real time".
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import gc
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

#: The kernel's default RT throttling limit (950 000 µs per 1 000 000 µs), assumed when
#: ``/proc/sys/kernel/sched_rt_*`` cannot be read.
RT_SHARE_DEFAULT = 0.95

#: SCHED_FIFO priority asked for (1..99); 50 is below the kernel's IRQ threads.
FIFO_PRIORITY = 50

#: Timer slack asked for with ``prctl(PR_SET_TIMERSLACK)`` (ns; 0 would mean "default").
TIMER_SLACK_NS = 1

# Linux prctl options and mlockall flags (<linux/prctl.h>, <asm-generic/mman-common.h>;
# powerpc and sparc use other mlockall values: mlockall is not attempted there).
PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4


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


@dataclass
class ProcessTuning:
    """The process settings of a real-time loop (module docstring), each switched on or
    off by its flag, applied where permitted by :meth:`enter` and undone by :meth:`exit`.
    ``applied`` and ``refused`` say what happened, one phrase each; ``cpu`` is the CPU
    the process was pinned to (None: not pinned)."""

    affinity: bool = True
    timer_slack: bool = True
    fifo: bool = True
    mlock: bool = False
    gc_off: bool = True
    applied: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    cpu: int | None = None
    _restore: list[Callable[[], None]] = field(default_factory=list, repr=False)

    def enter(self) -> None:
        """Apply what improves determinism and is permitted; note what was refused."""
        cfg = self
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
        if self.timer_slack and get_timer_slack() == 0:
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
