"""Campaigns: one firmware against a grid of scenario variants, run in parallel, each
given a verdict.

A campaign file (TOML; ``docs/campaigns.md``) names base scenarios, axes over any
scenario key (crossed, or zipped in groups), criteria over the metrics of a run
(:data:`METRICS`) and what to keep. Every variant is resolved as ``hdhil run`` resolves
its options and validated before anything runs. A variant is recognised by a digest of
its full settings and the hdhil version; its record is stored as
``DIR/runs/<digest>.json`` the moment it arrives, so an interrupted campaign keeps what
finished and a re-run only runs what has no result yet.

Execution goes through a :class:`concurrent.futures.Executor`: a local process pool or
a Dask cluster (``distributed.Client.get_executor()``), so both share this code. A
variant that raises is recorded with its error and never stops the campaign; a variant
whose worker was lost is submitted again.
"""

from __future__ import annotations

import concurrent.futures as cf
import gc
import hashlib
import itertools
import json
import math
import multiprocessing
import os
import re
import socket
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from importlib import metadata, resources
from pathlib import Path
from typing import Any

from hdhil.can.traces.sidecar import metadata_path
from hdhil.core.dataconf import ConfigError, from_dict, merge
from hdhil.core.files import load_toml
from hdhil.core.signals import leave_interrupt_to_parent
from hdhil.rig.scenario import load_scenario, scenario_data, scenario_from_dict
from hdhil.rig.variant import WALL_CLOCK_KEYS, RunSettings, run_settings

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover - exercised on Python 3.10 only
    pass

__all__ = [
    "METRICS",
    "Campaign",
    "CampaignRun",
    "Criterion",
    "Variant",
    "execute_variant",
    "expand",
    "list_campaigns",
    "load_campaign",
    "run_campaign",
]

# ----------------------------------------------------------------------------- metrics


def _get(path: str) -> Callable[[dict[str, Any]], Any]:
    keys = path.split(".")

    def get(result: dict[str, Any]) -> Any:
        value: Any = result
        for key in keys:
            if not isinstance(value, dict) or value.get(key) is None:
                return None
            value = value[key]
        return value

    return get


def _candidate(prefix: str, field_name: str) -> Callable[[dict], Any]:
    """A figure of the evaluation's row whose name starts with ``prefix``."""

    def get(result: dict[str, Any]) -> Any:
        for row in (result.get("evaluation") or {}).get("candidates") or ():
            if str(row.get("name", "")).startswith(prefix):
                return row.get(field_name)
        return None

    return get


def _firmware_candidate(field_name: str, sub: str | None = None) -> Callable[[dict], Any]:
    """A figure of the evaluation's firmware row (the filter the firmware ran)."""

    def get(result: dict[str, Any]) -> Any:
        evaluation = result.get("evaluation") or {}
        for row in evaluation.get("candidates") or ():
            if str(row.get("name", "")).startswith("firmware"):
                value = row.get(field_name)
                if sub is not None:
                    value = (value or {}).get(sub)
                return value
        return None

    return get


def _total_faults(result: dict[str, Any]) -> int | None:
    faults = result.get("faults")
    return None if faults is None else int(sum(faults.values()))


def _malformed(result: dict[str, Any]) -> int:
    return int(result["controller"].get("malformed_frames", 0)) + int(
        result["drive"].get("malformed_frames", 0)
    )


@dataclass(frozen=True)
class Metric:
    """A figure of a run: where it comes from in ``hdhil run --json`` and its kind."""

    source: str
    kind: str  # "float", "int" or "bool"
    get: Callable[[dict[str, Any]], Any]


#: Every metric a criterion or a plot can name, each read from the ``hdhil run --json``
#: result of the variant (``source``).  ``stopped_early`` compares the samples handled
#: with the samples the variant asked for.
METRICS: dict[str, Metric] = {
    "stopped_early": Metric("cycles < duration / sample period", "bool", lambda r: None),
    "simulated_s": Metric("simulated_s", "float", _get("simulated_s")),
    "cycles": Metric("cycles", "int", _get("cycles")),
    "headline_Nm": Metric("headline.value_Nm", "float", _get("headline.value_Nm")),
    "filtered_rms_err_Nm": Metric(
        "evaluation.candidates[firmware].rms_error (from the evaluation start)",
        "float",
        _firmware_candidate("rms_error"),
    ),
    "filtered_to_raw": Metric(
        "evaluation.candidates[firmware].rms_ratio", "float", _firmware_candidate("rms_ratio")
    ),
    "raw_rms_err_Nm": Metric(
        "evaluation.candidates[raw].rms_error (from the evaluation start)",
        "float",
        _candidate("raw", "rms_error"),
    ),
    "filtered_rms_err_whole_run_Nm": Metric(
        "torque.rms_error_filtered (whole run)", "float", _get("torque.rms_error_filtered")
    ),
    "filtered_max_err_whole_run_Nm": Metric(
        "torque.max_error_filtered (whole run)", "float", _get("torque.max_error_filtered")
    ),
    "raw_rms_err_whole_run_Nm": Metric(
        "torque.rms_error_raw (whole run)", "float", _get("torque.rms_error_raw")
    ),
    "true_rms_whole_run_Nm": Metric(
        "torque.rms_true (whole run)", "float", _get("torque.rms_true")
    ),
    "eval_rms_err_Nm": Metric(
        "evaluation.candidates[firmware].rms_error", "float", _firmware_candidate("rms_error")
    ),
    "eval_reduction_2x_dB": Metric(
        "evaluation.candidates[firmware].reduction_dB['2x motor']",
        "float",
        _firmware_candidate("reduction_dB", "2x motor"),
    ),
    "eval_reduction_4x_dB": Metric(
        "evaluation.candidates[firmware].reduction_dB['4x motor']",
        "float",
        _firmware_candidate("reduction_dB", "4x motor"),
    ),
    "max_abs_e_Nm": Metric("tracking.max_abs_error", "float", _get("tracking.max_abs_error")),
    "rms_e_Nm": Metric("tracking.rms_error", "float", _get("tracking.rms_error")),
    "velocity_final_radps": Metric("velocity_final", "float", _get("velocity_final")),
    "velocity_peak_radps": Metric("velocity_peak", "float", _get("velocity_peak")),
    "frames_total": Metric("frames_total", "int", _get("frames_total")),
    "faults_injected": Metric("sum of faults", "int", _total_faults),
    "malformed_frames": Metric(
        "controller.malformed_frames + drive.malformed_frames", "int", _malformed
    ),
    "kalman_skipped": Metric("controller.kalman_skipped", "int", _get("controller.kalman_skipped")),
    "tacho_rejections": Metric(
        "controller.tacho_rejections", "int", _get("controller.tacho_rejections")
    ),
    "encoder_rejections": Metric(
        "controller.encoder_rejections", "int", _get("controller.encoder_rejections")
    ),
    "plausibility_errors": Metric(
        "controller.plausibility_errors", "int", _get("controller.plausibility_errors")
    ),
    "covariance_resets": Metric(
        "controller.covariance_resets", "int", _get("controller.covariance_resets")
    ),
    "covariance_finite": Metric(
        "controller.covariance_finite", "bool", _get("controller.covariance_finite")
    ),
}


def metrics_of(result: dict[str, Any], planned_cycles: int) -> dict[str, Any]:
    """Every metric of :data:`METRICS` for one run's result (None: not reported)."""
    out = {name: m.get(result) for name, m in METRICS.items()}
    out["stopped_early"] = int(result["cycles"]) < planned_cycles
    return out


def stop_reason(result: dict[str, Any], planned_cycles: int) -> str:
    """Why a run ended before its duration, in words (the run's own reason when it
    reports one)."""
    ts = float(result.get("sample_period_s", 1e-3))
    text = (
        f"stopped early at {int(result['cycles']) * ts:g} s of {planned_cycles * ts:g} s "
        f"({result['cycles']} of {planned_cycles} samples)"
    )
    verdict = result.get("verdict")  # the run's own account of an early stop
    if isinstance(verdict, dict) and verdict.get("reason"):
        by = f" by node {verdict['node']}" if verdict.get("node") is not None else ""
        text += f"{by}: {verdict['reason']}"
        for key, label in (("emcy_sent", "EMCY sent"), ("emcy_received", "EMCY received")):
            emcy = verdict.get(key)
            if isinstance(emcy, dict) and emcy.get("code"):
                text += f"; {label} {emcy['code']} {emcy.get('text', '')}".rstrip()
    return text


# ----------------------------------------------------------------------------- criteria

_CRITERION = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|==|!=|<|>)\s*(\S.*?)\s*$")
_OPS: dict[str, Callable[[Any, Any], bool]] = {
    "<": lambda a, b: a < b,
    "<=": lambda a, b: a <= b,
    ">": lambda a, b: a > b,
    ">=": lambda a, b: a >= b,
    "==": lambda a, b: a == b,
    "!=": lambda a, b: a != b,
}


@dataclass(frozen=True)
class Criterion:
    """``METRIC OP VALUE``: a variant passes when its metric compares true."""

    text: str
    metric: str
    op: str
    value: float | bool

    @classmethod
    def parse(cls, text: Any, where: str = "criteria") -> Criterion:
        if not isinstance(text, str):
            raise ConfigError(f"{where}: expected a string 'METRIC OP VALUE', got {text!r}")
        m = _CRITERION.match(text)
        if m is None:
            raise ConfigError(
                f"{where}: {text!r} is not 'METRIC OP VALUE' (OP one of < <= > >= == !=)"
            )
        metric, op, raw = m.groups()
        if metric not in METRICS:
            raise ConfigError(
                f"{where}: unknown metric {metric!r} in {text!r} (known: {', '.join(METRICS)})"
            )
        kind = METRICS[metric].kind
        value: float | bool
        if raw in ("true", "false"):
            if kind != "bool" or op not in ("==", "!="):
                raise ConfigError(f"{where}: {text!r}: {metric} is a number, not true/false")
            value = raw == "true"
        else:
            try:
                value = float(raw)
            except ValueError:
                raise ConfigError(f"{where}: {text!r}: {raw!r} is not a number") from None
            if kind == "bool":
                raise ConfigError(f"{where}: {text!r}: {metric} is true or false")
            if not math.isfinite(value):
                raise ConfigError(f"{where}: {text!r}: the threshold must be finite")
        return cls(" ".join((metric, op, raw)), metric, op, value)

    def check(self, metrics: dict[str, Any]) -> tuple[bool, str]:
        """(passed, reason if not)."""
        actual = metrics.get(self.metric)
        if actual is None:
            return False, f"{self.metric} not reported"
        if isinstance(actual, float) and math.isnan(actual):
            return False, f"{self.metric} is NaN"
        if _OPS[self.op](actual, self.value):
            return True, ""
        return False, f"{self.metric} = {_fmt(actual)}, not {self.op} {_fmt(self.value)}"

    def badness(self, metrics: dict[str, Any]) -> float:
        """How far the metric is on the failing side (larger is worse), for ranking."""
        actual = metrics.get(self.metric)
        if actual is None or (isinstance(actual, float) and math.isnan(actual)):
            return math.inf
        if isinstance(self.value, bool) or self.op in ("==", "!="):
            return 0.0 if self.check(metrics)[0] else 1.0
        return (
            float(actual) - float(self.value)
            if self.op in ("<", "<=")
            else float(self.value) - float(actual)
        )


def _fmt(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


# ----------------------------------------------------------------------------- the file


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
        return [n for i, n in enumerate(names) if n not in names[:i] and METRICS[n].kind != "bool"]


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
    text = str(name_or_path)
    if not (text.endswith(".toml") or "/" in text or "\\" in text):
        path = _campaign_dir() / f"{text}.toml"
        if path.is_file():
            return path
        known = ", ".join(list_campaigns()) or "none"
        raise ConfigError(
            f"unknown campaign {text!r} (known: {known}; or give a path to a .toml file)"
        )
    path = Path(text)
    if not path.is_file():
        raise ConfigError(f"campaign file not found: {text}")
    return path


def _axis_values(key: str, spec: Any, where: str) -> tuple[Any, ...]:
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
        values: tuple[Any, ...] = tuple(range(*bounds))
    elif isinstance(spec, list):
        values = tuple(spec)
    else:
        raise ConfigError(f"{where}.{key}: expected a list of values, got {spec!r}")
    if not values:
        raise ConfigError(f"{where}.{key}: no values")
    return values


def _flatten_axes(table: Any, where: str, prefix: str = "") -> list[Axis]:
    """``a.b = [...]`` (a nested table in TOML) as axis ``a.b``; a table with ``range``
    is a value specification, not a deeper key."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table, got {table!r}")
    axes = []
    for key, spec in table.items():
        dotted = f"{prefix}{key}"
        if isinstance(spec, dict) and "range" not in spec:
            axes += _flatten_axes(spec, where, f"{dotted}.")
        else:
            axes.append(Axis(dotted, _axis_values(dotted, spec, where)))
    return axes


def load_campaign(name_or_path: str | Path) -> Campaign:
    """Read and check a campaign file (a shipped name or a path)."""
    path = _resolve(str(name_or_path))
    data = load_toml(path, "campaign file")  # regular file, size and depth capped
    try:
        return _campaign_from_dict(data, path)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


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
    if not header.scenarios:
        raise ConfigError("campaign.scenarios: at least one scenario")
    if header.duration_s is not None and not (
        math.isfinite(header.duration_s) and header.duration_s > 0
    ):
        raise ConfigError(f"campaign.duration_s must be > 0 and finite, got {header.duration_s}")
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
        if name not in METRICS:
            raise ConfigError(
                f"campaign.plots: unknown metric {name!r} (known: {', '.join(METRICS)})"
            )
    axes = tuple(_flatten_axes(data.get("axes", {}), "axes"))
    zips_data = data.get("zip", [])
    if not isinstance(zips_data, list):
        raise ConfigError("zip: expected [[zip]] tables (each a group of axes of equal length)")
    zips = []
    for i, group in enumerate(zips_data):
        members = tuple(_flatten_axes(group, f"zip[{i}]"))
        if not members:
            raise ConfigError(f"zip[{i}]: no axes")
        lengths = {len(a.values) for a in members}
        if len(lengths) != 1:
            sizes = ", ".join(f"{a.key} {len(a.values)}" for a in members)
            raise ConfigError(f"zip[{i}]: zipped axes need equal lengths ({sizes})")
        zips.append(members)
    keys = [a.key for a in axes] + [a.key for g in zips for a in g]
    for key in keys:
        if keys.count(key) > 1:
            raise ConfigError(f"axis {key} is given twice")
        if key in ("scenario", "variant") or key.split(".")[0] not in (
            "seed",
            "scenario",
            "plant",
            "firmware",
            "faults",
        ):
            raise ConfigError(
                f"axis {key}: not a scenario key (seed, scenario.*, plant.*, firmware.*, faults.*)"
            )
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
        zips=tuple(zips),
    )


# ----------------------------------------------------------------------------- variants


@dataclass(frozen=True)
class Variant:
    """One point of the grid, resolved and validated."""

    id: str
    scenario: str
    values: dict[str, Any]
    settings: RunSettings
    planned_cycles: int
    digest: str

    @property
    def seed(self) -> int:
        seed = self.settings.seed
        return int(self.settings.scenario["scenario"]["seed"]) if seed is None else seed


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
    suffix = f".{campaign.trace_format}" if campaign.keep_trace else None
    for base in campaign.scenarios:
        for point in points:
            overrides: dict[str, Any] = {}
            for key, value in point.items():
                if key != "seed":
                    overrides = merge(overrides, _nested(key, value))
            vid = f"{len(variants) + 1:0{width}d}"
            where = (
                f"variant {vid} ({base}"
                + "".join(f", {k}={_fmt(v)}" for k, v in point.items())
                + ")"
            )
            try:
                scenario = load_scenario(base, overrides or None)
                fw = scenario.firmware
                seed = point.get("seed")
                if seed is not None and (
                    isinstance(seed, bool) or not isinstance(seed, int) or seed < 0
                ):
                    raise ConfigError(f"seed must be an integer >= 0, got {seed!r}")
            except ConfigError as exc:
                raise ConfigError(f"{where}: {exc}") from None
            data = scenario_data(scenario)
            if scenario_from_dict(data) != scenario:  # pragma: no cover - a to_dict gap
                raise ConfigError(f"{where}: the scenario does not survive its plain-data form")
            duration = scenario.duration_s if campaign.duration_s is None else campaign.duration_s
            planned = round(duration / fw.sample_period_s)
            if fw.num_samples:
                planned = min(planned, fw.num_samples)
            settings = RunSettings(data, campaign.duration_s, seed, suffix)
            digest = digest_of(settings)
            if digest in seen:
                raise ConfigError(f"{where}: same settings as variant {seen[digest]}")
            seen[digest] = vid
            variants.append(Variant(vid, base, dict(point), settings, planned, digest))
    return variants


# ----------------------------------------------------------------------------- execution


def _worker_init() -> None:
    """Start of a local pool worker: leave Ctrl-C to the campaign (it cancels and keeps
    results), and move the objects inherited from the parent out of the garbage
    collector's reach (a forked worker would otherwise traverse, and so copy, the
    parent's whole heap at every full collection)."""
    leave_interrupt_to_parent()
    gc.freeze()


def execute_variant(settings: RunSettings) -> dict[str, Any]:
    """Run one variant where the executor put it; never raises for the run's own errors
    (they come back as ``error``)."""
    t0 = time.perf_counter()
    result: dict[str, Any] | None = None
    trace: bytes | None = None
    sidecar: bytes | None = None
    error = None
    try:
        if settings.trace_suffix and multiprocessing.current_process().daemon:
            raise RuntimeError(
                "the trace writer cannot start its process in a daemonic worker (Dask: "
                "start the workers with DASK_DISTRIBUTED__WORKER__DAEMON=False)"
            )
        result, trace, sidecar = run_settings(settings)
        result = {k: v for k, v in result.items() if k not in WALL_CLOCK_KEYS}
    except Exception as exc:  # a variant's failure is data, not the campaign's
        error = f"{type(exc).__name__}: {exc}".splitlines()[0]
    return {
        "result": result,
        "error": error,
        "trace": trace,
        "sidecar": sidecar,
        "wall_s": time.perf_counter() - t0,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }


def local_executor(workers: int) -> cf.Executor:
    """A process pool of ``workers`` processes (forked where the platform can: they
    start with hdhil already imported)."""
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init)


#: Submissions of one variant whose worker was lost before it is recorded as an error.
MAX_ATTEMPTS = 3


@dataclass
class Record:
    """A variant's outcome as the campaign keeps it."""

    variant: Variant
    result: dict[str, Any] | None
    error: str | None
    wall_s: float
    worker: str
    resumed: bool = False
    metrics: dict[str, Any] = field(default_factory=dict)
    verdicts: dict[str, bool] = field(default_factory=dict)
    reasons: list[str] = field(default_factory=list)

    @property
    def status(self) -> str:
        if self.error is not None:
            return "error"
        return "pass" if all(self.verdicts.values()) else "fail"


def judge(variant: Variant, result: dict | None, error: str | None,
          criteria: Iterable[Criterion]) -> tuple[dict, dict, list[str]]:  # fmt: skip
    """Metrics, verdict per criterion and the reasons of a variant's outcome."""
    if result is None:
        return {}, {c.text: False for c in criteria}, [error or "no result"]
    metrics = metrics_of(result, variant.planned_cycles)
    verdicts: dict[str, bool] = {}
    reasons: list[str] = []
    if metrics["stopped_early"]:
        reasons.append(stop_reason(result, variant.planned_cycles))
    for c in criteria:
        ok, why = c.check(metrics)
        verdicts[c.text] = ok
        if not ok:
            reasons.append(why)
    return metrics, verdicts, reasons


@dataclass
class CampaignRun:
    """What :func:`run_campaign` did."""

    records: dict[str, Record]
    ran: int
    resumed: int
    interrupted: bool
    lost: int
    wall_s: float


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all; only a regular file is ever replaced."""
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise ConfigError(f"{path} exists and is not a regular file: not overwriting it")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _load_stored(path: Path, variant: Variant) -> dict[str, Any] | None:
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None  # damaged or half-written elsewhere: run the variant again
    if not isinstance(stored, dict) or stored.get("digest") != variant.digest:
        return None
    return stored


def run_campaign(
    campaign: Campaign,
    variants: list[Variant],
    out: Path,
    make_executor: Callable[[], cf.Executor],
    on_record: Callable[[Record], None] | None = None,
    lost_errors: tuple[type[BaseException], ...] = (),
) -> CampaignRun:
    """Run every variant without a stored record through executors from
    ``make_executor``; store each record as it arrives (``DIR/runs/<digest>.json``).

    ``lost_errors``: exception types a future raises when its worker is gone (besides a
    broken local pool); such a variant is submitted again, up to :data:`MAX_ATTEMPTS`
    times, then recorded as an error for this invocation only (not stored, so a re-run
    retries it).  Ctrl-C cancels what has not started and returns with ``interrupted``.
    """
    t0 = time.perf_counter()
    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    trace_dir = out / "traces"
    records: dict[str, Record] = {}
    todo: list[Variant] = []
    for v in variants:
        stored = _load_stored(runs_dir / f"{v.digest}.json", v)
        if (
            stored is None
            or stored.get("error") is not None  # may come from the worker's environment
            or (campaign.keep_trace and not _trace_path(trace_dir, v).is_file())
        ):
            todo.append(v)
            continue
        rec = Record(v, stored.get("result"), stored.get("error"), float(stored["wall_s"]),
                     str(stored.get("worker", "")), resumed=True)  # fmt: skip
        rec.metrics, rec.verdicts, rec.reasons = judge(v, rec.result, rec.error, campaign.criteria)
        records[v.id] = rec
        if on_record is not None:
            on_record(rec)
    resumed = len(records)

    def finish(v: Variant, outcome: dict[str, Any], store: bool) -> None:
        if outcome.get("trace") is not None:
            trace_dir.mkdir(exist_ok=True)
            _write_atomic(_trace_path(trace_dir, v), outcome["trace"])
            if outcome.get("sidecar") is not None:
                _write_atomic(metadata_path(_trace_path(trace_dir, v)), outcome["sidecar"])
        rec = Record(v, outcome["result"], outcome["error"], outcome["wall_s"], outcome["worker"])
        rec.metrics, rec.verdicts, rec.reasons = judge(v, rec.result, rec.error, campaign.criteria)
        if store:
            stored = {
                "digest": v.digest,
                "variant": v.id,
                "settings": {
                    "scenario": v.settings.scenario,
                    "duration_s": v.settings.duration_s,
                    "seed": v.settings.seed,
                    "trace": v.settings.trace_suffix,
                },
                "result": rec.result,
                "error": rec.error,
                "wall_s": rec.wall_s,
                "worker": rec.worker,
            }
            _write_atomic(runs_dir / f"{v.digest}.json", json.dumps(stored, indent=1).encode())
        records[v.id] = rec
        if on_record is not None:
            on_record(rec)

    lost_types = (cf.BrokenExecutor, *lost_errors)
    attempts: dict[str, int] = {}
    interrupted = False
    lost = 0
    remaining = todo
    while remaining and not interrupted:
        retry: list[Variant] = []
        executor = make_executor()
        futures: dict[cf.Future, Variant] = {}
        try:
            futures = {executor.submit(execute_variant, v.settings): v for v in remaining}
            for fut in cf.as_completed(futures):
                v = futures[fut]
                try:
                    outcome = fut.result()
                except lost_types as exc:
                    lost += 1
                    attempts[v.id] = attempts.get(v.id, 0) + 1
                    if attempts[v.id] < MAX_ATTEMPTS:
                        retry.append(v)
                        continue
                    why = f"worker lost {attempts[v.id]} times ({type(exc).__name__}: {exc})"
                    finish(v, _failed(why.splitlines()[0]), store=False)
                    continue
                except cf.CancelledError:
                    continue
                if outcome["result"] is not None and outcome["result"].get("interrupted"):
                    retry.append(v)  # a worker stopped mid-run: its partial result is no result
                    continue
                finish(v, outcome, store=True)
        except KeyboardInterrupt:
            interrupted = True
            for fut in futures:
                fut.cancel()
        finally:
            # Dask's executor takes no cancel_futures; what is left was cancelled above.
            executor.shutdown(wait=not interrupted)
        remaining = retry
    return CampaignRun(records, len(records) - resumed, resumed, interrupted, lost,
                       time.perf_counter() - t0)  # fmt: skip


def _failed(error: str) -> dict[str, Any]:
    return {"result": None, "error": error, "trace": None, "wall_s": 0.0, "worker": ""}


def _trace_path(trace_dir: Path, v: Variant) -> Path:
    return trace_dir / f"{v.id}-{v.digest}{v.settings.trace_suffix}"
