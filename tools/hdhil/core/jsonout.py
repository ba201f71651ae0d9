"""The one JSON writer of hdhil's machine-readable output: always valid JSON (RFC 8259).

A run whose dynamics blow up yields NaN or infinite numbers, which :func:`json.dumps`
would print as ``NaN`` / ``Infinity``: tokens that strict parsers and ``jq`` refuse.
:func:`dumps` and :func:`dump` write every non-finite number (Python or NumPy float,
NumPy arrays included) as ``null``; when the top level is an object and anything was
replaced, they add ``"non_finite"``: the list of the JSON paths replaced (``$.summary.x``,
``$.laws[0].rms``, ``$["odd key"]``), so a reader can tell "not a number" from "not
reported".  The text is then encoded with ``allow_nan=False``: a value this module
missed fails loudly instead of printing an invalid token.  For finite data the output is
exactly what :func:`json.dumps` gives with the same keyword arguments.

:func:`restore` turns the paths of a ``non_finite`` note back into NaN, for hdhil's own
stored records that it reads again.
"""

from __future__ import annotations

import json
import math
import re
from typing import IO, Any

__all__ = ["NOTE", "dump", "dumps", "finite", "restore"]

#: The top-level key listing the JSON paths of the numbers written as ``null``.
NOTE = "non_finite"

_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_STEP = re.compile(r'\.([A-Za-z_][A-Za-z0-9_]*)|\[(\d+)\]|\[("(?:[^"\\]|\\.)*")\]')


def _key_step(key: Any) -> str:
    text = key if isinstance(key, str) else json.dumps(key)
    if isinstance(key, str) and _IDENT.match(key):
        return f".{key}"
    return f"[{json.dumps(text)}]"


def _numpy_plain(value: Any) -> Any:
    """A NumPy scalar or array as the Python value or list it stands for; else ``value``."""
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        return value.tolist()
    return value


def _clean(value: Any, path: str, found: list[str]) -> Any:
    value = _numpy_plain(value)
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        found.append(path)
        return None
    if isinstance(value, dict):
        return {k: _clean(v, path + _key_step(k), found) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v, f"{path}[{i}]", found) for i, v in enumerate(value)]
    return value


def finite(obj: Any) -> tuple[Any, list[str]]:
    """``obj`` with every non-finite float as ``None``, and the JSON paths replaced."""
    found: list[str] = []
    return _clean(obj, "$", found), found


def dumps(obj: Any, **kw: Any) -> str:
    """:func:`json.dumps` of ``obj`` with non-finite numbers as ``null`` (and the
    ``non_finite`` note on a top-level object); ``allow_nan`` is always False."""
    clean, found = finite(obj)
    if found and isinstance(clean, dict):
        clean[NOTE] = found
    kw["allow_nan"] = False
    return json.dumps(clean, **kw)


def dump(obj: Any, fp: IO[str], **kw: Any) -> None:
    """:func:`dumps` written to ``fp``."""
    fp.write(dumps(obj, **kw))


def restore(data: Any) -> Any:
    """``data`` read back from :func:`dumps`: the ``non_finite`` note removed and the
    numbers at its paths set to NaN again (an infinity comes back as NaN)."""
    if not isinstance(data, dict) or not isinstance(data.get(NOTE), list):
        return data
    paths = data.pop(NOTE)
    for path in paths:
        steps = _parse(path) if isinstance(path, str) else None
        if not steps:
            continue
        node: Any = data
        for step in steps[:-1]:
            node = _child(node, step)
        last = steps[-1]
        if _child(node, last, missing=0) is None:
            node[last] = math.nan
    return data


def _child(node: Any, step: str | int, missing: Any = None) -> Any:
    """``node[step]`` if ``node`` has it (a key of an object, an index of a list)."""
    if isinstance(node, dict) and isinstance(step, str):
        return node.get(step, missing)
    if isinstance(node, list) and isinstance(step, int) and step < len(node):
        return node[step]
    return missing


def _parse(path: str) -> list[str | int] | None:
    """The keys and indices of a path written by :func:`dumps`; None if it is not one."""
    if not path.startswith("$"):
        return None
    steps: list[str | int] = []
    pos = 1
    while pos < len(path):
        m = _STEP.match(path, pos)
        if m is None:
            return None
        name, index, quoted = m.groups()
        steps.append(name if name is not None else int(index) if index else json.loads(quoted))
        pos = m.end()
    return steps
