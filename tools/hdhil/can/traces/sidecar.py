"""The sidecar of a trace: ``run.blf.json`` beside ``run.blf``.

A JSON object with what a trace format has no place for: the scenario, seed, start time
and bus of the run, the drive's PDO mapping when it came from a DCF, and whatever the
caller adds.  The commands that read a trace (evaluate, plot, the PDO-aware decoder)
take what ran from it.  Written atomically (:mod:`hdhil.core.files`), by the trace
writer together with the trace itself: both are renamed into place, or neither.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.files import load_json, write_text

#: The sidecar file next to a trace: ``run.blf`` -> ``run.blf.json``.
METADATA_SUFFIX = ".json"


def metadata_path(trace: Path) -> Path:
    """Where the metadata of ``trace`` is stored: the trace's name plus ``.json``."""
    return trace.with_name(trace.name + METADATA_SUFFIX)


def metadata_text(metadata: dict[str, Any]) -> str:
    """The sidecar's text for ``metadata``: JSON, sorted keys, non-finite numbers as
    ``null`` (:mod:`hdhil.core.jsonout`)."""
    return jsonout.dumps(metadata, indent=1, sort_keys=True) + "\n"


def write_metadata(trace: Path, metadata: dict[str, Any]) -> Path:
    """Write ``metadata`` (scenario, seed, start time, ...) as JSON next to ``trace``.

    Through :func:`hdhil.core.files.write_text`: written to a temporary file and renamed,
    so a reader never sees half of it; an existing path that is not a regular file is
    left alone (ValueError).  Non-finite numbers are written as ``null``
    (:mod:`hdhil.core.jsonout`)."""
    target = metadata_path(trace)
    try:
        write_text(target, metadata_text(metadata), "sidecar")
    except UserError as exc:
        raise ValueError(f"cannot write {target}: {exc}") from None
    return target


def read_metadata(trace: Path) -> dict[str, Any] | None:
    """The sidecar metadata of ``trace`` (:func:`write_metadata`), or ``None`` if there
    is none or it is not a JSON object.  Read like any configuration file
    (:func:`hdhil.core.files.load_json`): a regular file, size and nesting capped, so a
    FIFO or a huge file in its place neither blocks nor fills the memory."""
    path = metadata_path(Path(trace))
    try:  # none, unreadable, or a name too long for the file system: no sidecar
        data = load_json(path, "sidecar")
    except (UserError, OSError):
        return None
    return data if isinstance(data, dict) else None
