"""hdhil: a hardware-in-the-loop emulator for joint-torque sensing and control of
harmonic-drive robot joints over CAN.

The public API (``docs/api.md``): resolve a scenario into a run request, run it, read and
score traces, and plug in your own plant or controller::

    import hdhil

    result = hdhil.run("free-motion", duration_s=1.0, trace="run.blf")
    print(result.headline)

Names are imported on first use, so ``import hdhil`` (and every command's start-up)
stays cheap.
"""

from __future__ import annotations

import importlib

# typing only for type checkers: this runs before the console's first Ctrl-C handler is
# in place (hdhil.console), so it imports nothing it does not need.
TYPE_CHECKING = False
if TYPE_CHECKING:
    from typing import Any

#: Public name -> the module that defines it.
_EXPORTS = {
    # run model
    "Scenario": "hdhil.rig.scenario",
    "load_scenario": "hdhil.api",
    "list_scenarios": "hdhil.rig.scenario",
    "RunRequest": "hdhil.rig.request",
    "resolve": "hdhil.api",
    "run": "hdhil.api",
    "RunResult": "hdhil.rig.result",
    # traces and scores
    "read_trace": "hdhil.api",
    "evaluate_trace": "hdhil.api",
    "cycle_arrays": "hdhil.api",
    # plug-ins: factories, the protocols a plant or an interrupt handler follows
    "NodeSite": "hdhil.rig.factories",
    "RigLayout": "hdhil.rig.factories",
    "DriveSlot": "hdhil.rig.factories",
    "ControllerFactory": "hdhil.rig.factories",
    "DriveFactory": "hdhil.rig.factories",
    "PlantModel": "hdhil.hostsim.plant_model",
    "InterruptHandlerModel": "hdhil.firmware.interrupt",
    # the nodes
    "ControllerNode": "hdhil.firmware.controller",
    "DriveNode": "hdhil.hostsim.drive",
}

__all__ = [*sorted(_EXPORTS), "__version__"]


def __getattr__(name: str) -> Any:
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("hdhil")
        except PackageNotFoundError:
            return "unknown"
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'hdhil' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
