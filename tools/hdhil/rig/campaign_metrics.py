"""What a campaign judges a variant by: the metrics of a run and the criteria over them.

:data:`METRICS` names every figure a criterion or a plot can use, each read from the
variant's ``hdhil run --json`` result (:func:`metrics_of`). A :class:`Criterion` is
``METRIC OP VALUE``, parsed and checked against the metric's kind when the campaign file
is loaded; :func:`judge` gives a variant's metrics, its verdict per criterion and the
reasons it failed (a run that stopped before its duration says why: :func:`stop_reason`).
The campaign file (:mod:`hdhil.rig.campaign_file`), the execution
(:mod:`hdhil.rig.campaign`) and the report (:mod:`hdhil.rig.campaign_report`) share them.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hdhil.core.dataconf import ConfigError
from hdhil.rig.headline import candidate_row

if TYPE_CHECKING:
    from hdhil.rig.campaign_variants import Variant

__all__ = [
    "JOINT_METRICS",
    "METRICS",
    "METRIC_WORDS",
    "Criterion",
    "JointMetric",
    "Metric",
    "format_value",
    "joint_columns",
    "joint_metrics_of",
    "judge",
    "known_metrics",
    "metric_kind",
    "metric_words",
    "metrics_of",
    "split_joint_metric",
    "stop_reason",
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


def _candidate(prefix: str, field_name: str, sub: str | None = None) -> Callable[[dict], Any]:
    """A figure of the evaluation's row whose name starts with ``prefix``."""

    def get(result: dict[str, Any]) -> Any:
        row = candidate_row(result.get("evaluation"), prefix)
        value = None if row is None else row.get(field_name)
        return (value or {}).get(sub) if sub is not None else value

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

    @classmethod
    def at(cls, path: str, kind: str, note: str = "") -> Metric:
        """The figure at the dotted ``path`` of the result (``note`` qualifies the source)."""
        return cls(f"{path} {note}".rstrip(), kind, _get(path))


#: Every metric a criterion or a plot can name, each read from the ``hdhil run --json``
#: result of the variant (``source``).  ``stopped_early`` compares the samples handled
#: with the samples the variant asked for.
METRICS: dict[str, Metric] = {
    "stopped_early": Metric("cycles < duration / sample period", "bool", lambda r: None),
    "simulated_s": Metric.at("simulated_s", "float"),
    "cycles": Metric.at("cycles", "int"),
    "headline_Nm": Metric.at("headline.value_Nm", "float"),
    "filtered_rms_err_Nm": Metric(
        "evaluation.candidates[firmware].rms_error (from the evaluation start)",
        "float",
        _candidate("firmware", "rms_error"),
    ),
    "filtered_to_raw": Metric(
        "evaluation.candidates[firmware].rms_ratio", "float", _candidate("firmware", "rms_ratio")
    ),
    "raw_rms_err_Nm": Metric(
        "evaluation.candidates[raw].rms_error (from the evaluation start)",
        "float",
        _candidate("raw", "rms_error"),
    ),
    "filtered_rms_err_whole_run_Nm": Metric.at("torque.rms_error_filtered", "float", "(whole run)"),
    "filtered_max_err_whole_run_Nm": Metric.at("torque.max_error_filtered", "float", "(whole run)"),
    "raw_rms_err_whole_run_Nm": Metric.at("torque.rms_error_raw", "float", "(whole run)"),
    "true_rms_whole_run_Nm": Metric.at("torque.rms_true", "float", "(whole run)"),
    "eval_rms_err_Nm": Metric(
        "evaluation.candidates[firmware].rms_error", "float", _candidate("firmware", "rms_error")
    ),
    "eval_reduction_2x_dB": Metric(
        "evaluation.candidates[firmware].reduction_dB['2x motor']",
        "float",
        _candidate("firmware", "reduction_dB", "2x motor"),
    ),
    "eval_reduction_4x_dB": Metric(
        "evaluation.candidates[firmware].reduction_dB['4x motor']",
        "float",
        _candidate("firmware", "reduction_dB", "4x motor"),
    ),
    "max_abs_e_Nm": Metric.at("tracking.max_abs_error", "float"),
    "rms_e_Nm": Metric.at("tracking.rms_error", "float"),
    "velocity_final_radps": Metric.at("velocity_final", "float"),
    "velocity_peak_radps": Metric.at("velocity_peak", "float"),
    "frames_total": Metric.at("frames_total", "int"),
    "faults_injected": Metric("sum of faults", "int", _total_faults),
    "malformed_frames": Metric(
        "controller.malformed_frames + drive.malformed_frames", "int", _malformed
    ),
    "kalman_skipped": Metric.at("controller.kalman_skipped", "int"),
    "tacho_rejections": Metric.at("controller.tacho_rejections", "int"),
    "encoder_rejections": Metric.at("controller.encoder_rejections", "int"),
    "plausibility_errors": Metric.at("controller.plausibility_errors", "int"),
    "covariance_resets": Metric.at("controller.covariance_resets", "int"),
    "covariance_finite": Metric.at("controller.covariance_finite", "bool"),
}


#: Every metric in words, for the campaign plots' axes (the unit comes from the name's
#: suffix, :func:`hdhil.core.plotlabels.split_unit`).
METRIC_WORDS: dict[str, str] = {
    "stopped_early": "stopped early",
    "simulated_s": "simulated time",
    "cycles": "control cycles",
    "headline_Nm": "headline torque error",
    "filtered_rms_err_Nm": "RMS error of the filtered torque",
    "filtered_to_raw": "RMS error, filtered relative to raw",
    "raw_rms_err_Nm": "RMS error of the raw torque",
    "filtered_rms_err_whole_run_Nm": "RMS error of the filtered torque, whole run",
    "filtered_max_err_whole_run_Nm": "max error of the filtered torque, whole run",
    "raw_rms_err_whole_run_Nm": "RMS error of the raw torque, whole run",
    "true_rms_whole_run_Nm": "RMS of the true torque, whole run",
    "eval_rms_err_Nm": "RMS error of the filtered torque",
    "eval_reduction_2x_dB": "reduction of the 2x motor ripple",
    "eval_reduction_4x_dB": "reduction of the 4x motor ripple",
    "max_abs_e_Nm": "max tracking error |e|",
    "rms_e_Nm": "RMS tracking error e",
    "velocity_final_radps": "final velocity",
    "velocity_peak_radps": "peak velocity",
    "frames_total": "CAN frames",
    "faults_injected": "faults injected",
    "malformed_frames": "malformed frames",
    "kalman_skipped": "Kalman updates skipped",
    "tacho_rejections": "tachometer samples rejected",
    "encoder_rejections": "encoder samples rejected",
    "plausibility_errors": "plausibility errors",
    "covariance_resets": "covariance resets",
    "covariance_finite": "covariance finite",
}


@dataclass(frozen=True)
class JointMetric:
    """A figure of one joint of a rig: where it comes from in the joint's entry of
    ``hdhil run --json``'s ``joints``, its kind, its words and which way is worse
    (``max``: the largest value is the worst joint's; ``min``: the smallest)."""

    source: str
    kind: str
    words: str
    worse: str = "max"

    def get(self, joint: dict[str, Any]) -> Any:
        return _get(self.source)(joint)


#: Every figure a rig reports per joint (``hdhil run --json`` of a scenario with
#: ``[joints]``: its ``joints`` list). A campaign names joint ``J3``'s as
#: ``joints.J3.METRIC`` and the worst joint's as ``worst.METRIC`` (:func:`metric_kind`).
JOINT_METRICS: dict[str, JointMetric] = {
    "samples": JointMetric("samples", "int", "control cycles", "min"),
    "filtered_rms_err_Nm": JointMetric("torque.rms_error_filtered", "float", "filtered RMS error"),
    "filtered_max_err_Nm": JointMetric("torque.max_error_filtered", "float", "filtered max error"),
    "raw_rms_err_Nm": JointMetric("torque.rms_error_raw", "float", "raw RMS error"),
    "true_rms_Nm": JointMetric("torque.rms_true", "float", "RMS of the true torque"),
    "filtered_to_raw": JointMetric("torque.filtered_to_raw", "float", "RMS error, filtered / raw"),
    "max_abs_e_Nm": JointMetric("tracking.max_abs_error", "float", "max |e|"),
    "rms_e_Nm": JointMetric("tracking.rms_error", "float", "RMS e"),
    "rms_e_measured_Nm": JointMetric(
        "tracking.rms_error_measured", "float", "RMS e on the measured torque"
    ),
    "share_within_goal_measured": JointMetric(
        "tracking.share_within_goal_measured", "float", "share of |e| ≤ 0.5 N·m", "min"
    ),
}

#: The prefixes of a joint's metric and of the worst joint's.
JOINT_PREFIX = "joints."
WORST_PREFIX = "worst."


def split_joint_metric(name: str) -> tuple[str | None, str] | None:
    """``joints.J3.rms_e_Nm`` as ``("J3", "rms_e_Nm")``, ``worst.rms_e_Nm`` as
    ``(None, "rms_e_Nm")``; None for any other name (a metric of :data:`METRICS`, or
    not a metric)."""
    if name.startswith(WORST_PREFIX):
        metric = name[len(WORST_PREFIX) :]
        return (None, metric) if metric in JOINT_METRICS else None
    if name.startswith(JOINT_PREFIX):
        joint, _, metric = name[len(JOINT_PREFIX) :].rpartition(".")
        return (joint, metric) if joint and metric in JOINT_METRICS else None
    return None


def metric_kind(name: str) -> str | None:
    """The kind (``float``, ``int``, ``bool``) of a metric a campaign may name: one of
    :data:`METRICS`, a joint's (``joints.NAME.METRIC``) or the worst joint's
    (``worst.METRIC``) of :data:`JOINT_METRICS`; None for an unknown name."""
    if name in METRICS:
        return METRICS[name].kind
    split = split_joint_metric(name)
    return JOINT_METRICS[split[1]].kind if split is not None else None


def metric_words(name: str) -> str | None:
    """A metric in words (None: unknown), for the campaign plots."""
    if name in METRIC_WORDS:
        return METRIC_WORDS[name]
    split = split_joint_metric(name)
    if split is None:
        return None
    joint, metric = split
    return f"{JOINT_METRICS[metric].words}, " + (f"joint {joint}" if joint else "worst joint")


def joint_columns(joints: Iterable[str]) -> list[str]:
    """The result columns of a rig's joints, named ``joints``: each joint's metrics,
    then the worst joint's, each followed by the name of the joint it is
    (``worst.METRIC.joint``); none without joints (a single-joint campaign)."""
    names = list(joints)
    if not names:
        return []
    cols = [f"{JOINT_PREFIX}{j}.{m}" for j in names for m in JOINT_METRICS]
    for m in JOINT_METRICS:
        cols += [f"{WORST_PREFIX}{m}", f"{WORST_PREFIX}{m}.joint"]
    return cols


def joint_metrics_of(result: dict[str, Any]) -> dict[str, Any]:
    """A rig's per-joint metrics (:data:`JOINT_METRICS`) from its ``hdhil run --json``
    result: ``joints.NAME.METRIC`` for every joint, and ``worst.METRIC`` with
    ``worst.METRIC.joint`` over the joints that report it (the first in the layout's
    order on a tie). Empty for a single joint's result."""
    joints = result.get("joints")
    if not isinstance(joints, list):
        return {}
    out: dict[str, Any] = {}
    for name, m in JOINT_METRICS.items():
        worst: tuple[Any, str] | None = None
        for joint in joints:
            value = m.get(joint)
            out[f"{JOINT_PREFIX}{joint['name']}.{name}"] = value
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                continue
            if isinstance(value, float) and math.isnan(value):
                continue
            if worst is None or (value > worst[0] if m.worse == "max" else value < worst[0]):
                worst = (value, str(joint["name"]))
        out[f"{WORST_PREFIX}{name}"] = None if worst is None else worst[0]
        out[f"{WORST_PREFIX}{name}.joint"] = None if worst is None else worst[1]
    return out


def _rig_metric(name: str, result: dict[str, Any]) -> Any:
    """A metric of :data:`METRICS` for a rig's result: what a rig reports for the run
    as a whole (its time, its cycles, its frames on every bus); None for the rest."""
    if name in ("simulated_s", "cycles"):
        return result.get(name)
    if name == "frames_total":
        return int(sum((result.get("frames") or {}).values()))
    return None


def metrics_of(result: dict[str, Any], planned_cycles: int) -> dict[str, Any]:
    """Every metric of :data:`METRICS` for one run's result (None: not reported) and,
    for a rig of several joints, its metrics per joint and for the worst joint
    (:func:`joint_metrics_of`)."""
    if isinstance(result.get("joints"), list):
        out = {name: _rig_metric(name, result) for name in METRICS}
        out.update(joint_metrics_of(result))
    else:
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

_CRITERION = re.compile(r"^\s*([A-Za-z_][\w.\-]*)\s*(<=|>=|==|!=|<|>)\s*(\S.*?)\s*$")
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
        kind = metric_kind(metric)
        if kind is None:
            raise ConfigError(f"{where}: unknown metric {metric!r} in {text!r} ({known_metrics()})")
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
        return (
            False,
            f"{self.metric} = {format_value(actual)}, not {self.op} {format_value(self.value)}",
        )

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


def known_metrics() -> str:
    """The metrics a campaign may name, for an error message."""
    return (
        f"known: {', '.join(METRICS)}; for a rig of several joints {JOINT_PREFIX}NAME.METRIC "
        f"and {WORST_PREFIX}METRIC with METRIC one of {', '.join(JOINT_METRICS)}"
    )


def format_value(value: Any) -> str:
    """A metric's value, a threshold or an axis value as a campaign prints it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


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
