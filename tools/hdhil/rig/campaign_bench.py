"""The campaign figures of ``hdhil bench``: variants per minute on 1 and N local workers,
the speed-up, and the per-variant overhead of the campaign machinery.

The campaign is ``variants`` seeds of the free-motion scenario, ``duration_s`` simulated
seconds each.  The reference is the same variants run one after the other in the bench's
own process through :func:`hdhil.rig.variant.run_settings` (the code a worker runs), so

- variants per minute = variants / campaign wall time x 60 (execution: from the first
  submission to the last record stored, pool start included; the report is timed apart);
- speed-up = wall time on 1 worker / wall time on N workers (goal: >= 0.85 N);
- per-variant overhead = (wall time on 1 worker - the variants' own run times, timed in
  the worker around the run) / variants: what the pool, the transfer of settings and
  results, and storing each record add; also as a share of one variant's run time
  (goal: < 5 %).  Timed in the same campaign, it does not drift with the machine's load
  as a comparison with the separate reference would (that figure is reported too).

Each figure is the median of ``repeat`` rounds; a round runs the reference, 1 worker and
N workers back to back so that the machine's load affects them alike.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from hdhil.rig.campaign import local_executor, run_campaign
from hdhil.rig.campaign_file import Axis, Campaign
from hdhil.rig.campaign_metrics import Criterion
from hdhil.rig.campaign_report import write_outputs
from hdhil.rig.campaign_variants import expand
from hdhil.rig.variant import run_settings


def bench_campaign(
    variants: int = 16, duration_s: float = 2.0, repeat: int = 3, workers: int | None = None
) -> dict[str, Any]:
    """Measure; see the module docstring.  ``workers`` defaults to the machine's cores."""
    n = workers or os.cpu_count() or 1
    campaign = Campaign(
        name="bench",
        source="hdhil bench",
        scenarios=("free-motion",),
        duration_s=duration_s,
        criteria=(
            Criterion.parse("stopped_early == false"),
            Criterion.parse("eval_rms_err_Nm < 0.06"),
        ),
        axes=(Axis("seed", tuple(range(1, variants + 1))),),
    )
    grid = expand(campaign)
    ref_s: list[float] = []
    wall: dict[int, list[float]] = {1: [], n: []}
    inside: list[float] = []
    report_s: list[float] = []
    load = [os.getloadavg()[0]] if hasattr(os, "getloadavg") else []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for v in grid:
            run_settings(v.settings)
        ref_s.append(time.perf_counter() - t0)
        for k in dict.fromkeys((1, n)):
            with tempfile.TemporaryDirectory(prefix="hdhil-bench-campaign-") as tmp:
                run = run_campaign(campaign, grid, Path(tmp), lambda k=k: local_executor(k))
                if run.interrupted:  # Ctrl-C: the campaign kept what it had; bench stops
                    raise KeyboardInterrupt
                if len(run.records) != len(grid) or any(
                    r.error for r in run.records.values()
                ):  # pragma: no cover - a broken campaign is not a figure
                    raise RuntimeError("the bench campaign did not complete")
                wall[k].append(run.wall_s)
                if k == 1:
                    inside.append(sum(r.wall_s for r in run.records.values()))
                    t1 = time.perf_counter()
                    write_outputs(campaign, grid, run, Path(tmp))
                    report_s.append(time.perf_counter() - t1)
    if load:
        load.append(os.getloadavg()[0])
    ref = statistics.median(ref_s)
    w1 = statistics.median(wall[1])
    wn = statistics.median(wall[n])
    per_variant_s = statistics.median(inside) / variants
    overhead_s = statistics.median(w - i for w, i in zip(wall[1], inside, strict=True)) / variants
    return {
        "scenario": "free-motion",
        "variants": variants,
        "duration_s": duration_s,
        "repeat": repeat,
        "workers": n,
        "cores": os.cpu_count(),
        "reference_s": ref,
        "run_s_per_variant": per_variant_s,
        "reference_s_per_variant": ref / variants,
        "overhead_vs_reference_share": (w1 - ref) / ref,
        "wall_s_1": w1,
        "wall_s_n": wn,
        "variants_per_min_1": variants / w1 * 60,
        "variants_per_min_n": variants / wn * 60,
        "speedup": w1 / wn,
        "speedup_goal": 0.85 * n,
        "overhead_s_per_variant": overhead_s,
        "overhead_share": overhead_s / per_variant_s,
        "overhead_goal": 0.05,
        "report_s": statistics.median(report_s),
        "load_average": load,
        "rounds": {"reference_s": ref_s, "wall_s_1": wall[1], "wall_s_n": wall[n]},
    }


def format_campaign_section(c: dict[str, Any]) -> list[str]:
    """The campaign section of ``hdhil bench``'s text report."""
    n = c["workers"]
    ok_speed = "met" if c["speedup"] >= c["speedup_goal"] else "NOT met"
    ok_over = "met" if c["overhead_share"] < c["overhead_goal"] else "NOT met"
    return [
        f"Campaign ({c['variants']} variants of {c['duration_s']:g} s {c['scenario']}, local "
        f"process pool; median of {c['repeat']} rounds)",
        f"  one variant's run               {c['run_s_per_variant'] * 1e3:.0f} ms in a worker, "
        f"{c['reference_s_per_variant'] * 1e3:.0f} ms in the bench's process",
        f"  1 worker                        {c['variants_per_min_1']:.0f} variants/min",
        f"  {n} workers                       {c['variants_per_min_n']:.0f} variants/min",
        f"  speed-up                        {c['speedup']:.2f}x on {n} workers "
        f"(goal >= {c['speedup_goal']:.2f}x: {ok_speed})",
        f"  overhead per variant            {c['overhead_s_per_variant'] * 1e3:+.1f} ms = "
        f"{c['overhead_share']:+.1%} of a variant's run (goal < 5 %: {ok_over}); "
        f"1 worker against the in-process reference: {c['overhead_vs_reference_share']:+.1%}",
        f"  report (CSV, parquet, plots)    {c['report_s']:.2f} s per campaign",
    ] + (
        [
            f"  load average (1 min) before / after: {c['load_average'][0]:.1f} / "
            f"{c['load_average'][1]:.1f} on {c['cores']} cores"
        ]
        if c["load_average"]
        else []
    )
