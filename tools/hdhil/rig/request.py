"""One model of a run: :func:`resolve` turns what a user names into a frozen :class:`RunRequest`.

A base scenario (a shipped name, a TOML file or a :class:`~hdhil.rig.scenario.Scenario`),
override files or tables, ``--fault`` flags, a calibration file, the drive's mapping (a
shipped name or a DCF), duration and seed are merged in that order and validated once;
every mistake is one :class:`~hdhil.core.dataconf.ConfigError` naming the TOML key, the
file or the flag. Every path that runs a scenario takes the result: ``hdhil run``,
``soak``, ``bench``, ``emulate``/``firmware``, campaigns and :mod:`hdhil.api`.

The request is plain data all the way down (:meth:`RunRequest.to_data`): a trace's
sidecar carries it, so ``hdhil evaluate`` scores a trace with exactly the settings it
was run with, and a campaign worker needs no scenario file. The drives are a list
(:attr:`RunRequest.layout`), so a rig of several drives is more entries, not more
parameters.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdhil.canopen.mapping import mapping_dcf
from hdhil.core.dataconf import ConfigError, merge
from hdhil.core.errors import UserError
from hdhil.core.files import load_toml
from hdhil.core.numbers import MAX_SECONDS
from hdhil.firmware.config import FirmwareConfig
from hdhil.rig.factories import DriveSlot, RigLayout
from hdhil.rig.faults import with_fault_flags
from hdhil.rig.scenario import (
    Scenario,
    actuation_delay,
    scenario_data,
    scenario_file_data,
    scenario_from_dict,
)

__all__ = ["Mapping", "RunRequest", "Sources", "resolve"]


@dataclass(frozen=True)
class Mapping:
    """The drive's PDO mapping: ``raw`` (the listing's ADC/DAC objects, no DCF), a
    shipped one by name (``cst``) or a DCF file the controller configures the drive from
    at boot (``label`` is then the file's name)."""

    label: str = "raw"
    dcf: Path | None = None


@dataclass(frozen=True)
class Sources:
    """Where the request's settings came from, as the user named them (recorded in a
    trace's sidecar; not needed to run it again)."""

    scenario: str = "free-motion"
    overrides: tuple[str, ...] = ()
    calibration: str | None = None
    faults: tuple[str, ...] = ()


@dataclass(frozen=True)
class RunRequest:
    """A run, resolved and validated: the typed scenario with everything merged in, the
    duration in whole sample periods, the noise seed, the mapping and the rig layout."""

    scenario: Scenario
    duration_s: float
    seed: int
    #: Where the evaluation starts (s); the scenario's ``evaluate_from_s`` unless a
    #: caller chose another (``hdhil run --skip``).
    evaluate_from_s: float = 0.0
    mapping: Mapping = field(default_factory=Mapping)
    layout: RigLayout = field(default_factory=RigLayout)
    sources: Sources = field(default_factory=Sources)

    def __post_init__(self) -> None:
        if not 0 <= self.evaluate_from_s <= MAX_SECONDS:
            raise ValueError(f"evaluation start must be >= 0 s, got {self.evaluate_from_s}")
        if not 0 < self.duration_s <= MAX_SECONDS:
            raise ValueError(f"duration must be in (0, {MAX_SECONDS:g}] s, got {self.duration_s}")
        if self.cycles < 1:
            raise ValueError(
                f"duration {self.duration_s:g} s is less than one sample period "
                f"({self.sample_period_s:g} s)"
            )

    @property
    def firmware(self) -> FirmwareConfig:
        return self.scenario.firmware

    def require_one_joint(self, what: str = "hdhil run") -> None:
        """Refuse a rig of several joints (:mod:`hdhil.rig.layout`) where only the
        single-joint rig runs: one-line :class:`ConfigError` naming what takes it."""
        s = self.scenario
        if s.is_rig:
            raise ConfigError(
                f"scenario {s.name} lays out {len(s.joints)} joint(s) on "
                f"{len(s.buses)} bus(es): {what} takes the single-joint rig only; "
                f"hdhil run (lockstep on simbus), hdhil evaluate of its trace, hdhil plan and "
                f"hdhil dbc export --scenario take this layout"
            )

    @property
    def name(self) -> str:
        return self.scenario.name

    @property
    def sample_period_s(self) -> float:
        return self.scenario.firmware.sample_period_s

    @property
    def cycles(self) -> int:
        """Interrupts to run in operation (``firmware.num_samples`` caps them)."""
        n = round(self.duration_s / self.sample_period_s)
        limit = self.scenario.firmware.num_samples
        return min(n, limit) if limit else n

    @property
    def actuation(self) -> str:
        return self.scenario.link.actuation

    @property
    def bitrate(self) -> int:
        return self.scenario.bus.bitrate

    def to_data(self) -> dict[str, Any]:
        """Plain data (JSON-able): the inverse of :meth:`from_data`."""
        return {
            "scenario": scenario_data(self.scenario),
            "duration_s": self.duration_s,
            "seed": self.seed,
            "evaluate_from_s": self.evaluate_from_s,
            "mapping": {
                "label": self.mapping.label,
                "dcf": str(self.mapping.dcf) if self.mapping.dcf else None,
            },
            "layout": {
                "controller_node_id": self.layout.controller_node_id,
                "drives": [{"node_id": d.node_id, "bus": d.bus} for d in self.layout.drives],
            },
            "sources": {
                "scenario": self.sources.scenario,
                "overrides": list(self.sources.overrides),
                "calibration": self.sources.calibration,
                "faults": list(self.sources.faults),
            },
        }

    @classmethod
    def from_data(cls, data: dict[str, Any], source: str = "request") -> RunRequest:
        """A request from :meth:`to_data`'s form (a sidecar's ``request``); a damaged one
        is a :class:`ConfigError` naming ``source``."""
        try:
            scenario = scenario_from_dict(data["scenario"], source)
            mapping = data.get("mapping") or {}
            layout = data.get("layout") or {}
            sources = data.get("sources") or {}
            dcf = mapping.get("dcf")
            return cls(
                scenario=scenario,
                duration_s=float(data["duration_s"]),
                seed=int(data["seed"]),
                evaluate_from_s=float(data.get("evaluate_from_s", scenario.evaluate_from_s)),
                mapping=Mapping(str(mapping.get("label", "raw")), Path(dcf) if dcf else None),
                layout=RigLayout(
                    int(layout.get("controller_node_id", 1)),
                    tuple(
                        DriveSlot(int(d["node_id"]))
                        for d in layout.get("drives") or [{"node_id": 2}]
                    ),
                ),
                sources=Sources(
                    str(sources.get("scenario", scenario.name)),
                    tuple(str(p) for p in sources.get("overrides", ())),
                    sources.get("calibration"),
                    tuple(str(f) for f in sources.get("faults", ())),
                ),
            )
        except ConfigError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ConfigError(
                f"{source}: damaged run request ({type(exc).__name__}: {exc})"
            ) from None


def _strip_source(message: str) -> str:
    """A scenario error without the scenario file's name in front (``path: ...``)."""
    head, sep, rest = message.partition(": ")
    return rest if sep and head.endswith(".toml") else message


def _override_table(item: Path | str | dict[str, Any]) -> tuple[dict[str, Any], str]:
    if isinstance(item, dict):
        return item, "overrides"
    path = Path(item)
    try:
        return load_toml(path, "override file"), f"override file {path}"
    except UserError as exc:
        raise ConfigError(str(exc)) from None


def resolve(
    scenario: str | Path | Scenario = "free-motion",
    *,
    overrides: Sequence[Path | str | dict[str, Any]] = (),
    faults: Sequence[str] = (),
    calibration: Path | str | None = None,
    mapping: str | None = None,
    drive_dcf: Path | str | None = None,
    duration_s: float | None = None,
    seed: int | None = None,
    evaluate_from_s: float | None = None,
    actuation: str | None = None,
    bitrate: int | None = None,
    layout: RigLayout | None = None,
) -> RunRequest:
    """Resolve a run: the base scenario, then each override (a TOML file or a nested
    dict in the scenario file's layout, in order), the ``--fault`` flags
    (``control.loss_rate=0.05``), the calibration file (``hdhil calibrate --out``), the
    mapping (a name of :data:`hdhil.dbc.MAPPINGS` or ``drive_dcf``), then duration, seed,
    evaluation start, actuation and bit rate (None keeps the scenario's). Raises
    :class:`ConfigError`."""
    from hdhil.firmware.odlimits import check_od_limits

    if mapping is not None and drive_dcf is not None:
        raise ConfigError("give a mapping name or a drive DCF, not both")
    if isinstance(scenario, Scenario):
        base, label, where = scenario_data(scenario), scenario.name, f"scenario {scenario.name}"
    else:
        if isinstance(scenario, bytes) or not isinstance(scenario, (str, Path)):
            raise ConfigError(f"scenario must be a name or a path, got {scenario!r}")
        path, base = scenario_file_data(scenario)
        label, where = str(scenario), str(path)
    data = base
    resolved = scenario_from_dict(data, where)  # its own mistakes name the scenario file
    for item in overrides:
        table, origin = _override_table(item)
        data = merge(data, table)
        try:  # a mistake an override brings in names the override
            resolved = scenario_from_dict(data, where)
            check_od_limits(resolved.firmware)
        except ConfigError as exc:
            raise ConfigError(f"{origin}: {_strip_source(str(exc))}") from None
    if faults:
        resolved = dataclasses.replace(resolved, faults=with_fault_flags(resolved.faults, faults))
    if calibration is not None:
        from hdhil.rig.calibration import load_calibration

        try:
            table = load_calibration(Path(calibration))
        except UserError as exc:
            raise ConfigError(str(exc)) from None
        data = merge(scenario_data(resolved), {"firmware": table})
        resolved = scenario_from_dict(data, f"calibration file {calibration}")
    extra: dict[str, Any] = {}
    if actuation is not None:  # the firmware's delay compensation follows the drive's
        extra["link"] = {"actuation": actuation}
        if actuation in ("next-sync", "immediate"):
            extra["firmware"] = {"control": {"delay_samples": actuation_delay(actuation)}}
    if bitrate is not None:
        extra["bus"] = {"bitrate": bitrate}
    if extra:
        resolved = scenario_from_dict(merge(scenario_data(resolved), extra), "options")
    duration = resolved.duration_s if duration_s is None else _seconds(duration_s, "duration")
    start = resolved.evaluate_from_s
    if evaluate_from_s is not None:
        start = _seconds(evaluate_from_s, "evaluation start", zero=True)
    if seed is not None and (
        isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63
    ):
        raise ConfigError(f"seed must be an integer in [0, 2**63), got {seed!r}")
    chosen = _mapping(mapping, drive_dcf)
    try:
        return RunRequest(
            scenario=resolved,
            duration_s=duration,
            seed=resolved.seed if seed is None else seed,
            evaluate_from_s=start,
            mapping=chosen,
            layout=layout or RigLayout(),
            sources=Sources(
                scenario=label,
                overrides=tuple(str(o) for o in overrides if not isinstance(o, dict)),
                calibration=str(calibration) if calibration is not None else None,
                faults=tuple(faults),
            ),
        )
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _seconds(value: Any, what: str, zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{what} must be a number of seconds, got {value!r}")
    low_ok = value >= 0 if zero else value > 0
    if not (low_ok and value <= MAX_SECONDS):
        bounds = "[0" if zero else "(0"
        raise ConfigError(f"{what} must be in {bounds}, {MAX_SECONDS:g}] s, got {value!r}")
    return float(value)


def _mapping(name: str | None, drive_dcf: Path | str | None) -> Mapping:
    if drive_dcf is not None:
        from hdhil.core.files import CONFIG_MAX_BYTES, check_input

        try:
            path = check_input(drive_dcf, "DCF", CONFIG_MAX_BYTES)
        except UserError as exc:
            raise ConfigError(str(exc)) from None
        return Mapping(path.name, path)
    label = name or "raw"
    try:
        return Mapping(label, mapping_dcf(label))
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
