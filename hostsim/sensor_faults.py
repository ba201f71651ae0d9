"""Faults of the drive's sensors: stuck or saturated channels, encoder glitches, tacho spikes.

:class:`SensorFaults` is the ``[faults.sensors]`` table of a scenario; a
:class:`SensorHook` applies it to the counts of every :meth:`hdhil.hostsim.plant.Plant.sample`,
drawing from the run's fault seed and recording each fault in the run's
:class:`~hdhil.core.faultbase.FaultLog`. The drive's object 0x2310 switches them at run
time (:meth:`SensorHook.reconfigure`). They are the plant's, not the bus's: this module
imports nothing of CAN; the bus faults are in :mod:`hdhil.can.faults`.
:class:`SensorFaultInjector` builds a plant's hook once, so the plant and the drive
share it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Protocol

from hdhil.core.faultbase import FaultLog, check_nonneg, check_rate, fault_rng
from hdhil.core.numbers import MAX_SECONDS

__all__ = [
    "SensorChannel",
    "SensorFaultInjector",
    "SensorFaultSource",
    "SensorFaults",
    "SensorHook",
    "SensorWindow",
]


SensorChannel = Literal["torque", "tacho", "current", "encoder"]
_SENSOR_INDEX = {"torque": 0, "tacho": 1, "current": 2, "encoder": 3}


@dataclass(frozen=True)
class SensorWindow:
    """A sensor channel misbehaving from ``start_s`` for ``duration_s``.  ``level`` is
    for saturation only: the top (``max``) or bottom (``min``) code."""

    channel: SensorChannel
    start_s: float
    duration_s: float = field(default=math.inf, metadata={"allow_inf": True})
    level: Literal["max", "min"] = "max"

    def __post_init__(self) -> None:
        if self.channel not in _SENSOR_INDEX:
            raise ValueError(f"SensorWindow.channel must be one of {list(_SENSOR_INDEX)}, "
                             f"got {self.channel!r}")  # fmt: skip
        check_nonneg(self, "start_s", hi=MAX_SECONDS)
        check_nonneg(self, "duration_s", allow_inf=True, hi=MAX_SECONDS)

    def active(self, t: float) -> bool:
        return self.start_s <= t < self.start_s + self.duration_s


@dataclass(frozen=True)
class SensorFaults:
    """Faults of the drive's sensors, applied to :meth:`hostsim.plant.Plant.sample`.

    ``stuck``: the channel holds the count it had when the fault began.  ``saturated``:
    the analog channel reads the converter's code limit (the encoder has none: not
    allowed).  ``encoder_glitch_rate`` (per sample): the count jumps by
    ``±encoder_glitch_counts`` (persistently, a lost/gained count burst).
    ``tacho_spike_rate`` (per sample): ``tacho_spike_V`` (random sign) added to one
    tacho sample.
    """

    stuck: tuple[SensorWindow, ...] = ()
    saturated: tuple[SensorWindow, ...] = ()
    encoder_glitch_rate: float = 0.0
    encoder_glitch_counts: int = 0
    tacho_spike_rate: float = 0.0
    tacho_spike_V: float = 0.0

    def __post_init__(self) -> None:
        check_rate(self, "encoder_glitch_rate")
        check_rate(self, "tacho_spike_rate")
        check_nonneg(self, "encoder_glitch_counts")
        check_nonneg(self, "tacho_spike_V")
        for w in self.saturated:
            if w.channel == "encoder":
                raise ValueError("SensorFaults.saturated: the encoder has no code limit")

    @property
    def enabled(self) -> bool:
        return self != SensorFaults()


class SensorHook:
    """The sensor-fault hook of a plant (``Plant(..., faults=...)``)."""

    def __init__(self, cfg: SensorFaults, seed: int, log: FaultLog) -> None:
        self.cfg = cfg
        self.log = log
        self._r_enc = fault_rng(seed, "plant", "encoder_glitch")
        self._r_tacho = fault_rng(seed, "plant", "tacho_spike")
        self._held: dict[SensorWindow, int] = {}  # active stuck windows -> held count
        self._enc_offset = 0

    def reconfigure(self, cfg: SensorFaults) -> None:
        """Switch to ``cfg`` from the next sample on (the drive's object 0x2310).

        The random streams go on where they are, so a run that switches at the same
        samples gets the same faults; the encoder's accumulated glitch offset stays (the
        lost counts are lost); a stuck window that is still configured keeps its count.
        """
        self.cfg = cfg
        for w in [w for w in self._held if w not in cfg.stuck]:
            del self._held[w]

    def apply(self, t: float, sample: tuple[int, int, int, int], code_min: int, code_max: int,
              lsb_V: float) -> tuple[int, int, int, int]:  # fmt: skip
        cfg, log = self.cfg, self.log
        out = list(sample)
        if cfg.encoder_glitch_rate and self._r_enc.random() < cfg.encoder_glitch_rate:
            jump = cfg.encoder_glitch_counts * (1 if self._r_enc.random() < 0.5 else -1)
            self._enc_offset += jump
            log.record(t, "plant", "encoder_glitch", None, counts=jump)
        if self._enc_offset:
            out[3] = (out[3] + self._enc_offset) % 65536
        if cfg.tacho_spike_rate and self._r_tacho.random() < cfg.tacho_spike_rate:
            spike = cfg.tacho_spike_V * (1 if self._r_tacho.random() < 0.5 else -1)
            out[1] = min(code_max, max(code_min, out[1] + round(spike / lsb_V)))
            log.record(t, "plant", "tacho_spike", None, volts=spike)
        for w in cfg.saturated:
            if w.active(t):
                i = _SENSOR_INDEX[w.channel]
                out[i] = code_max if w.level == "max" else code_min
                log.record(t, "plant", "saturated", None, sensor=w.channel, count=out[i])
        for w in cfg.stuck:
            i = _SENSOR_INDEX[w.channel]
            if w.active(t):
                held = self._held.setdefault(w, out[i])
                out[i] = held
                log.record(t, "plant", "stuck", None, sensor=w.channel, count=held)
            else:
                self._held.pop(w, None)
        return out[0], out[1], out[2], out[3]


class SensorFaultSource(Protocol):
    """Where a drive gets the sensor-fault hook of its plant and the log of its faults:
    the run's fault injector (:class:`hdhil.rig.faults.FaultInjector`) or a
    :class:`SensorFaultInjector` of its own."""

    @property
    def log(self) -> FaultLog:
        """The log every fault goes to."""
        ...

    def sensors(self, always: bool = False) -> SensorHook | None:
        """The plant's hook (the same object on every call); None without sensor faults
        unless ``always``."""
        ...


class SensorFaultInjector:
    """The sensor faults of one run: a :class:`SensorHook` built once from ``cfg`` and
    the fault ``seed``, recording into ``log``."""

    def __init__(self, cfg: SensorFaults, seed: int, log: FaultLog) -> None:
        self.cfg = cfg
        self.seed = seed
        self.log = log
        self._hook: SensorHook | None = None

    def sensors(self, always: bool = False) -> SensorHook | None:
        """The plant's sensor-fault hook; None without sensor faults unless ``always``
        (a hook to switch faults on later, :meth:`SensorHook.reconfigure`)."""
        if not (always or self.cfg.enabled):
            return None
        if self._hook is None:
            self._hook = SensorHook(self.cfg, self.seed, self.log)
        return self._hook
