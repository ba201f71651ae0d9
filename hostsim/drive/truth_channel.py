"""The drive's truth publisher: the plant's ground truth on the truth channel.

Every SYNC in OPERATIONAL, right after the sensor TPDO, the drive sends ``TRUTH_TORQUE``
(torque and ripple), ``TRUTH_MOTION`` (angles, wrapped to [0, 2 pi), and velocities) and
``TRUTH_JOINT`` (``tau_ext = tau_l + tau_g`` and ``tau_d`` of [Vertechy] Eq. 1,
``tau_m`` acting and commanded), all from the :class:`~hdhil.hostsim.plant.truth.Truth`
the plant gives at t(k), like the sensors. Ground truth goes to a bus of its own
(``truth.dbc``), never to the control bus: the firmware never reads it; the scorer does.
"""

from __future__ import annotations

import math

import can

from hdhil.dbc import codec, truth_frame_id
from hdhil.hostsim.plant.truth import Truth

__all__ = ["TruthPublisher"]

TWO_PI = 2.0 * math.pi


class TruthPublisher:
    """Encodes a :class:`Truth` into the three truth frames and sends them on ``bus``;
    the rig's ``joint_index``-th joint at its own identifiers
    (:func:`hdhil.dbc.truth_frame_id`: joint 0 at ``truth.dbc``'s)."""

    def __init__(self, bus: can.BusABC | None, joint_index: int = 0) -> None:
        self.bus = bus
        # Codecs are used by signal name: a DBC with reordered signals fails here, loudly.
        self._codecs = (
            codec("truth", "TRUTH_TORQUE").expect("T_true", "T_ripple"),
            codec("truth", "TRUTH_MOTION").expect(
                "theta_motor", "theta_output", "omega_motor", "omega_output"
            ),
            codec("truth", "TRUTH_JOINT").expect("tau_ext", "tau_d", "tau_m", "tau_m_cmd"),
        )
        #: The three frames' identifiers (TRUTH_TORQUE, TRUTH_MOTION, TRUTH_JOINT).
        self.ids = tuple(truth_frame_id(joint_index, c.frame_id) for c in self._codecs)
        self._msgs = tuple(
            can.Message(arbitration_id=i, is_extended_id=True, dlc=c.length, check=False)
            for i, c in zip(self.ids, self._codecs, strict=True)
        )

    @property
    def bus(self) -> can.BusABC | None:
        """The truth channel; None: nothing is published."""
        return self._bus

    @bus.setter
    def bus(self, bus: can.BusABC | None) -> None:
        self._bus = bus
        # A channel of frame groups (hdhil.can.groups, the in-process truth channel of a
        # lockstep run) takes the three payloads as one group; the simulated bus a
        # cycle's frames in one call; any other bus one by one.
        self._send_group = getattr(bus, "send_group", None)
        self._send_frames = getattr(bus, "send_frames", None) or self._send_each

    def _send_each(self, msgs: tuple[can.Message, ...]) -> None:
        send = self._bus.send  # type: ignore[union-attr]
        for msg in msgs:
            send(msg)

    def publish(self, t: Truth) -> None:
        """Send the three truth frames of ``t`` (the bus must be set)."""
        torque, motion, joint = self._codecs
        # The first ten fields by position (Truth's order), in one unpacking.
        T_true, th_m, th_o, w_m, w_o, tau_m, tau_m_cmd, T_ripple, tau_ext, tau_d = t[:10]
        d_torque = torque.encode(T_true, T_ripple)
        d_motion = motion.encode(th_m % TWO_PI, th_o % TWO_PI, w_m, w_o)
        d_joint = joint.encode(tau_ext, tau_d, tau_m, tau_m_cmd)
        if self._send_group is not None:
            self._send_group(self.ids, True, (d_torque, d_motion, d_joint))
            return
        m_torque, m_motion, m_joint = self._msgs
        m_torque.data, m_motion.data, m_joint.data = d_torque, d_motion, d_joint
        self._send_frames(self._msgs)
