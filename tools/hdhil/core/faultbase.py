"""What every fault injector shares, whatever it faults: the log and the random streams.

Bus faults (:mod:`hdhil.can.faults`) and sensor faults (:mod:`hdhil.hostsim.sensor_faults`)
live in different layers but must record into one :class:`FaultLog` and draw from
streams seeded the same way, so that a run's faults are reproducible by one seed and
none is injected unrecorded. The checks of a fault's rates and times are here too, so a
bad value is refused in the same words in both.
"""

from __future__ import annotations

import contextlib
import math
import random
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from hdhil.core import jsonout
from hdhil.core.errors import ConfigError, UserError
from hdhil.core.files import (
    check_output,
    commit_temporary,
    discard_temporary,
    temporary_for,
)

__all__ = ["FaultLog", "FaultRecord", "check_nonneg", "check_rate", "fault_rng"]


@dataclass(frozen=True)
class FaultRecord:
    """One injected fault: simulated time, channel (or ``plant``), kind, frame ID
    (``None`` for sensor faults) and details."""

    time: float
    channel: str
    kind: str
    frame_id: int | None
    details: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        return {"time": self.time, "channel": self.channel, "kind": self.kind,
                "frame_id": self.frame_id, "details": self.details}  # fmt: skip


class FaultLog:
    """Every injected fault, in memory (``records``) and optionally as JSON lines.

    The file is written atomically, like every output (:mod:`hdhil.core.files`): to a
    temporary beside ``path``, one flushed line per fault as it is injected (a run
    killed by SIGKILL loses none of the faults its trace shows: the trace writer renames
    the log into place with the trace, :meth:`hand_over`), renamed over ``path`` when
    the run's outputs are committed (:meth:`close`, or the trace writer).  A log that
    cannot be written (disk full) raises a one-line :class:`UserError` and is discarded
    (:meth:`discard`): the old file stays as it was, no temporary is left.  ``-`` writes
    to standard output as it goes."""

    def __init__(self, path: str | Path | None = None, keep: bool = True) -> None:
        self.records: list[FaultRecord] = []
        self.counts: Counter[str] = Counter()
        self._keep = keep
        self._fh: IO[str] | None = None
        self._target: Path | None = None
        self._tmp: Path | None = None
        #: :meth:`hand_over` gave the file to a trace writer, which renames it.
        self.handed_over = False
        #: Why the log could not be written (``None``: it could): :meth:`close` discards it.
        self.error: str | None = None
        self.label = f"fault log {path}"
        if path is None:
            return
        target = check_output(path, "fault log")  # a regular file, never a device
        try:
            if target is None:
                self._fh = open("/dev/stdout", "w", encoding="utf-8", buffering=1)  # noqa: SIM115
                return
            self._target = target
            self._tmp = temporary_for(target)
            # Line-buffered: a record is in the file as soon as it is injected.
            self._fh = open(self._tmp, "w", encoding="utf-8", buffering=1)  # noqa: SIM115
        except OSError as exc:
            self.discard()
            raise ConfigError(f"{self.label}: cannot write ({exc.strerror or exc})") from None

    def record(self, time: float, channel: str, kind: str, frame_id: int | None,
               **details: Any) -> None:  # fmt: skip
        rec = FaultRecord(time, channel, kind, frame_id, details)
        self.counts[kind] += 1
        if self._keep:
            self.records.append(rec)
        if self._fh is not None:
            try:
                self._fh.write(jsonout.dumps(rec.as_dict(), sort_keys=True) + "\n")
            except OSError as exc:
                self._fail(exc)

    @property
    def failed(self) -> bool:
        """The log could not be written (:attr:`error` says why)."""
        return self.error is not None

    def _fail(self, exc: OSError) -> None:
        self.error = f"{self.label}: cannot write ({exc.strerror or exc})"
        self.discard()
        raise UserError(self.error) from None

    def hand_over(self) -> tuple[Path, Path, str] | None:
        """``(temporary, target, label)`` for a trace writer that renames the log into
        place with its trace (:class:`hdhil.can.traces.writer.WriterProcess`'s
        ``companions``); :meth:`close` then only closes the file.  ``None`` without a
        file (no path, or standard output)."""
        if self._tmp is None or self._target is None:
            return None
        self.handed_over = True
        return self._tmp, self._target, self.label

    def finish(self) -> None:
        """Close the file (every line is in it), without renaming it into place; an error
        discards it (:class:`UserError`)."""
        fh, self._fh = self._fh, None
        if fh is None:
            return
        try:
            fh.close()
        except OSError as exc:
            self._fail(exc)

    def close(self) -> None:
        """Close the file and rename it into place (unless it failed, or was handed over
        to a trace writer, which renames it with its trace)."""
        self.finish()
        if self._tmp is None or self._target is None or self.handed_over:
            return
        if self.failed:
            self.discard()
            return
        tmp, self._tmp = self._tmp, None
        try:
            commit_temporary(tmp, self._target, self.label)
        except UserError as exc:
            self.error = str(exc)
            raise

    def discard(self) -> None:
        """Close and remove the temporary: the old file at ``path`` stays as it was."""
        fh, self._fh = self._fh, None
        if fh is not None:
            with contextlib.suppress(OSError):
                fh.close()
        if self._tmp is not None:
            discard_temporary(self._tmp)
            self._tmp = None


def fault_rng(seed: int, where: str, kind: str) -> random.Random:
    """The random stream of one kind of fault at one place (a channel, ``plant``).

    One generator per place and kind: enabling one fault does not move another's.
    """
    return random.Random(f"hdhil-faults:{seed}:{where}:{kind}")


def check_rate(obj: object, name: str) -> None:
    """``obj.name`` must be a probability in [0, 1]."""
    value = getattr(obj, name)
    if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
        raise ValueError(f"{type(obj).__name__}.{name} must be a probability in [0, 1], "
                         f"got {value!r}")  # fmt: skip


def check_nonneg(obj: object, name: str, allow_inf: bool = False, hi: float | None = None) -> None:
    """``obj.name`` must be >= 0, finite unless ``allow_inf``, and at most ``hi``."""
    value = getattr(obj, name)
    ok = isinstance(value, (int, float)) and value >= 0
    if ok and not allow_inf:
        ok = math.isfinite(value)
    if not ok:
        raise ValueError(f"{type(obj).__name__}.{name} must be >= 0, got {value!r}")
    if hi is not None and value > hi and not (allow_inf and value == math.inf):
        raise ValueError(f"{type(obj).__name__}.{name} must be <= {hi:g}, got {value!r}")
