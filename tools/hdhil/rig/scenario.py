"""Scenarios: a named experiment as data (a TOML file), loaded once into typed configuration.

A scenario describes both nodes and what is scored, so it lives above them: the drive's
physics (``[plant]``, :class:`hdhil.hostsim.plant.PlantConfig`), the firmware
(``[firmware]``, :class:`hdhil.firmware.config.FirmwareConfig`), injected faults
(``[faults]``), the bus (``[bus]``), the SYNC link (``[link]``) and the evaluation
(``[scenario] evaluate_from_s`` and ``scores``). Every table is typed and validated
here, so a mistake is one :class:`~hdhil.core.dataconf.ConfigError` naming the key.

Shipped scenarios are package data (``hdhil/rig/scenarios/*.toml``) addressed by file
stem; any other ``.toml`` file by path. :func:`scenario_data` is the inverse of
:func:`scenario_from_dict`: the plain form a trace's sidecar, a campaign worker and a
:class:`hdhil.rig.request.RunRequest` carry. The keys are listed in
``docs/reference/scenario-keys.md``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from hdhil.core.dataconf import ConfigError, from_dict, merge, to_dict
from hdhil.core.errors import UserError
from hdhil.core.files import load_toml, shipped_or_path
from hdhil.firmware.config import FirmwareConfig, Law
from hdhil.hostsim.plant import PlantConfig, check_step
from hdhil.rig.faults import FaultConfig
from hdhil.rig.layout import (
    BusSpec,
    JointSpec,
    RobotSpec,
    is_robot_name,
    parse_buses,
    parse_joints,
)

__all__ = [
    "BusConfig",
    "LinkConfig",
    "Scenario",
    "ScenarioHeader",
    "actuation_delay",
    "list_scenarios",
    "load_scenario",
    "scenario_data",
    "scenario_from_dict",
]

_TOP_LEVEL = ("scenario", "plant", "firmware", "faults", "bus", "link", "buses", "joints", "robot")

#: What an evaluation can score: the torque-ripple filter against the true torque, and
#: the torque-control law's tracking of its desired torque ([Vertechy]).
Score = Literal["ripple", "tracking"]


@dataclass(frozen=True)
class BusConfig:
    """The control bus: its bit rate (bit/s) sets the frames' time on the wire."""

    bitrate: int = 1_000_000

    def __post_init__(self) -> None:
        if isinstance(self.bitrate, bool) or not 10_000 <= self.bitrate <= 8_000_000:
            raise ValueError(f"bus.bitrate must be 10000..8000000 bit/s, got {self.bitrate!r}")


@dataclass(frozen=True)
class LinkConfig:
    """When the drive applies a command: at the next SYNC (CiA 402 cyclic synchronous
    modes) or as soon as it arrives."""

    actuation: Literal["next-sync", "immediate"] = "next-sync"


def actuation_delay(actuation: str) -> int:
    """The samples of delay between a command's sample and its action with this
    actuation: the firmware's ``control.delay_samples`` must equal it."""
    return 1 if actuation == "next-sync" else 0


@dataclass(frozen=True)
class Scenario:
    """One experiment, typed: duration, noise seed, both nodes' configuration, faults,
    bus, link and what is scored from when."""

    name: str
    description: str
    duration_s: float
    seed: int
    plant: PlantConfig = field(default_factory=PlantConfig)
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    #: Where the evaluation starts (s): after the motor has turned enough for any filter
    #: to tell ripple from torque (ripple at standstill is a static offset).
    evaluate_from_s: float = 0.0
    #: Injected faults (the optional ``[faults]`` table); None = a healthy setup.
    faults: FaultConfig | None = None
    bus: BusConfig = field(default_factory=BusConfig)
    link: LinkConfig = field(default_factory=LinkConfig)
    #: What the evaluation scores; empty = by the law (:attr:`scored`).
    scores: tuple[Score, ...] = ()
    #: A rig of several joints (:mod:`hdhil.rig.layout`): its named buses (empty: the one
    #: bus of ``bus``), its joints (empty: the one joint of ``plant`` and ``firmware``),
    #: the URDF they come from (None: none) and each joint's merged configuration.
    buses: tuple[tuple[str, BusSpec], ...] = ()
    joints: tuple[JointSpec, ...] = ()
    robot: RobotSpec | None = None
    joint_configs: tuple[tuple[PlantConfig, FirmwareConfig], ...] = field(
        default=(), compare=False, repr=False
    )

    @property
    def is_rig(self) -> bool:
        """Whether the scenario lays out a rig of its own (``[joints]`` or ``[robot]``)."""
        return bool(self.joints)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise ValueError(f"scenario.name must be a non-empty string, got {self.name!r}")
        if "\n" in self.name or "\r" in self.name:
            raise ValueError("scenario.name must be one line")
        if not (isinstance(self.duration_s, (int, float)) and self.duration_s > 0):
            raise ValueError(f"scenario.duration_s must be > 0, got {self.duration_s!r}")
        if self.duration_s == float("inf"):
            raise ValueError("scenario.duration_s must be finite")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"scenario.seed must be an integer >= 0, got {self.seed!r}")
        if not 0.0 <= self.evaluate_from_s < self.duration_s:
            raise ValueError(
                f"scenario.evaluate_from_s must be in [0, duration_s), got {self.evaluate_from_s!r}"
            )
        if not isinstance(self.firmware, FirmwareConfig):
            raise ValueError(f"firmware must be a FirmwareConfig, got {self.firmware!r}")
        # the drive advances its plant once per sample period: refused here, naming the
        # key and its limit, what the stepper could not integrate stably at that step
        if not isinstance(self.plant, PlantConfig):
            raise ValueError(f"plant must be a PlantConfig, got {self.plant!r}")
        check_step(self.plant, self.firmware.sample_period_s)
        firmwares = [("firmware", self.firmware)] + [
            (f"joints.{j.name}.firmware", fw)
            for j, (_, fw) in zip(self.joints, self.joint_configs, strict=False)
        ]
        for where, fw in firmwares:
            control = fw.control
            if control.active and control.delay_samples != actuation_delay(self.link.actuation):
                raise ValueError(
                    f"{where}.control.delay_samples = {control.delay_samples} does not match "
                    f"link.actuation = {self.link.actuation!r} (delay_samples = "
                    f"{actuation_delay(self.link.actuation)}; --actuation sets both)"
                )

    @property
    def scored(self) -> tuple[Score, ...]:
        """What the evaluation scores: ``scores`` if given, else the tracking of a
        torque-control law or, without one, the ripple filter. The ripple filter is
        scored only where its output is used (:attr:`hdhil.firmware.config.ControlConfig.
        ripple_filter_in_loop`): a law regulating on the measured torque leaves it out
        of the loop, and ``scores`` naming it there score the tracking only."""
        control = self.firmware.control
        scored = self.scores or (("tracking",) if control.law != Law.NONE else ("ripple",))
        if not control.ripple_filter_in_loop:
            scored = tuple(s for s in scored if s != "ripple") or ("tracking",)
        return scored


@dataclass(frozen=True)
class ScenarioHeader:
    """The ``[scenario]`` table: the experiment's name and description, its simulated
    duration in operation (s), the plant's noise seed, where the evaluation starts (s)
    and what it scores (``ripple``, ``tracking``; empty: by the control law)."""

    name: str
    duration_s: float
    description: str = ""
    seed: int = 0
    evaluate_from_s: float = 0.0
    scores: tuple[Score, ...] = ()


def _scenario_dir() -> Path:
    return Path(str(resources.files("hdhil.rig").joinpath("scenarios")))


def list_scenarios() -> list[str]:
    """Names (file stems) of the shipped scenarios, sorted."""
    return sorted(p.stem for p in _scenario_dir().glob("*.toml") if p.is_file())


def _table(data: dict[str, Any], key: str) -> dict[str, Any]:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise ConfigError(f"{key}: expected a table, got {value!r}")
    return value


def scenario_from_dict(data: dict[str, Any], source: str = "scenario") -> Scenario:
    """Build a :class:`Scenario` from the plain-data form of a scenario file.

    ``source`` only prefixes error messages (a file name, say).
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a table, got {data!r}")
    unknown = sorted(set(data) - set(_TOP_LEVEL))
    if unknown:
        raise ConfigError(
            f"{source}: unknown table [{unknown[0]}] (known: {', '.join(_TOP_LEVEL)})"
        )
    if "scenario" not in data:
        raise ConfigError(f"{source}: missing [scenario] table (name, duration_s, ...)")
    try:
        header_data = _table(data, "scenario")
        for key in ("name", "duration_s"):
            if key not in header_data:
                raise ConfigError(f"missing key scenario.{key}")
        header = from_dict(ScenarioHeader, header_data, "scenario")
        faults_data = data.get("faults")
        faults = None
        if faults_data is not None:
            if not isinstance(faults_data, dict):
                raise ConfigError(f"faults: expected a table, got {faults_data!r}")
            faults = from_dict(FaultConfig, faults_data, "faults")
        plant_data, firmware_data = _table(data, "plant"), _table(data, "firmware")
        robot = None
        if "robot" in data:
            robot_data = _table(data, "robot")
            if "urdf" not in robot_data:
                raise ConfigError("missing key robot.urdf")
            robot = from_dict(RobotSpec, robot_data, "robot")
        buses: tuple[tuple[str, BusSpec], ...] = ()
        joints: tuple[JointSpec, ...] = ()
        if any(key in data for key in ("buses", "joints", "robot")):
            buses = parse_buses(data.get("buses"), _table(data, "bus"))
            joints = parse_joints(data.get("joints"), buses, robot)
            if not joints:
                raise ConfigError("joints: a rig needs joints ([joints.NAME] or [robot] urdf)")
        joint_configs = tuple(_joint_config(j, plant_data, firmware_data) for j in joints)
        return Scenario(
            name=header.name,
            description=header.description,
            duration_s=header.duration_s,
            seed=header.seed,
            plant=from_dict(PlantConfig, plant_data, "plant"),
            firmware=from_dict(FirmwareConfig, firmware_data, "firmware"),
            evaluate_from_s=header.evaluate_from_s,
            faults=faults,
            bus=from_dict(BusConfig, _table(data, "bus"), "bus"),
            link=from_dict(LinkConfig, _table(data, "link"), "link"),
            scores=header.scores,
            buses=buses,
            joints=joints,
            robot=robot,
            joint_configs=joint_configs,
        )
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    except ValueError as exc:  # Scenario.__post_init__
        raise ConfigError(f"{source}: {exc}") from None


def _joint_config(
    joint: JointSpec, plant: dict[str, Any], firmware: dict[str, Any]
) -> tuple[PlantConfig, FirmwareConfig]:
    """A joint's plant and firmware: its own keys deep-merged over the scenario's."""
    where = f"joints.{joint.name}"
    plant_cfg = from_dict(PlantConfig, merge(plant, joint.plant_overrides), f"{where}.plant")
    fw = from_dict(FirmwareConfig, merge(firmware, joint.firmware_overrides), f"{where}.firmware")
    try:
        check_step(plant_cfg, fw.sample_period_s)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return plant_cfg, fw


def scenario_data(scenario: Scenario) -> dict[str, Any]:
    """The scenario in its TOML layout with every default filled in (plain data):
    ``scenario_from_dict(scenario_data(s)) == s``."""
    header: dict[str, Any] = {
        "name": scenario.name,
        "description": scenario.description,
        "duration_s": scenario.duration_s,
        "seed": scenario.seed,
        "evaluate_from_s": scenario.evaluate_from_s,
    }
    if scenario.scores:
        header["scores"] = list(scenario.scores)
    data: dict[str, Any] = {
        "scenario": header,
        "plant": to_dict(scenario.plant),
        "firmware": to_dict(scenario.firmware),
        "bus": to_dict(scenario.bus),
        "link": to_dict(scenario.link),
    }
    if scenario.faults is not None:
        data["faults"] = to_dict(scenario.faults)
    if scenario.joints:
        data["buses"] = {name: to_dict(spec) for name, spec in scenario.buses}
        # each joint's whole configuration: a mode-dependent default (the ripple filter's
        # oscillators) must not be read back from the scenario's table under its own mode
        data["joints"] = {
            j.name: {**j.to_data(), "plant": to_dict(plant), "firmware": to_dict(fw)}
            for j, (plant, fw) in zip(scenario.joints, scenario.joint_configs, strict=True)
        }
    if scenario.robot is not None:
        data["robot"] = to_dict(scenario.robot)
    return data


def scenario_path(name_or_path: str) -> Path:
    """A shipped scenario's file for a bare name; otherwise the path as given."""
    return shipped_or_path(str(name_or_path), _scenario_dir(), "scenario", list_scenarios())


#: How many scenario files a chain of ``[scenario] base`` may hold.
MAX_BASE_DEPTH = 8


def scenario_file_data(
    name_or_path: str | Path, _chain: tuple[Path, ...] = ()
) -> tuple[Path, dict[str, Any]]:
    """The scenario file's path and its plain data (not validated yet).

    A file whose ``[scenario]`` table has ``base`` (a shipped scenario's name, or a
    ``.toml`` path relative to the file) starts from that scenario's data: its own tables
    are deep-merged over the base's, as ``--override`` files are over a scenario.
    """
    path = scenario_path(str(name_or_path))
    try:
        data = load_toml(path, "scenario file")
    except UserError as exc:
        raise ConfigError(str(exc)) from None
    robot = data.get("robot")
    if (
        isinstance(robot, dict)
        and isinstance(robot.get("urdf"), str)
        and not is_robot_name(robot["urdf"])
    ):
        # a URDF is named relative to the file that names it
        data = {**data, "robot": {**robot, "urdf": str(path.parent / robot["urdf"])}}
    header = data.get("scenario")
    if not isinstance(header, dict) or "base" not in header:
        return path, data
    base = header["base"]
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"{path}: scenario.base must be a scenario name or a .toml path")
    chain = (*_chain, path.resolve())
    if len(chain) > MAX_BASE_DEPTH:
        raise ConfigError(f"{path}: scenario.base: more than {MAX_BASE_DEPTH} files in a chain")
    if "/" in base or base.endswith(".toml"):
        base_ref: str | Path = path.parent / base
    else:
        base_ref = base
    if scenario_path(str(base_ref)).resolve() in chain:
        raise ConfigError(f"{path}: scenario.base {base!r} leads back to a file of its chain")
    _, base_data = scenario_file_data(base_ref, chain)
    own = {**data, "scenario": {k: v for k, v in header.items() if k != "base"}}
    return path, merge(base_data, own)


def load_scenario(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """Load a shipped scenario by name (``"free-motion"``) or a ``.toml`` file by path.

    ``overrides`` is a nested dict in the file's layout (for example
    ``{"scenario": {"seed": 7}, "plant": {"drivetrain": {"b_motor": 2.0}}}``),
    deep-merged over the file before validation.
    """
    text = os.fspath(name_or_path) if isinstance(name_or_path, os.PathLike) else name_or_path
    if not isinstance(text, str):  # bytes too: a name is text, never looked up as b'...'
        raise TypeError(
            f"scenario must be a name or a path (str or os.PathLike), "
            f"got {type(name_or_path).__name__}"
        )
    path, data = scenario_file_data(text)
    if overrides:
        if not isinstance(overrides, dict):
            raise ConfigError(f"overrides must be a nested dict, got {overrides!r}")
        data = merge(data, overrides)
    return scenario_from_dict(data, str(path))
