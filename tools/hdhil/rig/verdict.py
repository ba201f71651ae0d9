"""Why a run stopped before its planned end: every early stop is a verdict.

A run that ends before its planned number of cycles without being interrupted has been
stopped by a fault reaction of the controller (module docstring of
:mod:`hdhil.firmware.controller`: phase "safe" or "stopped").  :func:`stop_verdict` says
which node reacted, why (the reason of the phase change), at which cycle and time, and
which EMCY was involved: the last the controller sent (its 0x1003 error history) and the
last it received (from the drive).  A drive whose plant went non-finite
(:class:`hdhil.hostsim.plant.NonFiniteStateError`) faults, and its reason (what went
non-finite, when) is the verdict.  ``hdhil run``, ``firmware``, ``emulate`` and ``soak``
print it in their text and JSON output and exit with code 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hdhil.canopen.services import emcy_text


def _emcy(code: int | None, node: int | None, time_s: float | None = None) -> dict[str, Any] | None:
    if code is None:
        return None
    out: dict[str, Any] = {"code": f"0x{code:04X}", "text": emcy_text(code), "node": node}
    if time_s is not None:
        out["time_s"] = time_s
    return out


def last_emcy_received(services: Any) -> dict[str, Any] | None:
    """The newest EMCY a node's CiA 301 services received, or ``None``."""
    log = getattr(services, "emcy_log", None)
    if not log:
        return None
    ev = log[-1]
    return _emcy(ev.code, ev.node_id, ev.time)


def last_emcy_sent(services: Any, node_id: int) -> dict[str, Any] | None:
    """The newest entry of a node's error history (0x1003), or ``None``."""
    history = services.emcy.history
    history = history() if callable(history) else history
    return _emcy(history[0] & 0xFFFF, node_id) if history else None


def plant_failure(drive: Any) -> str | None:
    """Why ``drive``'s plant could not be advanced (its state went non-finite, with the
    time), or ``None``: :attr:`hdhil.hostsim.drive.DriveDiagnostics.plant_failure`."""
    return getattr(getattr(drive, "diagnostics", None), "plant_failure", None)


def stop_verdict(
    controller: Any, cycles_planned: int, cycles_done: int, sample_period_s: float
) -> dict[str, Any] | None:
    """The verdict of a run that stopped at ``cycles_done`` of ``cycles_planned`` cycles,
    or ``None`` if it completed."""
    if cycles_done >= cycles_planned:
        return None
    d = controller.diagnostics
    reason = d.safe_reason
    if reason is None and d.phase_history:
        reason = d.phase_history[-1].reason
    if getattr(controller, "boot_error", None):
        reason = controller.boot_error
    return {
        "stopped_early": True,
        "node": getattr(controller, "node_id", 1),
        "phase": str(getattr(controller.phase, "value", controller.phase)),
        "reason": reason or f"controller left operation (phase {controller.phase})",
        "cycle": cycles_done,
        "cycles_planned": cycles_planned,
        "time_s": cycles_done * sample_period_s,
        "emcy_sent": last_emcy_sent(controller.services, getattr(controller, "node_id", 1)),
        "emcy_received": last_emcy_received(controller.services),
    }


def with_plant_failure(
    verdict: dict[str, Any] | None,
    drives: Sequence[Any],
    cycles_planned: int,
    cycles_done: int,
    sample_period_s: float,
) -> dict[str, Any] | None:
    """``verdict`` (None: the run completed) with the first drive whose plant could not
    be advanced (:func:`plant_failure`) as its reason: node, phase ``plant``, what went
    non-finite and when (also under ``plant_failure``).  A run whose plant failed has a
    verdict even if it reached its planned end; ``verdict`` unchanged without one."""
    failed = [(d, why) for d in drives if (why := plant_failure(d))]
    if not failed:
        return verdict
    drive, why = failed[0]
    out = (
        dict(verdict)
        if verdict is not None
        else {
            "stopped_early": cycles_done < cycles_planned,
            "cycle": cycles_done,
            "cycles_planned": cycles_planned,
            "time_s": cycles_done * sample_period_s,
            "emcy_sent": None,
            "emcy_received": None,
        }
    )
    node = getattr(getattr(drive, "config", None), "node_id", None)
    out["node"] = node if node is not None else getattr(drive, "node_id", 2)
    out["phase"] = "plant"
    out["reason"] = why
    out["plant_failure"] = why
    return out


def dcf_refused(controller: Any) -> bool:
    """Whether the controller's boot failed because the drive refused a value of the
    user's DCF (an input error, exit code 2), rather than on the bus (an SDO timeout,
    abort 0x05040000: a stop, exit code 1)."""
    conf = getattr(controller, "configurator", None)
    error = getattr(conf, "error", None)
    return bool(error) and "abort 0x05040000" not in error


def startup_verdict(
    controller: Any,
    reason: str,
    node: int | None,
    startup_cycles: int,
    cycles_planned: int,
    sample_period_s: float,
) -> dict[str, Any]:
    """The verdict of a run whose start-up failed: ``node`` (the drive that did not reach
    "operation enabled", or the controller's own id), phase ``start-up``, ``reason``, the
    start-up cycles spent, and the EMCYs as in :func:`stop_verdict`.  The run did no
    cycle in operation: ``cycle`` is 0."""
    own = getattr(controller, "node_id", 1)
    return {
        "stopped_early": True,
        "node": node if node is not None else own,
        "phase": "start-up",
        "controller_phase": str(getattr(controller.phase, "value", controller.phase)),
        "reason": reason,
        "cycle": 0,
        "cycles_planned": cycles_planned,
        "startup_cycles": startup_cycles,
        "time_s": 0.0,
        "emcy_sent": last_emcy_sent(controller.services, own),
        "emcy_received": last_emcy_received(controller.services),
    }


def format_verdict(verdict: dict[str, Any]) -> str:
    """One line: ``stopped early at cycle N of M (t s) by node n (phase): reason; EMCY ...``."""
    where = (
        f"at cycle {verdict['cycle']} of {verdict['cycles_planned']} "
        if "cycle" in verdict
        else "at "
    )
    if verdict.get("phase") == "start-up":
        parts = [
            f"stopped in start-up after {verdict.get('startup_cycles', 0)} cycles, none of "
            f"the {verdict.get('cycles_planned', 0)} planned run, by node {verdict['node']}: "
            f"{verdict['reason']}"
        ]
    else:
        parts = [
            f"stopped early {where}({verdict['time_s']:.3f} s) by node {verdict['node']} "
            f"({verdict['phase']}): {verdict['reason']}"
        ]
    for key, what in (("emcy_received", "EMCY received"), ("emcy_sent", "EMCY sent")):
        e = verdict.get(key)
        if e:
            parts.append(f"{what} {e['code']} ({e['text']}), node {e['node']}")
    return "; ".join(parts)


def drive_verdict(drive: Any) -> dict[str, Any] | None:
    """The verdict of a drive emulator that ended in a CiA 402 fault (its fault reaction),
    or ``None``.  The EMCY is the newest error the drive signalled."""
    state = drive.drive_state
    name = getattr(state, "name", str(state))
    if name not in ("FAULT", "FAULT_REACTION_ACTIVE"):
        return None
    log = drive.diagnostics.emcy_log
    last = log[-1] if log else None
    why = plant_failure(drive)
    return {
        "stopped_early": True,
        "node": getattr(drive, "node_id", 2),
        "phase": name.lower(),
        "reason": f"drive in CiA 402 {name.replace('_', ' ')}" + (f": {why}" if why else ""),
        "time_s": drive.plant.time,
        "emcy_sent": _emcy(last.code, getattr(drive, "node_id", 2), last.time) if last else None,
        "emcy_received": last_emcy_received(drive.services),
    }
