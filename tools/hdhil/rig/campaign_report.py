"""A campaign's outputs: ``results.csv`` (and ``results.parquet``), ``timings.csv``,
``report.md`` and its plots.

``results.csv`` has one row per variant, sorted by variant: the base scenario, the axis
values, the seed, every metric, one pass/fail column per criterion, the status and its
reasons, and the variant's digest.  Nothing in it depends on the host, the number of
workers or the order results arrived in (numbers are written in their shortest exact
form), so the same campaign gives the same bytes on one worker, many, or a cluster.
Wall-clock figures go to ``timings.csv``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hdhil.core.plotlabels import axis_label, key_label, split_unit
from hdhil.rig.campaign import CampaignRun, Record, _write_atomic
from hdhil.rig.campaign_file import Campaign
from hdhil.rig.campaign_metrics import METRICS, format_value, joint_columns
from hdhil.rig.campaign_metrics import metric_words as words_of_metric
from hdhil.rig.campaign_variants import Variant

#: Variants listed per criterion under "worst variants".
WORST = 5


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else repr(value)
    if isinstance(value, (list, dict)):
        return json.dumps(value, sort_keys=True, separators=(",", ":"))
    return str(value)


def joint_names(variants: Sequence[Variant]) -> list[str]:
    """The joints of a campaign's rigs, in the order they first appear (none for a
    campaign of single joints): the per-joint columns of ``results.csv``."""
    names: list[str] = []
    for v in variants:
        names += [j for j in v.joints if j not in names]
    return names


def columns(campaign: Campaign, joints: Sequence[str] = ()) -> list[str]:
    """``results.csv``'s columns; with the ``joints`` of a campaign's rigs, each joint's
    metrics and the worst joint's after the run's (:func:`~hdhil.rig.campaign_metrics.
    joint_columns`)."""
    axis = campaign.axis_keys
    head = ["variant", "scenario", *axis]
    if "seed" not in axis:
        head.append("seed")
    return [*head, *METRICS, *joint_columns(joints), *(c.text for c in campaign.criteria),
            "status", "reason", "digest"]  # fmt: skip


def rows(campaign: Campaign, records: dict[str, Record]) -> list[dict[str, Any]]:
    """One plain row per recorded variant, sorted by variant."""
    out = []
    for vid in sorted(records):
        rec = records[vid]
        v = rec.variant
        row: dict[str, Any] = {"variant": v.id, "scenario": v.scenario}
        row.update({k: v.values.get(k) for k in campaign.axis_keys})
        row["seed"] = v.seed
        row.update({m: rec.metrics.get(m) for m in METRICS})
        row.update({m: rec.metrics.get(m) for m in joint_columns(v.joints)})
        for c in campaign.criteria:
            row[c.text] = (
                "error" if rec.error is not None else "pass" if rec.verdicts.get(c.text) else "fail"
            )
        row["status"] = rec.status
        row["reason"] = "; ".join(rec.reasons)
        row["digest"] = v.digest
        out.append(row)
    return out


def results_csv(
    campaign: Campaign, table: list[dict[str, Any]], joints: Sequence[str] = ()
) -> bytes:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    head = columns(campaign, joints)
    writer.writerow(head)
    for row in table:
        writer.writerow([_cell(row.get(c)) for c in head])
    return buf.getvalue().encode()


def timings_csv(records: dict[str, Record]) -> bytes:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["variant", "digest", "wall_s", "worker", "resumed"])
    for vid in sorted(records):
        r = records[vid]
        writer.writerow([vid, r.variant.digest, f"{r.wall_s:.4f}", r.worker, _cell(r.resumed)])
    return buf.getvalue().encode()


def write_parquet(
    path: Path, campaign: Campaign, table: list[dict[str, Any]], joints: Sequence[str] = ()
) -> str | None:
    """``results.parquet`` through pyarrow; returns why not when it cannot."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return "pyarrow is not installed (pip install 'hdhil[cluster]'): no results.parquet"
    data: dict[str, list[Any]] = {}
    for col in columns(campaign, joints):
        values = [row.get(col) for row in table]
        present = [x for x in values if x is not None]
        if present and all(isinstance(x, bool) for x in present):
            data[col] = values
        elif present and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in present
        ):
            integral = all(isinstance(x, int) for x in present)
            if integral and not all(-(2**63) <= x < 2**63 for x in present):
                data[col] = [None if x is None else _cell(x) for x in values]  # beyond int64
                continue
            data[col] = [None if x is None else (x if integral else float(x)) for x in values]
        else:
            data[col] = [None if x is None else _cell(x) for x in values]
    sink = io.BytesIO()  # not a path: pyarrow refuses names that are not UTF-8
    pq.write_table(pa.table(data), sink)
    _write_atomic(path, sink.getvalue())
    return None


def _axis_label(value: Any) -> str:
    return _cell(value) if not isinstance(value, str) else value


#: Campaign axes (scenario keys) in words; other keys read as their last two parts.
AXIS_WORDS: dict[str, str] = {
    "scenario": "scenario",
    "seed": "noise seed",
    "faults.seed": "fault seed",
    "firmware.ripple.mode": "ripple filter",
    "faults.control.loss_rate": "control-bus frame loss rate",
    "faults.sensor.loss_rate": "sensor-bus frame loss rate",
}


def is_categorical(axis: str, values: Sequence[Any]) -> bool:
    """Whether a campaign axis is a set of labels rather than a quantity: any non-numeric
    value, or a seed (an integer that names a noise pattern; its order means nothing).
    Over a categorical axis the plots draw points per category, never a line between
    categories."""
    numeric = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in values)
    return not numeric or axis == "seed" or axis.endswith(".seed")


def _is_fraction(axis: str) -> bool:
    """A fault rate, a fraction of frames or samples: drawn in per cent."""
    return axis.startswith("faults.") and axis.rsplit(".", 1)[-1].endswith("_rate")


def axis_words(axis: str) -> str:
    """A campaign axis as an axis label: words and unit (:data:`AXIS_WORDS`)."""
    if _is_fraction(axis):
        return axis_label(AXIS_WORDS.get(axis) or key_label(axis), "%")
    if axis.startswith("joints.") and axis.count(".") >= 2:  # joints.NAME.KEY: the joint's
        _, joint, key = axis.split(".", 2)
        return f"{joint}: {key_label(key, AXIS_WORDS)}"
    return key_label(axis, AXIS_WORDS)


def metric_words(metric: str) -> str:
    """A metric as an axis label: its words and unit (:data:`METRIC_WORDS`; a joint's
    metric: :func:`hdhil.rig.campaign_metrics.metric_words`)."""
    words = words_of_metric(metric)
    return key_label(metric, {metric: words} if words else None)


def plot_files(campaign: Campaign, table: list[dict[str, Any]], plots: Path) -> list[Path]:
    """One PNG per plotted metric and axis, labelled in words and units, with the legend
    beside the axes.  Every variant is a dot, coloured by another axis with few values
    when there is one.  Over a numeric axis (a loss rate) a line joins the means per
    value; over a categorical one (the ripple filter, the seed) each category has its
    points side by side per colour and a bar at their mean, with no line across
    categories."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    axes = [a.key for a in campaign.axes] + [group[0].key for group in campaign.zips]
    if len(campaign.scenarios) > 1:
        axes.insert(0, "scenario")
    ok = [r for r in table if r["status"] != "error"]
    files: list[Path] = []
    if not ok or not axes:
        return files
    plots.mkdir(exist_ok=True)
    for old in plots.glob("*-over-*.png"):  # an earlier run's plots of other metrics or axes
        if old.is_file() and not old.is_symlink():
            old.unlink()
    for metric in campaign.plot_metrics:
        for axis in axes:
            xs_all = []
            for r in ok:
                if r[axis] not in xs_all:
                    xs_all.append(r[axis])
            categorical = is_categorical(axis, xs_all)
            numeric = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in xs_all)
            order = sorted(xs_all) if numeric else xs_all
            colour_by = next(
                (
                    a
                    for a in axes
                    if a not in (axis, "seed") and len({_cell(r[a]) for r in ok}) <= 6
                ),
                None,
            )
            groups: dict[str, list[dict[str, Any]]] = {}
            for r in ok:
                groups.setdefault(_cell(r[colour_by]) if colour_by else "", []).append(r)
            fig, ax = plt.subplots(figsize=(7.0, 3.4), dpi=90, layout="constrained")
            # Categories at 0, 1, ...; the colour groups side by side within each.
            width = 0.7 / max(1, len(groups))
            for g, members in enumerate(groups.values()):
                shift = (g - (len(groups) - 1) / 2.0) * width if categorical else 0.0
                pos = {x: (order.index(x) + shift if categorical else x) for x in order}
                pts = [(pos[r[axis]], r[metric]) for r in members if _finite(r[metric])]
                if not pts:
                    continue
                value = members[0][colour_by] if colour_by else None
                name = (
                    f"{_words_of(colour_by)} = {_value_words(colour_by, value)}"
                    if colour_by
                    else "variants"
                )
                dots = ax.plot([p[0] for p in pts], [p[1] for p in pts], "o", alpha=0.45,
                               markersize=3, label=name)[0]  # fmt: skip
                means = []
                for x in order:
                    ys = [r[metric] for r in members if r[axis] == x and _finite(r[metric])]
                    if ys:
                        means.append((pos[x], sum(ys) / len(ys)))
                mx, my = [m[0] for m in means], [m[1] for m in means]
                if categorical:
                    ax.plot(mx, my, "_", color=dots.get_color(), markersize=16, mew=2.0)
                else:
                    ax.plot(mx, my, "-", color=dots.get_color())
            # One neutral legend entry for the means, in the style drawn.
            mean_style = {"marker": "_", "markersize": 16, "mew": 2.0, "ls": "none"}
            ax.plot([], [], color="0.2", label="mean per category" if categorical
                    else "mean per value", **(mean_style if categorical else {}))  # fmt: skip
            for c in campaign.criteria:
                if c.metric == metric and not isinstance(c.value, bool):
                    ax.axhline(c.value, color="0.3", linestyle="--", linewidth=0.8,
                               label=f"criterion {c.op} {format_value(c.value)}")  # fmt: skip
            if categorical:
                ax.set_xticks(range(len(order)), [_axis_label(x) for x in order])
                ax.set_xlim(-0.5, len(order) - 0.5)
            elif _is_fraction(axis):
                ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{100.0 * v:g}"))
            ax.set_xlabel(axis_words(axis))
            ax.set_ylabel(metric_words(metric))
            what = f"{words_of_metric(metric) or metric} over {_words_of(axis)}"
            ax.set_title(f"{campaign.name}: {what}", fontsize=9)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
            path = plots / f"{_file_part(metric)}-over-{_file_part(axis.replace('.', '_'))}.png"
            fig.savefig(path)
            plt.close(fig)
            files.append(path)
    return files


def _file_part(name: str) -> str:
    """A metric or axis as part of a file name: a joint's name may hold any character."""
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)


def _value_words(axis: str | None, value: Any) -> str:
    """An axis value as a legend shows it (a fault rate in per cent)."""
    if axis is not None and _is_fraction(axis) and _finite(value):
        return f"{100.0 * value:g} %"
    return _axis_label(value)


def _words_of(key: str | None, words: dict[str, str] | None = None) -> str:
    """A key in words without its unit (for titles and legends)."""
    if key is None:
        return ""
    words = AXIS_WORDS if words is None else words
    if words is AXIS_WORDS and key.startswith("joints.") and key.count(".") >= 2:
        _, joint, rest = key.split(".", 2)
        return f"{joint}'s {_words_of(rest)}"
    return words.get(key) or key_label(split_unit(key)[0])


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def summary(campaign: Campaign, variants: Sequence[Variant], run: CampaignRun) -> dict[str, Any]:
    """Counts of the campaign (what ``--json`` prints)."""
    recs = run.records.values()
    crit = {
        c.text: {
            "pass": sum(1 for r in recs if r.error is None and r.verdicts.get(c.text)),
            "fail": sum(1 for r in recs if r.error is None and not r.verdicts.get(c.text)),
        }
        for c in campaign.criteria
    }
    return {
        "campaign": campaign.name,
        "variants": len(variants),
        "recorded": len(run.records),
        "ran": run.ran,
        "resumed": run.resumed,
        "not_run": len(variants) - len(run.records),
        "passed": sum(1 for r in recs if r.status == "pass"),
        "failed": sum(1 for r in recs if r.status == "fail"),
        "errors": sum(1 for r in recs if r.status == "error"),
        "workers_lost": run.lost,
        "interrupted": run.interrupted,
        "criteria": crit,
        "wall_s": run.wall_s,
    }


def report_md(campaign: Campaign, variants: Sequence[Variant], run: CampaignRun,
              table: list[dict[str, Any]], plots: list[Path], notes: list[str]) -> str:  # fmt: skip
    s = summary(campaign, variants, run)
    lines = [f"# Campaign {campaign.name}", ""]
    if campaign.description:
        lines += [campaign.description, ""]
    axes = ", ".join(f"{a.key} ({len(a.values)})" for a in campaign.axes) or "none"
    zips = "; ".join(" + ".join(a.key for a in g) + f" ({len(g[0].values)})" for g in campaign.zips)
    lines += [
        f"- scenarios: {', '.join(Path(x).stem for x in campaign.scenarios)}",
        f"- crossed axes: {axes}" + (f"; zipped: {zips}" if zips else ""),
        # Not how many ran now and earlier (timings.csv): a campaign completed after an
        # interrupt gives the uninterrupted campaign's report.
        f"- variants: {s['variants']}; recorded {s['recorded']}, not run {s['not_run']}"
        + (" (interrupted)" if s["interrupted"] else ""),
        f"- **passed {s['passed']}, failed {s['failed']}, errors {s['errors']}**",
        "",
        "## Criteria",
        "",
        "| criterion | pass | fail | error |",
        "|---|---:|---:|---:|",
    ]
    for text, counts in s["criteria"].items():
        lines.append(f"| `{text}` | {counts['pass']} | {counts['fail']} | {s['errors']} |")
    by_id = {r.variant.id: r for r in run.records.values()}
    axis_cols = [c for c in columns(campaign)[1 : columns(campaign).index(next(iter(METRICS)))]]
    lines += ["", "## Worst variants", ""]
    errored = [r for r in table if r["status"] == "error"]
    if errored:
        lines += ["Errors:", ""]
        for r in errored[:WORST]:
            lines.append(f"- {_describe(r, axis_cols)}: {r['reason']}")
        if len(errored) > WORST:
            lines.append(f"- ... and {len(errored) - WORST} more (results.csv)")
        lines.append("")
    for c in campaign.criteria:
        ranked = sorted(
            (r for r in table if r["status"] != "error"),
            key=lambda r: (-c.badness(by_id[r["variant"]].metrics), r["variant"]),
        )[:WORST]
        if not ranked:
            continue
        lines += [f"`{c.text}`:", ""]
        for r in ranked:
            ok, why = c.check(by_id[r["variant"]].metrics)
            shown = f"{c.metric} = {format_value(r[c.metric])} (pass)" if ok else f"FAIL: {why}"
            early = [x for x in by_id[r["variant"]].reasons if x.startswith("stopped early")]
            lines.append(f"- {_describe(r, axis_cols)}: " + "; ".join([shown, *early]))
        lines.append("")
    lines += _by_axis_values(campaign, table)
    if plots:
        lines += ["## Plots", ""]
        lines += [f"![{p.stem}](plots/{p.name})" for p in plots]
        lines.append("")
    if notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(lines)


def _by_axis_values(campaign: Campaign, table: list[dict[str, Any]]) -> list[str]:
    """Pass counts and metric means per combination of the crossed axes (seeds and
    zipped groups pooled)."""
    keys = [a.key for a in campaign.axes if a.key != "seed"]
    if len(campaign.scenarios) > 1:
        keys.insert(0, "scenario")
    if not keys or not table:
        return []
    metrics = campaign.plot_metrics
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for r in table:
        groups.setdefault(tuple(_cell(r[k]) for k in keys), []).append(r)
    lines = [
        "## By axis values",
        "",
        "Means over the variants of each row that report the metric.",
        "",
        "| " + " | ".join([*keys, "passed", *(f"mean {m}" for m in metrics)]) + " |",
        "|" + "---|" * len(keys) + "---:|" * (1 + len(metrics)),
    ]
    for key, members in groups.items():
        passed = sum(1 for r in members if r["status"] == "pass")
        means = []
        for m in metrics:
            ys = [r[m] for r in members if _finite(r[m])]
            means.append(f"{sum(ys) / len(ys):.4g}" if ys else "n/a")
            if ys and len(ys) < len(members):
                means[-1] += f" ({len(ys)})"
        lines.append("| " + " | ".join([*key, f"{passed}/{len(members)}", *means]) + " |")
    return [*lines, ""]


def _describe(row: dict[str, Any], axis_cols: list[str]) -> str:
    return (
        f"variant {row['variant']} (" + ", ".join(f"{c}={_cell(row[c])}" for c in axis_cols) + ")"
    )


def write_outputs(campaign: Campaign, variants: Sequence[Variant], run: CampaignRun,
                  out: Path) -> dict[str, Any]:  # fmt: skip
    """Write every output file from the records; returns the summary with the paths."""
    table = rows(campaign, run.records)
    joints = joint_names(variants)
    _write_atomic(out / "results.csv", results_csv(campaign, table, joints))
    _write_atomic(out / "timings.csv", timings_csv(run.records))
    notes = []
    why = write_parquet(out / "results.parquet", campaign, table, joints)
    if why:
        notes.append(why)
    if run.interrupted:  # drawing takes longer than the rest: the campaign is ending
        plots: list[Path] = []
        notes.append("interrupted: the plots are drawn once the campaign is complete")
    else:
        plots = plot_files(campaign, table, out / "plots")
    _write_atomic(
        out / "report.md", report_md(campaign, variants, run, table, plots, notes).encode()
    )
    s = summary(campaign, variants, run)
    s["out"] = str(out)
    s["notes"] = notes
    return s
