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

from hdhil.rig.campaign import CampaignRun, Record, _write_atomic
from hdhil.rig.campaign_file import Campaign
from hdhil.rig.campaign_metrics import METRICS, format_value
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


def columns(campaign: Campaign) -> list[str]:
    axis = campaign.axis_keys
    head = ["variant", "scenario", *axis]
    if "seed" not in axis:
        head.append("seed")
    return [*head, *METRICS, *(c.text for c in campaign.criteria), "status", "reason", "digest"]


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
        for c in campaign.criteria:
            row[c.text] = (
                "error" if rec.error is not None else "pass" if rec.verdicts.get(c.text) else "fail"
            )
        row["status"] = rec.status
        row["reason"] = "; ".join(rec.reasons)
        row["digest"] = v.digest
        out.append(row)
    return out


def results_csv(campaign: Campaign, table: list[dict[str, Any]]) -> bytes:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    head = columns(campaign)
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


def write_parquet(path: Path, campaign: Campaign, table: list[dict[str, Any]]) -> str | None:
    """``results.parquet`` through pyarrow; returns why not when it cannot."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return "pyarrow is not installed (pip install 'hdhil[cluster]'): no results.parquet"
    data: dict[str, list[Any]] = {}
    for col in columns(campaign):
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


def plot_files(campaign: Campaign, table: list[dict[str, Any]], plots: Path) -> list[Path]:
    """One PNG per plotted metric and axis: every variant as a dot, the mean per axis
    value as a line, coloured by another axis with few values when there is one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
            numeric = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in xs_all)
            order = sorted(xs_all) if numeric else xs_all
            pos = {x: (x if numeric else i) for i, x in enumerate(order)}
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
            fig, ax = plt.subplots(figsize=(5.0, 3.2), dpi=90)
            for label, members in groups.items():
                pts = [(pos[r[axis]], r[metric]) for r in members if _finite(r[metric])]
                if not pts:
                    continue
                line = ax.plot(
                    [p[0] for p in pts], [p[1] for p in pts], "o", alpha=0.35, markersize=3
                )[0]
                means = []
                for x in order:
                    ys = [r[metric] for r in members if r[axis] == x and _finite(r[metric])]
                    if ys:
                        means.append((pos[x], sum(ys) / len(ys)))
                ax.plot(
                    [m[0] for m in means],
                    [m[1] for m in means],
                    "-",
                    color=line.get_color(),
                    label=f"{colour_by} = {label} (mean)" if colour_by else "mean",
                )
            for c in campaign.criteria:
                if c.metric == metric and not isinstance(c.value, bool):
                    ax.axhline(c.value, color="0.3", linestyle="--", linewidth=0.8,
                               label=f"criterion {c.op} {format_value(c.value)}")  # fmt: skip
            if not numeric:
                ax.set_xticks(range(len(order)), [_axis_label(x) for x in order])
            unit = metric.rsplit("_", 1)[-1] if "_" in metric else ""
            ax.set_xlabel(axis)
            ax.set_ylabel(f"{metric}" + (f" ({unit})" if unit in ("Nm", "dB", "radps") else ""))
            ax.set_title(f"{campaign.name}: {metric} over {axis}", fontsize=9)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7)
            fig.tight_layout()
            path = plots / f"{metric}-over-{axis.replace('.', '_')}.png"
            fig.savefig(path)
            plt.close(fig)
            files.append(path)
    return files


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
    _write_atomic(out / "results.csv", results_csv(campaign, table))
    _write_atomic(out / "timings.csv", timings_csv(run.records))
    notes = []
    why = write_parquet(out / "results.parquet", campaign, table)
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
