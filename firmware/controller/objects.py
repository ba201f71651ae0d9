"""The controller's own object dictionary: what it holds and when its values change.

The communication values the node runs with (0x1006, 0x1019), the firmware parameters
that SDO may change and their application at the cycle boundary, the mirrors of the
controlword and of the drive's statusword, the validity of the control telemetry PDO,
and the PDO mapping taken from the drive's DCF.  Kept apart from the frames so that the
per-cycle code touches the object dictionary only through one check for new parameters
(:meth:`ControllerObjects.apply_pending`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from hdhil.canopen.cia402 import CONTROLWORD_OBJECT
from hdhil.canopen.mapping import dcf_layouts, peer_pdo_writes
from hdhil.canopen.od import index_of
from hdhil.canopen.pdo import PdoLayout
from hdhil.canopen.sdo import ABORT_DEVICE_STATE
from hdhil.canopen.services import ResetKind
from hdhil.firmware.parameters import LiveParameters, Parameter, apply_config, store_value

if TYPE_CHECKING:
    from hdhil.firmware.controller.node import ControllerNode

__all__ = ["ControllerObjects"]


class ControllerObjects:
    """The controller's object dictionary and its live parameters.

    0x1006 (communication cycle period) holds the running period and 0x1019 the SYNC
    counter overflow; neither can be changed over SDO (abort 0x08000022): the runner
    paces the cycle and the drive's SYNC consumer expects the overflow.  PDO-mapped
    process data (ADC counts, telemetry) is not mirrored into the OD; the controlword
    (0x6040) and the drive's statusword (0x2011) are, when they change.

    Live parameters: objects 0x2400-0x2430 hold the firmware parameters
    (:data:`hdhil.firmware.parameters.PARAMETERS`), checked and staged by
    :class:`hdhil.firmware.parameters.LiveParameters`.  Accepted writes are applied at the
    next cycle boundary (``tick`` or ``send_sync``, whichever comes first) by
    :func:`hdhil.firmware.parameters.apply_config`:

    - reference generator (0x2400): rebuilt; the wave continues at the present sample;
    - ``num_samples`` (0x2401:1): the new limit counts from the first operational sample;
    - ripple filter (0x2410): the filter chain is rebuilt, **the ripple Kalman filter
      restarts** from P0 (its learned ripple is lost); the differentiator and the encoder
      unwrapping carry over.  Writing ``mode`` gives the mode's default tuning for the
      same harmonics (:func:`hdhil.firmware.config.paper_config` /
      ``recommended_config``), and the OD's r, residual_q and q_i follow it;
    - control law (0x2420:1): the LQG stage is rebuilt (observer from rest);
      ``CTRL_TPDO2`` is sent only while a law is active and 0x1801:1 bit 31 follows; the
      desired torque's amplitude/frequency only swap the desired-torque generator;
    - calibration (0x2430): used from the next sample on.

    The drive's mapping: with a DCF, this node's own PDOs get the matching mapping
    (:func:`hdhil.canopen.mapping.peer_pdo_writes`: the drive's TPDO is this node's RPDO
    with the same COB-ID, objects matched by name), written through the CiA 301 checks.
    """

    def __init__(self, node: ControllerNode) -> None:
        self.node = node
        services = node.services
        #: The controller's own controlword mirror, by name (CiA 402 object 0x6040).
        self.controlword_index = index_of(services.od, CONTROLWORD_OBJECT)
        self.period_us = round(node.config.sample_period_s * 1e6)
        self.store_comm_values()
        if node.sync_producer:
            services.make_sync_producer()
        self.parameters = LiveParameters(services, lambda: node.config, self._on_parameter)
        self.parameters.store(node.config)
        self.parameters.enabled = node.own_isr
        services.add_validator(0x1006, 0, self._check_cycle_period)
        #: The drive's PDOs as its DCF leaves them (empty without a DCF), and the writes
        #: that gave this node's own PDOs the matching mapping (empty: the default).
        self.drive_layouts: dict[tuple[str, int], PdoLayout] = {}
        self.pdo_writes: list[tuple[int, int, int]] = []

    def take_drive_mapping(self, drive_dcf: str | Path) -> None:
        """Give this node's PDOs the mapping of the drive's DCF (class docstring).  Raises
        ``ValueError`` for a mapping the controller cannot take."""
        services = self.node.services
        from hdhil.canopen.rigdb import RigDrive, drive_pdo_layouts

        node_id = self.node.drive_node_id
        drive_od, _ = dcf_layouts(drive_dcf, node_id)
        # the drive's PDOs at its node-ID (the COB-IDs _address_drive gave this node's)
        self.drive_layouts = drive_pdo_layouts(RigDrive("", node_id, dcf=drive_dcf))
        self.pdo_writes = peer_pdo_writes(services.od, services.read, drive_od, self.drive_layouts)
        for index, sub, value in self.pdo_writes:
            try:
                services.write(index, sub, value)
            except Exception as exc:
                raise ValueError(
                    f"the controller cannot take 0x{index:04X}:{sub:02X} = 0x{value:X} "
                    f"for the drive's mapping: {exc}"
                ) from None

    # ------------------------------------------------------------------ values

    def store_comm_values(self) -> None:
        """0x1006 = the sample period (µs) and 0x1019 = the SYNC counter overflow."""
        services = self.node.services
        store_value(services, 0x1006, 0, self.period_us)
        store_value(services, 0x1019, 0, self.node.sync_overflow)

    def store_control_pdo_validity(self) -> None:
        """0x1801:1 bit 31 (PDO not valid) follows ``node.control_pdo_valid``."""
        services = self.node.services
        cob = services.read(0x1801, 1)
        cob = cob & ~0x80000000 if self.node.control_pdo_valid else cob | 0x80000000
        store_value(services, 0x1801, 1, cob)

    def mirror_controlword(self, controlword: int) -> None:
        store_value(self.node.services, self.controlword_index, 0, controlword)

    def mirror_statusword(self, statusword: int) -> None:
        store_value(self.node.services, 0x2011, 0, statusword)

    def restore_after_reset(self, kind: ResetKind) -> None:
        """After an NMT reset by another master: OD values back to what the node runs
        (the EDS defaults would not be)."""
        node = self.node
        self.store_comm_values()
        sync = node.services.sync
        if sync is not None:
            sync.configure(overflow=node.sync_overflow, cob_id=sync.cob_id)
        if kind == "node":
            self.parameters.store(self.parameters.pending or node.config)
        self.store_control_pdo_validity()

    def _check_cycle_period(self, value: int) -> int | None:
        """0x1006 holds the running period: the runner paces the cycle.  Refusing 0 also
        keeps 0x1019 fixed (CiA 301: writable only while 0x1006 is 0), which the drive's
        SYNC consumer is configured with."""
        return None if value == self.period_us else ABORT_DEVICE_STATE

    # ---------------------------------------------------------- live parameters

    def _on_parameter(self, _: Parameter) -> None:
        self.node.diagnostics.parameter_writes += 1

    def apply_pending(self) -> None:
        """Swap the changed stages in at the cycle boundary (class docstring)."""
        params = self.parameters
        if params.pending is None:  # nearly every cycle: nothing was written
            return
        new = params.take_pending()
        if new is None:
            return
        node = self.node
        old = node.config
        prebuilt = None
        if new.control != old.control:
            prebuilt, params.prebuilt_control = params.prebuilt_control, None
        node.config = new
        done = apply_config(node.isr, old, new, prebuilt)
        d = node.diagnostics
        if done.filter_restarted:
            d.filter_restarts += 1
        if done.control_rebuilt:
            d.control_rebuilds += 1
        if done.control_changed:
            node.control_pdo_valid = new.control.active
            self.store_control_pdo_validity()
        d.parameter_updates_applied += 1
