"""One notation for the axis labels of every figure hdhil draws (``hdhil plot``,
``calibrate --plot``, ``identify --plot``, the campaign plots).

A label is the quantity in words, then its unit in parentheses: ``torque (N·m)``,
``angular frequency (rad/s)``, ``frequency (Hz)``; a dimensionless quantity has no
parentheses.  Symbols are matplotlib mathtext (``$\\tau_l$``).  :func:`key_label` turns a
dotted configuration or metric key with a unit suffix (``eval_rms_err_Nm``,
``faults.control.loss_rate``) into that form when no words are given for it.
"""

from __future__ import annotations

import re

__all__ = ["NM", "UNIT_OF_SUFFIX", "axis_label", "key_label", "split_unit"]

#: The torque unit as written on every figure.
NM = "N·m"

#: Key suffixes that name a unit, and the unit as written on a figure.
UNIT_OF_SUFFIX: dict[str, str] = {
    "Nm": NM,
    "Nms": "N·m·s",
    "dB": "dB",
    "radps": "rad/s",
    "rad": "rad",
    "deg": "deg",
    "s": "s",
    "ms": "ms",
    "us": "µs",
    "Hz": "Hz",
    "V": "V",
    "A": "A",
    "pct": "%",
}

_PLAIN = re.compile(r"[A-Za-z0-9]")


def axis_label(quantity: str, unit: str = "") -> str:
    """``quantity (unit)``, or the quantity alone for a dimensionless one."""
    return f"{quantity} ({unit})" if unit else quantity


def split_unit(key: str) -> tuple[str, str]:
    """A key's stem and the unit its last ``_`` suffix names (``""`` when none):
    ``("eval_rms_err", "N·m")`` for ``eval_rms_err_Nm``."""
    stem, sep, suffix = key.rpartition("_")
    if sep and stem and suffix in UNIT_OF_SUFFIX:
        return stem, UNIT_OF_SUFFIX[suffix]
    return key, ""


def key_label(key: str, words: dict[str, str] | None = None) -> str:
    """The axis label of a dotted key: ``words[key]`` if given (the quantity in words,
    its unit still taken from the key's suffix), else the key's last two parts with
    underscores as spaces (``faults.control.loss_rate`` → ``control loss rate``)."""
    stem, unit = split_unit(key)
    if words and key in words:
        return axis_label(words[key], unit)
    parts = [p for p in stem.split(".") if _PLAIN.search(p)]
    text = " ".join(parts[-2:]).replace("_", " ") if parts else stem
    return axis_label(text, unit)
