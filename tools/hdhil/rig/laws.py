"""``hdhil run --compare-laws``: one scenario run once per torque-control law, each closed
over the bus, for the tracking table (:func:`hdhil.rig.result.format_tracking`).

:data:`COMPARED_LAWS` are the laws of [Vertechy] (JTF1/2/3, the §V filter estimates, JTF1
with feedforward); a scenario with the Eq. 5 friction compensation also runs JTF1
without it. Each law is a variant of the request's scenario, run by
:func:`hdhil.rig.runner.run_lockstep` with its own trace (``run-LABEL.blf``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from hdhil.core.dataconf import ConfigError, merge
from hdhil.rig.request import RunRequest
from hdhil.rig.runner import run_lockstep
from hdhil.rig.scenario import scenario_data, scenario_from_dict

#: The laws ``--compare-laws`` runs, as ``(label, trace suffix, [firmware.control]
#: overrides)``: the seed's three ([Vertechy] §IV: JTF1 = Eq. 4 with the LQ design, JTF2
#: k3 = 0, k4 = 1 + Jm/Jl, JTF3 k3 = 0, k4 = 1), JTF2 and JTF3 as [Vertechy] §V says the
#: literature builds them (τ̂s, τ̂s' from a low-pass and a derivative filter of the
#: measurement, ``estimates = "filters"``, cut-offs ``firmware.config.JTF_LOWPASS_HZ``,
#: ``JTF_DERIVATIVE_HZ``), and JTF1 with desired-torque-derivative feedforward tuned for
#: the tracking scenario (:data:`firmware.config.JTF1_FF_TRACKING`: exact feedforward
#: gains, V = 1e7).  A scenario with the Eq. 5 friction compensation keeps it for every
#: law and adds JTF1 without it (:data:`WITHOUT_FRICTION_COMPENSATION`).
COMPARED_LAWS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("JTF1", "jtf1", {"law": "jtf1"}),
    ("JTF2", "jtf2", {"law": "jtf2"}),
    ("JTF3", "jtf3", {"law": "jtf3"}),
    ("JTF2, filters (§V)", "jtf2-filters", {"law": "jtf2", "estimates": "filters"}),
    ("JTF3, filters (§V)", "jtf3-filters", {"law": "jtf3", "estimates": "filters"}),
    ("JTF1 + feedforward", "jtf1_ff",
     {"law": "jtf1_ff", "feedforward": "exact", "weights": {"V": 1e7}}),
)  # fmt: skip
#: The extra row of a scenario that compensates the motor friction (Eq. 5): JTF1 with
#: Eq. 4, no model.
WITHOUT_FRICTION_COMPENSATION = (
    "JTF1 without friction comp. (Eq. 4)",
    "jtf1-eq4",
    {"law": "jtf1", "friction": {"coulomb_Nm": 0.0}},
)


def _suffixed(trace: Path, label: str) -> Path:
    """``run.blf`` -> ``run-LABEL.blf``; the whole format extension is kept
    (``run.asc.gz`` -> ``run-LABEL.asc.gz``)."""
    from hdhil.can.traces.formats import trace_format

    fmt, compressed = trace_format(trace)
    ext = fmt + (".gz" if compressed else "")
    base = trace.name[: -len(ext)] if ext and trace.name.lower().endswith(ext) else trace.stem
    return trace.with_name(f"{base}-{label}{trace.name[len(base) :]}")


def _compared(request: RunRequest) -> list[tuple[str, str, dict[str, Any]]]:
    laws = list(COMPARED_LAWS)
    if request.scenario.firmware.control.friction.coulomb_Nm > 0.0:
        laws.insert(1, WITHOUT_FRICTION_COMPENSATION)
        laws[0] = ("JTF1 with friction comp. (Eq. 5)", "jtf1", {"law": "jtf1"})
    return laws


def compared_traces(request: RunRequest, trace: Path) -> list[Path]:
    """The traces :func:`compare_laws` writes for ``trace`` (one per law), so that they
    can be checked before the first run."""
    return [_suffixed(trace, slug) for _, slug, _ in _compared(request)]


def compare_laws(request: RunRequest, **kwargs: Any) -> list[dict[str, Any]]:
    """Run ``request`` once per law of :data:`COMPARED_LAWS` (and without friction
    compensation if the scenario has it), each closed over the bus."""
    rows = []
    trace: Path | None = kwargs.pop("trace", None)
    laws = _compared(request)
    scenario = request.scenario
    if trace is not None:
        from hdhil.can.traces.writer import check_trace_path

        for law_trace in compared_traces(request, trace):
            check_trace_path(law_trace)  # every one writable before the first run
    base = scenario_data(scenario)
    for label, slug, control in laws:
        variant = scenario_from_dict(merge(base, {"firmware": {"control": control}}), label)
        law_trace = _suffixed(trace, slug) if trace else None
        r = run_lockstep(dataclasses.replace(request, scenario=variant), trace=law_trace,
                         evaluate=False, **kwargs)  # fmt: skip
        if r.tracking is None:
            raise ConfigError(f"{scenario.name}: no tracking telemetry for {label}")
        row = {**r.tracking, "law": label, "trace": str(law_trace) if law_trace else None,
               "real_time_factor": r.real_time_factor}  # fmt: skip
        if r.verdict is not None:
            row["verdict"] = r.verdict
        rows.append(row)
        if r.interrupted:
            break
    return rows
