"""A run's injected faults as one table: the scenario's ``[faults]`` and its ``--fault`` flags.

:class:`FaultConfig` gathers what goes wrong on the control and truth channels
(:class:`hdhil.can.faults.BusFaults`) and at the drive's sensors
(:class:`hdhil.hostsim.sensor_faults.SensorFaults`) under one seed; a
:class:`FaultInjector` builds the hooks the simulated bus, a node's own bus and the plant
take, all recording into one :class:`~hdhil.core.faultbase.FaultLog`::

    injector = FaultInjector(from_dict(FaultConfig, {"control": {"loss_rate": 0.05}}))
    bus = can.Bus(interface="simbus", channel="control", clock=clock,
                  faults=injector.channel("control"))
    plant = Plant(cfg, seed, faults=injector.sensors())
    ...
    injector.summary()  # {"loss": 97, ...}

It lives here, above both the CAN layer and the emulator, because it holds both kinds.
``--fault KEY=VALUE`` (:func:`parse_fault_flags`, :func:`with_fault_flags`) takes the
table's dotted keys, each value a TOML value, merged over the scenario's table (a flag
wins) and checked by the same dataclasses.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from hdhil.can.faults import BusFaults, ChannelFaults
from hdhil.core.dataconf import ConfigError, from_dict, merge, to_dict
from hdhil.core.faultbase import FaultLog
from hdhil.hostsim.sensor_faults import SensorFaultInjector, SensorFaults, SensorHook

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

__all__ = ["FaultConfig", "FaultInjector", "parse_fault_flags", "with_fault_flags"]


@dataclass(frozen=True)
class FaultConfig:
    """All injected faults of a run (the ``[faults]`` table); ``seed`` makes them
    reproducible: the same seed gives the same faults at the same frames."""

    seed: int = 0
    control: BusFaults = field(default_factory=BusFaults)
    truth: BusFaults = field(default_factory=BusFaults)
    sensors: SensorFaults = field(default_factory=SensorFaults)

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"FaultConfig.seed must be an integer >= 0, got {self.seed!r}")

    @property
    def enabled(self) -> bool:
        return self.control.enabled or self.truth.enabled or self.sensors.enabled


class FaultInjector:
    """Builds the hooks of a :class:`FaultConfig` and keeps their common log."""

    def __init__(self, config: FaultConfig, log: FaultLog | None = None, stream: str = "") -> None:
        """``stream`` names the node whose transmissions the channel hooks fault, when each
        node runs in a process of its own (see :class:`ChannelFaults`)."""
        self.config = config
        self.log = log if log is not None else FaultLog()
        self.stream = stream
        self._channels: dict[str, ChannelFaults] = {}
        self._sensors = SensorFaultInjector(config.sensors, config.seed, self.log)

    def channel(self, role: Literal["control", "truth"]) -> ChannelFaults | None:
        """The hook for the ``control`` or ``truth`` channel; None without faults there.
        Every bus of the channel may pass it (it is the same object)."""
        cfg: BusFaults = getattr(self.config, role)
        if not cfg.enabled:
            return None
        hook = self._channels.get(role)
        if hook is None:
            hook = self._channels[role] = ChannelFaults(
                cfg, role, self.config.seed, self.log, self.stream
            )
        return hook

    def sensors(self, always: bool = False) -> SensorHook | None:
        """The plant's sensor-fault hook; None without sensor faults unless ``always``
        (a hook to switch faults on later, :meth:`SensorHook.reconfigure`)."""
        return self._sensors.sensors(always)

    def summary(self) -> dict[str, int]:
        """Injected faults per kind."""
        return dict(sorted(self.log.counts.items()))


# ----------------------------------------------------------------------------- flags
#: A dotted key of the ``[faults]`` table: TOML bare keys joined by dots.
_FLAG_KEY = re.compile(r"[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*")


def parse_fault_flags(flags: Sequence[str]) -> dict[str, Any]:
    """``--fault KEY=VALUE`` flags as a nested ``[faults]`` table, later flags winning.

    ``KEY`` is a dotted key of the table (``control.loss_rate``, ``seed``); ``VALUE`` is a
    TOML value (``0.05``, ``[{node = 2, start_s = 1}]``, ``"max"``).  Syntax errors raise
    :class:`hdhil.core.dataconf.ConfigError` naming the flag; the values are checked by
    :func:`with_fault_flags`.
    """
    table: dict[str, Any] = {}
    for flag in flags:
        key, sep, text = flag.partition("=")
        key = key.strip()
        if not sep or not _FLAG_KEY.fullmatch(key):
            raise ConfigError(
                f"--fault {flag!r}: expected KEY=VALUE with a dotted key of the [faults] "
                "table, e.g. control.loss_rate=0.05"
            )
        try:
            parsed = tomllib.loads(f"value = {text}")
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(
                f"--fault {key}: {text!r} is not a TOML value ({exc}); strings need quotes, "
                'e.g. sensors.stuck=[{channel="tacho", start_s=1}]'
            ) from None
        if set(parsed) != {"value"}:
            raise ConfigError(f"--fault {key}: {text!r} is more than one TOML value")
        value: Any = parsed["value"]
        for part in reversed(key.split(".")):
            value = {part: value}
        table = merge(table, value)
    return table


def with_fault_flags(config: FaultConfig | None, flags: Sequence[str]) -> FaultConfig | None:
    """``config`` (a scenario's ``[faults]``, None if it has none) with ``--fault`` flags
    merged over it, validated as the table is: unknown keys, wrong types and values out of
    range raise :class:`hdhil.core.dataconf.ConfigError` naming the key."""
    if not flags:
        return config
    table = merge(to_dict(config) if config is not None else {}, parse_fault_flags(flags))
    try:
        return from_dict(FaultConfig, table, "faults")
    except ConfigError as exc:
        raise ConfigError(f"--fault: {exc}") from None
