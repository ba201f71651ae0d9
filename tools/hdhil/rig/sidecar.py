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
from hdhil.core.dataconf import ConfigError, merge
from hdhil.core.errors import UserError
from hdhil.rig.request import RunRequest, resolve

__all__ = ["mapping_metadata", "request_for_trace", "run_metadata"]


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
    node_id = request.layout.drives[0].node_id
    return {
        "scenario_source": request.sources.scenario,
        "overrides": list(request.sources.overrides),
        "calibration": request.sources.calibration,
        **mapping_metadata(request.mapping.dcf, request.mapping.label, node_id),
        "request": request.to_data(),
    }


def request_for_trace(trace: Path, given: str | None = None) -> tuple[RunRequest | None, str]:
    """The request a trace was recorded with, and where it came from.

    ``given`` (``--scenario``) wins; else the sidecar's ``request``; else the scenario
    its sidecar names, with the override and calibration files that still exist; else
    ``None`` (the firmware defaults). Returns ``(request or None, note)``."""
    if given:
        return resolve(given), "--scenario"
    meta = read_metadata(trace)
    note = metadata_path(trace).name
    if not meta or not meta.get("scenario"):
        return None, "no scenario recorded with the trace"
    if isinstance(meta.get("request"), dict):
        return RunRequest.from_data(meta["request"], note), note
    source = str(meta.get("scenario_source") or meta["scenario"])
    overrides: dict[str, Any] = {}
    from hdhil.core.files import load_toml

    for path in meta.get("overrides") or []:
        try:
            overrides = merge(overrides, load_toml(Path(path), "override file"))
        except (OSError, ValueError, UserError):
            return resolve(str(meta["scenario"])), f"{note} (override {path} unreadable: left out)"
    try:
        request = resolve(source, overrides=[overrides] if overrides else ())
    except (OSError, ValueError, UserError):
        request = resolve(str(meta["scenario"]))
    if meta.get("calibration"):
        try:
            request = resolve(
                source,
                overrides=[overrides] if overrides else (),
                calibration=Path(meta["calibration"]),
            )
        except (OSError, ValueError, UserError, ConfigError):
            return request, f"{note} (calibration file unreadable)"
    return request, note
