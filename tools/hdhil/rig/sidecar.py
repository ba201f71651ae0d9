"""What a trace's sidecar JSON says about the run that wrote it, and the run read back.

Every trace hdhil writes gets ``TRACE.json`` beside it (:mod:`hdhil.can.traces.writer`). For a
run it carries the resolved :class:`~hdhil.rig.request.RunRequest` (``request``), so
``hdhil evaluate``, ``plot``, ``tune`` and :func:`hdhil.api.evaluate_trace` score a trace
with the very settings it ran with (firmware, evaluation start, mapping), whatever
files have changed since. Older sidecars without ``request`` name the scenario and its
override and calibration files, which are loaded again where they still exist.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hdhil.can.traces.sidecar import metadata_path, read_metadata
from hdhil.core.errors import UserError
from hdhil.rig.request import RunRequest, resolve

__all__ = ["mapping_metadata", "request_for_trace", "run_metadata"]


def utc_text(unix_s: float) -> str:
    """``unix_s`` as an ISO 8601 UTC date and time, to the millisecond (a sidecar's
    ``start_time_utc``)."""
    import datetime

    when = datetime.datetime.fromtimestamp(unix_s, tz=datetime.timezone.utc)
    return when.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def mapping_metadata(dcf: Path | None, label: str, node_id: int = 2) -> dict[str, Any]:
    """What a sidecar records about a mapping from a DCF: its label, the DCF's name and
    the drive's PDOs (so ``evaluate`` and ``dump`` decode the trace); empty for the
    default mapping. A DCF canopen cannot read is a one-line error."""
    if dcf is None:
        return {}
    from hdhil.canopen.mapping import dcf_layouts, layouts_to_json

    try:
        _, layouts = dcf_layouts(dcf, node_id)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    return {"mapping": label, "drive_dcf": dcf.name, "drive_pdos": layouts_to_json(layouts)}


def run_metadata(request: RunRequest) -> dict[str, Any]:
    """The sidecar entries of a run: where its settings came from, its mapping's PDOs
    and the whole request."""
    layout = request.layout
    node_id = layout.drives[0].node_id
    return {
        "scenario_source": request.sources.scenario,
        # who is on the bus at which node-ID (hdhil.canopen.mapping.trace_decoder)
        "layout": {
            "controller_node_id": layout.controller_node_id,
            "drives": [{"node_id": d.node_id, "bus": d.bus} for d in layout.drives],
        },
        "overrides": list(request.sources.overrides),
        "calibration": request.sources.calibration,
        **mapping_metadata(request.mapping.dcf, request.mapping.label, node_id),
        "request": request.to_data(),
    }


def request_for_trace(trace: Path, given: str | None = None) -> RunRequest | None:
    """The request a trace was recorded with: ``given`` (``--scenario``) if any; else the
    sidecar's ``request``; else, for older sidecars, the scenario they name with those of
    the run's override and calibration files that can still be read; else ``None`` (the
    firmware defaults)."""
    if given:
        return resolve(given)
    meta = read_metadata(trace)
    if not meta or not meta.get("scenario"):
        return None
    if isinstance(meta.get("request"), dict):
        return RunRequest.from_data(meta["request"], metadata_path(trace).name)
    source = str(meta.get("scenario_source") or meta["scenario"])
    overrides = [Path(p) for p in meta.get("overrides") or []]
    calibration = meta.get("calibration")
    for files, cal in ((overrides, calibration), (overrides, None), ([], None)):
        try:
            return resolve(source, overrides=files, calibration=cal)
        except (OSError, ValueError, UserError):
            continue  # a file of the run that can no longer be read: left out
    return resolve(str(meta["scenario"]))
