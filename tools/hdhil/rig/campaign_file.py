"""The campaign file (TOML; ``docs/campaigns.md``), read and checked.

A campaign names base scenarios, axes over any scenario key (crossed, or zipped in groups
of equal length), criteria over the metrics of a run
(:data:`hdhil.rig.campaign_metrics.METRICS`), plots and what to keep.
:func:`load_campaign` takes the name of a campaign shipped beside the scenarios
(:func:`list_campaigns`) or a path, and rejects a bad file with a one-line error naming
it before anything runs. The grid is counted from the axes' lengths before a value list is
built: more than :data:`MAX_VARIANTS` variants is such an error. The grid becomes variants
in :mod:`hdhil.rig.campaign_variants`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.core.errors import UserError
from hdhil.core.files import load_toml, shipped_or_path
from hdhil.core.numbers import MAX_SECONDS, check_number
from hdhil.rig.campaign_metrics import Criterion, known_metrics, metric_kind

__all__ = ["MAX_VARIANTS", "Axis", "Campaign", "list_campaigns", "load_campaign", "printable"]

#: The most variants a campaign may have (base scenarios times the grid's points); a
#: larger grid is refused before its values are built. Split a larger study into files.
MAX_VARIANTS = 10_000

#: Seeds a run takes (``hdhil run --seed``): integers in [0, 2**63).
_SEED_LIMIT = 2**63


@dataclass(frozen=True)
class Axis:
    """A scenario key and the values it takes."""

    key: str
    values: tuple[Any, ...]


@dataclass(frozen=True)
class Campaign:
    """A campaign file, checked: every name resolved, every criterion parsed."""

    name: str
    source: str
    scenarios: tuple[str, ...]
    description: str = ""
    duration_s: float | None = None
    keep_trace: bool = False
    trace_format: str = "blf"
    criteria: tuple[Criterion, ...] = ()
    plots: tuple[str, ...] = ()
    axes: tuple[Axis, ...] = ()
    zips: tuple[tuple[Axis, ...], ...] = ()

    @property
    def axis_keys(self) -> list[str]:
        return [a.key for a in self.axes] + [a.key for group in self.zips for a in group]

    @property
    def plot_metrics(self) -> list[str]:
        names = [c.metric for c in self.criteria] + list(self.plots)
        return [n for i, n in enumerate(names) if n not in names[:i] and metric_kind(n) != "bool"]

    @property
    def joint_names(self) -> list[str]:
        """The joints the axes, criteria and plots name (``joints.NAME...``), in order:
        each must be a joint of every base scenario (:mod:`hdhil.rig.campaign_variants`)."""
        from hdhil.rig.campaign_metrics import split_joint_metric

        names = [key.split(".")[1] for key in self.axis_keys if key.startswith("joints.")]
        for metric in [c.metric for c in self.criteria] + list(self.plots):
            split = split_joint_metric(metric)
            if split is not None and split[0] is not None:
                names.append(split[0])
        return [n for i, n in enumerate(names) if n not in names[:i]]

    @property
    def names_joints(self) -> bool:
        """Whether the axes, criteria or plots name a joint or the worst joint: the
        campaign then takes rigs of several joints only."""
        from hdhil.rig.campaign_metrics import split_joint_metric

        metrics = [c.metric for c in self.criteria] + list(self.plots)
        return bool(self.joint_names) or any(split_joint_metric(m) for m in metrics)


@dataclass(frozen=True)
class _Header:
    name: str
    scenarios: list[str]
    description: str = ""
    duration_s: float | None = None
    keep_trace: bool = False
    trace_format: str = "blf"
    criteria: list[str] = field(default_factory=list)
    plots: list[str] = field(default_factory=list)


_TRACE_FORMATS = ("blf", "asc", "log", "csv", "trc")


def _campaign_dir() -> Path:
    return Path(str(resources.files("hdhil.rig").joinpath("campaigns")))


def list_campaigns() -> list[str]:
    """Names (file stems) of the campaigns shipped beside the scenarios, sorted."""
    return sorted(p.stem for p in _campaign_dir().glob("*.toml") if p.is_file())


def _resolve(name_or_path: str) -> Path:
    return shipped_or_path(str(name_or_path), _campaign_dir(), "campaign", list_campaigns())


def _axis_values(key: str, spec: Any, where: str) -> range | tuple[Any, ...]:
    """The values of an axis; a range stays a range (not built) until the grid's size
    is known."""
    if isinstance(spec, dict):
        if set(spec) != {"range"}:
            raise ConfigError(f"{where}.{key}: expected a list of values or {{ range = [...] }}")
        bounds = spec["range"]
        if (
            not isinstance(bounds, list)
            or not 2 <= len(bounds) <= 3
            or not all(isinstance(b, int) and not isinstance(b, bool) for b in bounds)
        ):
            raise ConfigError(
                f"{where}.{key}: range takes 2 or 3 integers [start, stop(, step)], got {bounds!r}"
            )
        if len(bounds) == 3 and bounds[2] == 0:
            raise ConfigError(f"{where}.{key}: range step must not be 0")
        values: range | tuple[Any, ...] = range(*bounds)
    elif isinstance(spec, list):
        values = tuple(spec)
    else:
        raise ConfigError(f"{where}.{key}: expected a list of values, got {spec!r}")
    if _count(values) == 0:
        raise ConfigError(f"{where}.{key}: no values")
    return values


def _count(values: range | tuple[Any, ...]) -> int:
    """How many values, without building a range (``len`` of a range fails beyond
    ``sys.maxsize``)."""
    if isinstance(values, range):
        start, stop, step = values.start, values.stop, values.step
        span = stop - start if step > 0 else start - stop
        return max(0, -(-span // abs(step)))
    return len(values)


@dataclass(frozen=True)
class _Lazy:
    """An axis before the grid's size is checked: its values may be an unbuilt range."""

    key: str
    values: range | tuple[Any, ...]
    where: str

    def build(self) -> Axis:
        values = tuple(self.values)
        if self.key == "seed":
            for seed in values:
                if isinstance(seed, bool) or not isinstance(seed, int):
                    bad = True
                else:
                    bad = not 0 <= seed < _SEED_LIMIT
                if bad:
                    raise ConfigError(
                        f"{self.where}.seed: seed must be an integer in [0, 2**63), got {seed!r}"
                    )
        return Axis(self.key, values)


def printable(text: str) -> str:
    """``text`` on one line: control characters escaped as in a Python literal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _one_line(text: str, where: str) -> None:
    if not text.isprintable():
        raise ConfigError(f"{where} must be one line of printable characters, got {text!r}")


def _flatten_axes(table: Any, where: str, prefix: str = "") -> list[_Lazy]:
    """``a.b = [...]`` (a nested table in TOML) as axis ``a.b``; a table with ``range``
    is a value specification, not a deeper key."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table, got {table!r}")
    axes = []
    for key, spec in table.items():
        dotted = f"{prefix}{key}"
        if not dotted.isprintable():
            raise ConfigError(f"{where}: axis {dotted!r}: a key must be one printable line")
        if isinstance(spec, dict) and "range" not in spec:
            axes += _flatten_axes(spec, where, f"{dotted}.")
        else:
            axes.append(_Lazy(dotted, _axis_values(dotted, spec, where), where))
    return axes


def load_campaign(name_or_path: str | Path) -> Campaign:
    """Read and check a campaign file (a shipped name or a path); a mistake is one line
    (a name or key holding a line break is shown escaped)."""
    try:
        path = _resolve(str(name_or_path))
        data = load_toml(path, "campaign file")  # regular file, size and depth capped
    except (ConfigError, UserError) as exc:
        raise type(exc)(printable(str(exc))) from None
    try:
        return _campaign_from_dict(data, path)
    except ConfigError as exc:
        raise ConfigError(printable(f"{path}: {exc}")) from None


def _campaign_from_dict(data: dict[str, Any], path: Path) -> Campaign:
    unknown = sorted(set(data) - {"campaign", "axes", "zip"})
    if unknown:
        raise ConfigError(f"unknown table [{unknown[0]}] (known: campaign, axes, zip)")
    if not isinstance(data.get("campaign"), dict):
        raise ConfigError("missing [campaign] table (name, scenarios, criteria, ...)")
    head = data["campaign"]
    for key in ("name", "scenarios"):
        if key not in head:
            raise ConfigError(f"missing key campaign.{key}")
    if isinstance(head.get("scenarios"), str):
        head = {**head, "scenarios": [head["scenarios"]]}
    header = from_dict(_Header, head, "campaign")
    if not header.name.strip():
        raise ConfigError("campaign.name must be a non-empty string")
    _one_line(header.name, "campaign.name")
    if not header.scenarios:
        raise ConfigError("campaign.scenarios: at least one scenario")
    for name in header.scenarios:
        _one_line(name, f"campaign.scenarios: {name!r}")
    if header.duration_s is not None:  # as ``hdhil run --duration``: (0 s, one year]
        check_number(header.duration_s, "campaign.duration_s", lo=0.0, lo_open=True,
                     hi=MAX_SECONDS)  # fmt: skip
    if header.trace_format not in _TRACE_FORMATS:
        raise ConfigError(
            f"campaign.trace_format must be one of {', '.join(_TRACE_FORMATS)}, "
            f"got {header.trace_format!r}"
        )
    scenarios = []
    for name in header.scenarios:
        looks_like_path = name.endswith(".toml") or "/" in name or "\\" in name
        scenarios.append(str(path.parent / name) if looks_like_path else name)
    criteria = tuple(Criterion.parse(c, "campaign.criteria") for c in header.criteria)
    for name in header.plots:
        if metric_kind(name) is None:
            raise ConfigError(f"campaign.plots: unknown metric {name!r} ({known_metrics()})")
    lazy_axes = _flatten_axes(data.get("axes", {}), "axes")
    zips_data = data.get("zip", [])
    if not isinstance(zips_data, list):
        raise ConfigError("zip: expected [[zip]] tables (each a group of axes of equal length)")
    zips = []
    for i, group in enumerate(zips_data):
        members = tuple(_flatten_axes(group, f"zip[{i}]"))
        if not members:
            raise ConfigError(f"zip[{i}]: no axes")
        lengths = {_count(a.values) for a in members}
        if len(lengths) != 1:
            sizes = ", ".join(f"{a.key} {_count(a.values)}" for a in members)
            raise ConfigError(f"zip[{i}]: zipped axes need equal lengths ({sizes})")
        zips.append(members)
    keys = [a.key for a in lazy_axes] + [a.key for g in zips for a in g]
    for key in keys:
        if keys.count(key) > 1:
            raise ConfigError(f"axis {key} is given twice")
        if key in ("scenario", "variant") or key.split(".")[0] not in (
            "seed",
            "scenario",
            "plant",
            "firmware",
            "faults",
            "joints",
        ):
            raise ConfigError(
                f"axis {key}: not a scenario key (seed, scenario.*, plant.*, firmware.*, "
                "faults.*, joints.NAME.*)"
            )
        if key.startswith("joints.") and len(key.split(".")) < 3:
            raise ConfigError(
                f"axis {key}: a joint's key is joints.NAME.KEY (e.g. "
                "joints.J3.firmware.control.torque_limit_Nm), NAME a joint of the scenario"
            )
    _check_size(scenarios, lazy_axes, zips)
    axes = tuple(a.build() for a in lazy_axes)
    return Campaign(
        name=header.name,
        source=str(path),
        scenarios=tuple(scenarios),
        description=header.description,
        duration_s=header.duration_s,
        keep_trace=header.keep_trace,
        trace_format=header.trace_format,
        criteria=criteria,
        plots=tuple(header.plots),
        axes=axes,
        zips=tuple(tuple(a.build() for a in group) for group in zips),
    )


def _check_size(scenarios: list[str], axes: list[_Lazy], zips: list[tuple[_Lazy, ...]]) -> None:
    """Refuse a grid of more than :data:`MAX_VARIANTS` variants, counted from the axes'
    lengths (nothing built)."""
    n = len(scenarios)
    factors = [f"{n} scenario{'s' if n != 1 else ''}"]
    total = n
    for a in axes:
        total *= _count(a.values)
        factors.append(f"{a.key} {_count(a.values)}")
    for i, group in enumerate(zips):
        total *= _count(group[0].values)
        factors.append(f"zip[{i}] {_count(group[0].values)}")
    if total > MAX_VARIANTS:
        raise ConfigError(
            f"the grid gives {total} variants ({' x '.join(factors)}): more than "
            f"{MAX_VARIANTS}, the most a campaign may have; split it into several files"
        )
