"""Node factories: the seam through which the runner gets its nodes.

:func:`hdhil.rig.runner.run_lockstep` opens the buses, then asks one
:class:`ControllerFactory` for the controller and one :class:`DriveFactory` per entry
of :attr:`RigLayout.drives` for the drives; it never builds a node itself. Node-IDs and
the bus each drive sits on come from the :class:`RigLayout` (configuration), so a
second drive, or a drive on a second bus, is a layout entry, not a change of the runner.

The default factories (:func:`scenario_controller`, :func:`scenario_drive`) build what
the scenario describes: the firmware's :class:`firmware.controller.ControllerNode` with
its interrupt handler, and :class:`hostsim.drive.DriveNode` around the emulator's
:class:`hostsim.plant.Plant`. Your own plant is a :class:`DriveFactory` that wraps any
:class:`hdhil.hostsim.plant_model.PlantModel` in a ``DriveNode``; your own controller
law is a :class:`ControllerFactory` that hands the ``ControllerNode`` an interrupt
handler of your own (:class:`hdhil.firmware.interrupt.InterruptHandlerModel`). Example
(README, "Plugging in a plant")::

    def rigid_drive(site: NodeSite) -> DriveNode:
        return DriveNode(site.bus, RigidInertia(), site.drive_config(), truth_bus=site.truth_bus)

    run_lockstep(resolve("free-motion"), drive_factories=[rigid_drive])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

import can

from hdhil.can.groups import GroupChannel
from hdhil.core.dataconf import ConfigError
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode, JointSetup
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant
from hdhil.rig.faults import FaultInjector
from hdhil.rig.scenario import Scenario

#: The buses a node can sit on: the CAN control bus, and the truth channel that exists
#: only in simulation (ground truth for scoring; the firmware never reads it).
BusName = Literal["control"]


@dataclass(frozen=True)
class DriveSlot:
    """One drive of the rig: its CANopen node-ID and the bus it sits on."""

    node_id: int = 2
    bus: BusName = "control"

    def __post_init__(self) -> None:
        if isinstance(self.node_id, bool) or not 1 <= self.node_id <= 127:
            raise ValueError(f"drive node-ID must be 1..127, got {self.node_id!r}")
        if self.bus != "control":
            raise ValueError(f"a drive sits on a control bus, got {self.bus!r}")


@dataclass(frozen=True)
class RigLayout:
    """Who is on which bus: the controller's node-ID and the drives.

    Each node's PDO COB-IDs follow its node-ID (the EDS files' ``$NODEID+0x180`` etc.,
    CiA 301's pre-defined connection set), the layouts stay the DBC's
    (:func:`hdhil.can.node.pdo_cob_id`); the controller addresses its drive at the
    drive's node-ID.  The run's scorers, its trace's sidecar and the tools that decode
    the trace follow the layout."""

    controller_node_id: int = 1
    drives: tuple[DriveSlot, ...] = field(default_factory=lambda: (DriveSlot(),))

    def __post_init__(self) -> None:
        if not self.drives:
            raise ValueError("the rig needs at least one drive")
        ids = [self.controller_node_id, *(d.node_id for d in self.drives)]
        if len(set(ids)) != len(ids):
            raise ValueError(f"node-IDs must be unique on the rig, got {ids}")


@dataclass(frozen=True)
class NodeSite:
    """Where a factory builds its node: the node's own handle on its bus (and on the
    truth channel, for a drive), its node-ID, the controller's node-ID (a drive
    monitors its heartbeat), the run's sample period, noise seed, SYNC actuation and
    fault injector (None: no faults)."""

    bus: can.BusABC
    node_id: int
    controller_node_id: int
    sample_period_s: float
    seed: int
    actuation: Literal["next-sync", "immediate"] = "next-sync"
    truth_bus: can.BusABC | GroupChannel | None = None
    faults: FaultInjector | None = None
    #: The node-IDs of the drives (what the controller addresses).
    drive_node_ids: tuple[int, ...] = ()
    #: Each drive's joint, in the order of ``drive_node_ids``: its name and firmware
    #: configuration (:func:`layout_joints`); empty: the run's configuration for each.
    joint_configs: tuple[tuple[str, FirmwareConfig], ...] = ()

    def drive_config(self) -> DriveConfig:
        """The drive node's settings for this site (period, actuation, node-IDs)."""
        return DriveConfig(
            sample_period_s=self.sample_period_s,
            actuation=self.actuation,
            node_id=self.node_id,
            controller_node_id=self.controller_node_id,
        )


class ControllerFactory(Protocol):
    """Builds the controller node (the SYNC producer) for a run."""

    def __call__(self, site: NodeSite, config: FirmwareConfig) -> ControllerNode:
        """The controller on ``site.bus`` with the run's firmware configuration."""
        ...


class DriveFactory(Protocol):
    """Builds one drive node for a run."""

    def __call__(self, site: NodeSite) -> DriveNode:
        """The drive on ``site.bus``, publishing truth on ``site.truth_bus`` (if any)."""
        ...


def layout_joints(scenario: Scenario, layout: RigLayout) -> tuple[tuple[str, FirmwareConfig], ...]:
    """The joint of each drive of ``layout``, in its order: the name and firmware
    configuration (filter, law, gains, calibration) of the scenario's joint with the
    drive's node-ID (``Scenario.joint_configs``); for a single-joint scenario, the
    scenario's firmware for every drive.  A drive no joint of the scenario has is a
    one-line :class:`ConfigError`."""
    if not scenario.is_rig:
        return tuple(("", scenario.firmware) for _ in layout.drives)
    out = []
    for slot in layout.drives:
        found = [
            (joint.name, fw)
            for joint, (_, fw) in zip(scenario.joints, scenario.joint_configs, strict=True)
            if joint.node_id == slot.node_id
        ]
        if len(found) != 1:
            names = ", ".join(name for name, _ in found) or "none"
            raise ConfigError(
                f"the layout's drive at node-ID {slot.node_id} must be one joint of scenario "
                f"{scenario.name} (joints with that node-ID: {names})"
            )
        out.append(found[0])
    return tuple(out)


def scenario_controller(site: NodeSite, config: FirmwareConfig) -> ControllerNode:
    """The firmware's controller node with its own interrupt handler per joint: one
    joint, or each drive of the layout as a joint with its own configuration
    (``site.joint_configs``) on one node (one NMT master and SYNC producer per bus)."""
    drives: Sequence[int] = site.drive_node_ids or (2,)
    joints = site.joint_configs or tuple(("", config) for _ in drives)
    if len(joints) != len(drives):
        raise ConfigError(f"{len(joints)} joint configurations for drives {list(drives)}")
    if len(drives) == 1:
        return ControllerNode(site.bus, joints[0][1], node_id=site.node_id,
                              drive_node_id=drives[0])  # fmt: skip
    setups = [
        JointSetup(cfg, node_id, name) for node_id, (name, cfg) in zip(drives, joints, strict=True)
    ]
    try:
        return ControllerNode(site.bus, node_id=site.node_id, joints=setups)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def dcf_controller(drive_dcf: Path) -> ControllerFactory:
    """The firmware's controller node configuring its drive at boot from ``drive_dcf``
    (CiA 306) and exchanging the PDOs that DCF maps (e.g. the CiA 402 CST mapping of
    ``dbc/drive-cst.dcf``)."""

    def make(site: NodeSite, config: FirmwareConfig) -> ControllerNode:
        drives: Sequence[int] = site.drive_node_ids or (2,)
        if len(drives) != 1:
            raise ValueError(
                f"a drive DCF configures one joint's drive; the layout has drives {list(drives)}"
            )
        return ControllerNode(
            site.bus, config, node_id=site.node_id, drive_node_id=drives[0], drive_dcf=drive_dcf
        )

    return make


def scenario_drive(scenario: Scenario) -> DriveFactory:
    """A factory of drives emulating ``scenario``'s plant (:class:`hostsim.plant.Plant`),
    with the run's sensor faults."""

    def make(site: NodeSite) -> DriveNode:
        injector = site.faults
        plant = Plant(scenario.plant, site.seed, faults=injector.sensors() if injector else None)
        return DriveNode(
            site.bus, plant, site.drive_config(), truth_bus=site.truth_bus, faults=injector
        )

    return make
