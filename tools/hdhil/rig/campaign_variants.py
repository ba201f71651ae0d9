"""A campaign's grid as variants, each resolved and validated before anything runs.

:func:`expand` crosses the campaign's axes (a zipped group counts as one axis) over every
base scenario, the last axis varying fastest, and builds each point as ``hdhil run``
builds its options into a scenario, resolved as the worker will resolve it
(:func:`hdhil.rig.variant.request_of`): a variant that would not run is an error of
the campaign file, reported before the first run and before anything is written. A
:class:`Variant` is recognised by :func:`digest_of` its full settings and the hdhil
version; the execution (:mod:`hdhil.rig.campaign`) stores its record under that digest,
so a re-run finds what already finished.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
from dataclasses import dataclass
from importlib import metadata
from typing import Any

from hdhil.core.dataconf import ConfigError, merge
from hdhil.rig.campaign_file import Campaign, printable
from hdhil.rig.campaign_metrics import format_value
from hdhil.rig.rigrun import check_rig_options
from hdhil.rig.scenario import Scenario, scenario_data, scenario_file_data, scenario_from_dict
from hdhil.rig.variant import RunSettings, request_of

__all__ = ["Variant", "digest_of", "expand"]


@dataclass(frozen=True)
class Variant:
    """One point of the grid, resolved and validated."""

    id: str
    scenario: str
    values: dict[str, Any]
    settings: RunSettings
    planned_cycles: int
    digest: str
    #: The joints of the variant's rig, in the layout's order (empty: a single joint).
    joints: tuple[str, ...] = ()

    @property
    def seed(self) -> int:
        seed = self.settings.seed
        return int(self.settings.scenario["scenario"]["seed"]) if seed is None else seed


@functools.cache
def _hdhil_version() -> str:
    try:
        return metadata.version("hdhil")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a checkout
        return "unknown"


def _nested(key: str, value: Any) -> dict[str, Any]:
    out: Any = value
    for part in reversed(key.split(".")):
        out = {part: out}
    return out


def digest_of(settings: RunSettings) -> str:
    """A variant's identity: SHA-256 of its full settings and the hdhil version."""
    blob = json.dumps(
        {
            "scenario": settings.scenario,
            "duration_s": settings.duration_s,
            "seed": settings.seed,
            "trace": settings.trace_suffix,
            "hdhil": _hdhil_version(),
        },
        sort_keys=True,
        separators=(",", ":"),
        allow_nan=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _check_joints(campaign: Campaign, base: str, scenario: Scenario) -> None:
    """Refuse a base scenario that lacks a joint the campaign names (an axis
    ``joints.NAME.*``, a metric ``joints.NAME.*``), or a single joint where the campaign
    names joints or the worst joint: an axis naming a joint the scenario does not have
    would add one."""
    if not campaign.names_joints:
        return
    if not scenario.is_rig:
        raise ConfigError(
            f"scenario {scenario.name} is a single joint: axes and metrics of a joint "
            "(joints.NAME.*, worst.*) take a rig of several joints"
        )
    names = [j.name for j in scenario.joints]
    for name in campaign.joint_names:
        if name not in names:
            raise ConfigError(
                f"joint {printable(name)} is not a joint of scenario {scenario.name} "
                f"({', '.join(names)})"
            )


def expand(campaign: Campaign) -> list[Variant]:
    """Every variant of the campaign in order (scenarios, then the axes as written, the
    last varying fastest), each built and validated as ``hdhil run`` would build it."""
    groups: list[list[dict[str, Any]]] = [
        [{axis.key: v} for v in axis.values] for axis in campaign.axes
    ]
    for group in campaign.zips:
        groups.append([{a.key: a.values[i] for a in group} for i in range(len(group[0].values))])
    points = [
        {k: v for part in combo for k, v in part.items()} for combo in itertools.product(*groups)
    ]
    total = len(campaign.scenarios) * len(points)
    width = max(4, len(str(total)))
    variants: list[Variant] = []
    seen: dict[str, str] = {}
    # A scenario is read, validated and resolved once per base file and once per set of
    # overrides: variants that differ only in the seed share its plain data (one dict).
    files: dict[str, tuple[str, dict[str, Any]]] = {}
    resolved: dict[tuple[str, str], tuple[dict[str, Any], int, tuple[str, ...]]] = {}
    suffix = f".{campaign.trace_format}" if campaign.keep_trace else None
    for base in campaign.scenarios:
        for point in points:
            overrides: dict[str, Any] = {}
            for key, value in point.items():
                if key != "seed":
                    overrides = merge(overrides, _nested(key, value))
            vid = f"{len(variants) + 1:0{width}d}"
            where = printable(
                f"variant {vid} ({base}"
                + "".join(f", {k}={format_value(v)}" for k, v in point.items())
                + ")"
            )
            seed = point.get("seed")
            try:
                key = (base, json.dumps(overrides, sort_keys=True, default=repr))
                if key not in resolved:
                    if base not in files:
                        path, raw = scenario_file_data(base)
                        files[base] = (str(path), raw)
                        _check_joints(campaign, base, scenario_from_dict(raw, str(path)))
                    source, raw = files[base]
                    scenario = scenario_from_dict(merge(raw, overrides), source)
                    data = scenario_data(scenario)
                    if scenario_from_dict(data) != scenario:  # pragma: no cover - to_dict gap
                        raise ConfigError("the scenario does not survive its plain-data form")
                    # What the worker will resolve; the seed (checked in the file, as
                    # ``resolve`` checks it) does not change the cycles planned.
                    request = request_of(RunSettings(data, campaign.duration_s))
                    if scenario.is_rig:  # what a rig's run refuses, before anything runs
                        check_rig_options(request)
                    joints = tuple(j.name for j in scenario.joints)
                    resolved[key] = (data, request.cycles, joints)
                data, planned, joints = resolved[key]
                settings = RunSettings(data, campaign.duration_s, seed, suffix)
            except ConfigError as exc:
                raise ConfigError(f"{where}: {printable(str(exc))}") from None
            digest = digest_of(settings)
            if digest in seen:
                raise ConfigError(f"{where}: same settings as variant {seen[digest]}")
            seen[digest] = vid
            variants.append(Variant(vid, base, dict(point), settings, planned, digest, joints))
    return variants
