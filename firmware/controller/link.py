"""How a controller node addresses one drive: the drive's node-ID and the joint's PDOs.

A :class:`DriveLink` is the seam between a joint of the controller
(:class:`~hdhil.firmware.controller.joint.ControllerJoint`) and the frames on the bus:
which node the sequencer walks (NMT, heartbeat, SDO), which identifiers carry that
drive's sensor frame, statusword and command, and which carry the controller's telemetry
of the joint.  The default is the single-joint link of ``control.dbc`` (drive node-ID 2,
controller node-ID 1); :meth:`DriveLink.predefined` numbers the PDOs of any drive and
joint rank as :mod:`hdhil.canopen.rigdb` does.
"""

from __future__ import annotations

from dataclasses import dataclass

from hdhil.dbc import predefined_cob_id

__all__ = ["MAX_JOINTS_PER_NODE", "DriveLink"]

#: The controller's telemetry of its ``r``-th joint is its TPDO(2r+1) and TPDO(2r+2) of
#: the CiA 301 pre-defined connection set, which gives a node four TPDOs: one controller
#: node reports (so serves) at most two joints.
MAX_JOINTS_PER_NODE = 2


@dataclass(frozen=True)
class DriveLink:
    """The drive a joint commands and the identifiers of the joint's PDOs.

    ``sensor_cob_id`` (the drive's TPDO1, the sensor frame), ``status_cob_id`` (its TPDO2,
    the statusword) and ``command_cob_id`` (its RPDO1) are the drive's PDOs;
    ``telemetry_cob_id`` and ``control_cob_id`` the controller's telemetry of this joint
    (``CTRL_TPDO1``, ``CTRL_TPDO2``).  The defaults are ``control.dbc``'s.
    """

    node_id: int = 2
    sensor_cob_id: int = 0x182
    status_cob_id: int = 0x282
    command_cob_id: int = 0x202
    telemetry_cob_id: int = 0x181
    control_cob_id: int = 0x281

    def __post_init__(self) -> None:
        if isinstance(self.node_id, bool) or not 1 <= self.node_id <= 127:
            raise ValueError(f"drive node-ID must be 1..127, got {self.node_id!r}")
        ids = self.cob_ids
        for cob in ids:
            if isinstance(cob, bool) or not 0x001 <= cob <= 0x7FF:
                raise ValueError(f"a PDO identifier must be 0x001..0x7FF, got {cob!r}")
        if len(set(ids)) != len(ids):
            raise ValueError(f"drive (node {self.node_id}): two PDOs share an identifier")

    @property
    def cob_ids(self) -> tuple[int, ...]:
        """Every identifier of the link: sensor, status, command, telemetry, control."""
        return (self.sensor_cob_id, self.status_cob_id, self.command_cob_id,
                self.telemetry_cob_id, self.control_cob_id)  # fmt: skip

    @classmethod
    def predefined(cls, node_id: int, controller_node_id: int = 1, rank: int = 0) -> DriveLink:
        """The link of the drive at ``node_id`` served as the ``rank``-th joint (0-based)
        of the controller node ``controller_node_id``, in CiA 301's pre-defined connection
        set (:mod:`hdhil.canopen.rigdb`): the drive's TPDO1, TPDO2 and RPDO1, the
        controller's TPDO(2 rank + 1) and TPDO(2 rank + 2).  Rank 0 of drive 2 under
        controller 1 is the default link."""
        if not 0 <= rank < MAX_JOINTS_PER_NODE:
            raise ValueError(
                f"a controller node reports the telemetry of at most {MAX_JOINTS_PER_NODE} "
                f"joints (its four pre-defined TPDOs), got joint rank {rank}: give the "
                "joint a controller node of its own"
            )
        return cls(
            node_id=node_id,
            sensor_cob_id=predefined_cob_id("tpdo", 1, node_id),
            status_cob_id=predefined_cob_id("tpdo", 2, node_id),
            command_cob_id=predefined_cob_id("rpdo", 1, node_id),
            telemetry_cob_id=predefined_cob_id("tpdo", 2 * rank + 1, controller_node_id),
            control_cob_id=predefined_cob_id("tpdo", 2 * rank + 2, controller_node_id),
        )
