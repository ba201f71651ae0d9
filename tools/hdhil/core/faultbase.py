"""What every fault injector shares, whatever it faults: the log and the random streams.

Bus faults (:mod:`hdhil.can.faults`) and sensor faults (:mod:`hdhil.hostsim.sensor_faults`)
live in different layers but must record into one :class:`FaultLog` and draw from
streams seeded the same way, so that a run's faults are reproducible by one seed and
none is injected unrecorded. The checks of a fault's rates and times are here too, so a
bad value is refused in the same words in both.
"""

from __future__ import annotations

import math
import random
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from hdhil.core import jsonout
from hdhil.core.errors import ConfigError
from hdhil.core.files import check_output

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
    """Every injected fault, in memory (``records``) and optionally as JSON lines."""

    def __init__(self, path: str | Path | None = None, keep: bool = True) -> None:
        self.records: list[FaultRecord] = []
        self.counts: Counter[str] = Counter()
        self._keep = keep
        self._fh: IO[str] | None = None
        if path is not None:
            target = check_output(path, "fault log")  # a regular file, never a device
            try:
                # Line-buffered: a record is in the file as soon as it is injected, so a
                # killed run (SIGKILL) loses none of the faults its trace shows.
                self._fh = open(target or "/dev/stdout", "w", encoding="utf-8", buffering=1)  # noqa: SIM115
            except OSError as exc:
                raise ConfigError(
                    f"fault log {path}: cannot write ({exc.strerror or exc})"
                ) from None

    def record(self, time: float, channel: str, kind: str, frame_id: int | None,
               **details: Any) -> None:  # fmt: skip
        rec = FaultRecord(time, channel, kind, frame_id, details)
        self.counts[kind] += 1
        if self._keep:
            self.records.append(rec)
        if self._fh is not None:
            self._fh.write(jsonout.dumps(rec.as_dict(), sort_keys=True) + "\n")

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


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
