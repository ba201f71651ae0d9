"""Scenarios: a named experiment as data (a TOML file), loaded into typed configuration.

Layout of a scenario file::

    [scenario]                 # required
    name = "free-motion"       # required, non-empty
    description = "..."        # optional
    duration_s = 2.0           # required, > 0
    seed = 1                   # optional (default 0), >= 0: noise seed of the plant

    [plant.drivetrain]         # optional: overrides of PlantConfig, table by table
    b_motor = 1.7              # (hostsim.plant; defaults fill the rest)

    [plant.bridge]             # the strain-gauge torque sensor (hostsim.bridge)
    volt2Nm = 6.62             # its TRUE gain; the firmware's calibration may differ

    [plant.load]               # external load torque on the output (LoadTorqueConfig)
    kind = "steps"
    step_times_s = [1.0, 2.0]
    step_values_Nm = [-1.0, 0.0]

    [faults]                   # optional: injected faults (hdhil.can.faults.FaultConfig)
    seed = 3
    control = { loss_rate = 0.05, jitter_us = 200.0 }

    [firmware.reference]       # optional: passed through as a raw dict; the runner
    wave = "step"              # validates it with the firmware's own config class

Shipped scenarios live in ``hdhil/hostsim/scenarios/*.toml`` (package data) and are
addressed by file stem; any other ``.toml`` file is addressed by path:

- ``free-motion``: [Taghirad97] Fig. 8-9, step to ~156 rad/s, 2x/4x ripple;
- ``misalignment``: [Taghirad97] §5 Fig. 10-11, constant ~156 rad/s, 10 Nm p-p
  misalignment at the output angle, 15 s (3.7 output revolutions);
- ``speed-chirp``: triangle sweep of the motor between ~20 and ~200 rad/s, 20 s;
- ``torque-steps``: load-torque steps of 0.5-1 Nm at 98-171 rad/s, 6 s;
- ``chirp``: [Vertechy] Fig. 5, the exoskeleton joint under a motor-torque chirp;
- ``lqg-tracking``: [Vertechy] §VI Fig. 7, JTF1 with the link moved 20° sin 2πt;
- ``lqg-experiment``: [Vertechy] §VI Fig. 8, JTF1 with the Eq. 5 friction compensation
  while a person moves the link over ±60°;
- ``lqg-misalignment``: [Vertechy]'s regulator on the ripple-filtered torque of a joint
  with [Taghirad97]'s meshing ripple and misalignment.

Every
mistake (unknown name, missing file, TOML syntax, unknown key, wrong type, value out
of range) raises :class:`hdhil.core.dataconf.ConfigError` with a one-line message.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from hdhil.core.dataconf import ConfigError, from_dict, merge
from hdhil.core.errors import UserError
from hdhil.core.files import load_toml
from hdhil.hostsim.plant import PlantConfig
from hdhil.rig.faults import FaultConfig

__all__ = ["Scenario", "list_scenarios", "load_scenario", "scenario_from_dict"]

_TOP_LEVEL = ("scenario", "plant", "firmware", "faults")


@dataclass(frozen=True)
class Scenario:
    """One experiment: how long, which noise seed, the drive's physics, the firmware setup.

    ``firmware`` is the raw ``[firmware]`` table (nested dicts); this module does not
    import the firmware and does not validate it.
    """

    name: str
    description: str
    duration_s: float
    seed: int
    plant: PlantConfig = field(default_factory=PlantConfig)
    firmware: dict[str, Any] = field(default_factory=dict)
    #: Where the side-by-side evaluation starts (s): after the motor has turned enough for
    #: any filter to tell ripple from torque (a ripple at standstill is a static offset
    #: no causal filter can separate from true torque).  The whole-run figure is always
    #: reported too.
    evaluate_from_s: float = 0.0
    #: Injected faults (the optional ``[faults]`` table); None = a healthy setup.
    faults: FaultConfig | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise ValueError(f"scenario.name must be a non-empty string, got {self.name!r}")
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
        if not isinstance(self.firmware, dict):
            raise ValueError(f"firmware must be a table, got {self.firmware!r}")


@dataclass(frozen=True)
class _Header:
    """The ``[scenario]`` table (validated on its own so errors name ``scenario.*``)."""

    name: str
    duration_s: float
    description: str = ""
    seed: int = 0
    evaluate_from_s: float = 0.0


def _scenario_dir() -> Path:
    return Path(str(resources.files("hdhil.hostsim").joinpath("scenarios")))


def list_scenarios() -> list[str]:
    """Names (file stems) of the scenarios shipped in ``hdhil/hostsim/scenarios``, sorted."""
    return sorted(p.stem for p in _scenario_dir().glob("*.toml") if p.is_file())


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
        header_data = data["scenario"]
        if not isinstance(header_data, dict):
            raise ConfigError(f"scenario: expected a table, got {header_data!r}")
        for key in ("name", "duration_s"):
            if key not in header_data:
                raise ConfigError(f"missing key scenario.{key}")
        header = from_dict(_Header, header_data, "scenario")
        plant_data = data.get("plant", {})
        if not isinstance(plant_data, dict):
            raise ConfigError(f"plant: expected a table, got {plant_data!r}")
        plant = from_dict(PlantConfig, plant_data, "plant")
        firmware = data.get("firmware", {})
        if not isinstance(firmware, dict):
            raise ConfigError(f"firmware: expected a table, got {firmware!r}")
        faults_data = data.get("faults")
        faults = None
        if faults_data is not None:
            if not isinstance(faults_data, dict):
                raise ConfigError(f"faults: expected a table, got {faults_data!r}")
            faults = from_dict(FaultConfig, faults_data, "faults")
        return Scenario(
            name=header.name,
            description=header.description,
            duration_s=header.duration_s,
            seed=header.seed,
            plant=plant,
            firmware=firmware,
            evaluate_from_s=header.evaluate_from_s,
            faults=faults,
        )
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    except ValueError as exc:  # Scenario.__post_init__
        raise ConfigError(f"{source}: {exc}") from None


def _resolve(name_or_path: str) -> Path:
    """A shipped scenario's file for a bare name; otherwise the path as given."""
    text = str(name_or_path)
    looks_like_path = text.endswith(".toml") or "/" in text or "\\" in text
    if not looks_like_path:
        path = _scenario_dir() / f"{text}.toml"
        if path.is_file():
            return path
        known = ", ".join(list_scenarios()) or "none"
        raise ConfigError(
            f"unknown scenario {text!r} (known: {known}; or give a path to a .toml file)"
        )
    path = Path(text)
    if not path.exists():
        raise ConfigError(f"scenario file not found: {text}")
    return path  # load_toml refuses what is not a regular file, naming it


def load_scenario(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """Load a shipped scenario by name (``"free-motion"``) or a ``.toml`` file by path.

    ``overrides`` is a nested dict in the file's layout (for example
    ``{"scenario": {"seed": 7}, "plant": {"drivetrain": {"b_motor": 2.0}}}``),
    deep-merged over the file before validation.
    """
    path = _resolve(str(name_or_path))
    try:
        data = load_toml(path, "scenario file")
    except UserError as exc:
        raise ConfigError(str(exc)) from None
    if overrides:
        if not isinstance(overrides, dict):
            raise ConfigError(f"overrides must be a nested dict, got {overrides!r}")
        data = merge(data, overrides)
    return scenario_from_dict(data, str(path))
