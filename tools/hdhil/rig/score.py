"""Scoring the firmware against ground truth, from what is on the buses.

The scorer is a python-can listener: it reads the controller's telemetry (``CTRL_TPDO1``)
from the control bus and the emulator's ``TRUTH_TORQUE`` from the truth channel, exactly
as a logger would, so a live run and a recorded trace are scored by the same code.  Each
telemetry frame of cycle k is paired with the latest truth frame, which the drive sent
when it sampled the sensors of cycle k (both describe the instant t(k)).

Running sums only: memory stays flat however long the run.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from hdhil.can.groups import FrameGroup
from hdhil.dbc import codec, predefined_cob_id, truth_frame_id

if TYPE_CHECKING:
    from hdhil.hostsim.plant import LinkMotionConfig


def _telemetry_id(number: int, controller_node_id: int) -> int:
    """The controller's telemetry TPDO ``number`` at its node-ID (CiA 301 pre-defined
    connection set, as its EDS sets it: ``$NODEID+0x180``, ``$NODEID+0x280``)."""
    return predefined_cob_id("tpdo", number, controller_node_id)


def _truth_at(frame: Any, joint_index: int) -> Any:
    """A truth codec at the identifier of the rig's ``joint_index``-th joint (joint 0:
    ``truth.dbc``'s own, the codec itself)."""
    return frame.at(truth_frame_id(joint_index, frame.frame_id))


@dataclass(frozen=True)
class TorqueScore:
    """RMS errors against the emulator's true transmitted torque ``T_true``."""

    samples: int
    rms_true: float
    rms_error_raw: float
    rms_error_filtered: float
    max_error_raw: float
    max_error_filtered: float

    @property
    def filtered_to_raw(self) -> float:
        """Filtered RMS error as a fraction of the raw (unfiltered) RMS error."""
        return self.rms_error_filtered / self.rms_error_raw if self.rms_error_raw else math.nan

    def as_dict(self) -> dict[str, float]:
        d = asdict(self)
        d["filtered_to_raw"] = self.filtered_to_raw
        return d


class TorqueScorer(can.Listener):
    """Accumulates raw and filtered torque errors from telemetry and truth frames.

    ``skip_s``: telemetry before this time (trace time) is not scored, e.g. to leave out
    the filter's start-up transient; ``skip_from_first_s``: nor is telemetry less than
    this long after the first telemetry frame (the first interrupt in operation; within
    half a ``sample_period_s``, as :class:`TrackingScorer` counts it, so that decimated
    telemetry starts where every-cycle telemetry would).  The defaults score everything.
    A joint of a rig: ``telemetry_id`` its ``CTRL_TPDO1`` (the controller's TPDO1 at
    ``controller_node_id`` by default) and ``joint_index`` its truth
    (:func:`hdhil.dbc.truth_frame_id`).
    """

    def __init__(
        self,
        skip_s: float = 0.0,
        block_s: float = 60.0,
        controller_node_id: int = 1,
        *,
        telemetry_id: int | None = None,
        joint_index: int = 0,
        skip_from_first_s: float = 0.0,
        sample_period_s: float = 1e-3,
    ) -> None:
        self.skip_s = skip_s
        #: Telemetry before this time (the first frame's plus ``skip_from_first_s``, less
        #: half a period) is not scored; set by the first telemetry frame.
        self._scored_from = -math.inf if not skip_from_first_s else math.inf
        self._skip_from_first = skip_from_first_s - 0.5 * sample_period_s
        #: Telemetry frames seen, scored or not.
        self.telemetry_frames = 0
        #: RMS filtered error per ``block_s`` of telemetry time (whether it drifts).
        self.block_s = block_s
        self.block_rms: list[float] = []
        self._block_sum = 0.0
        self._block_n = 0
        self._block_start: float | None = None
        self._block_end = block_s
        tele = codec("control", "CTRL_TPDO1").expect("T_meas", "T_filtered", "velocity", "current")
        tele = tele.at(telemetry_id or _telemetry_id(1, controller_node_id))
        truth = _truth_at(codec("truth", "TRUTH_TORQUE").expect("T_true", "T_ripple"), joint_index)
        self._tele_key = (tele.frame_id, False)
        self._truth_key = (truth.frame_id, True)
        self._tele = tele
        self._truth = truth
        self._keys = frozenset((self._tele_key, self._truth_key))
        self._T_true: float | None = None
        self._group_ids: tuple[int, ...] | None = None  # the last group's ids, and where
        self._group_at: int | None = None  # its truth frame is
        self.n = 0
        self._sum_true2 = 0.0
        self._sum_raw2 = 0.0
        self._sum_filt2 = 0.0
        self._max_raw = 0.0
        self._max_filt = 0.0
        #: Last and largest-magnitude motor velocity the telemetry reported (rad/s).
        self.velocity_final = 0.0
        self.velocity_peak = 0.0

    def on_message_received(self, msg: can.Message) -> None:
        key = (msg.arbitration_id, msg.is_extended_id)
        if key == self._truth_key and len(msg.data) == self._truth.length:
            self._T_true = self._truth.decode(msg.data)[0]
        elif key == self._tele_key and len(msg.data) == self._tele.length:
            T_meas, T_filtered, velocity, _current = self._tele.decode(msg.data)
            self.velocity_final = velocity
            if abs(velocity) > abs(self.velocity_peak):
                self.velocity_peak = velocity
            self.telemetry_frames += 1
            if self.telemetry_frames == 1 and self._scored_from == math.inf:
                self._scored_from = msg.timestamp + self._skip_from_first
            if (
                self._T_true is None
                or msg.timestamp < self.skip_s
                or msg.timestamp < self._scored_from
            ):
                return
            T_true = self._T_true
            # Each truth frame scores one telemetry frame: a cycle whose truth is missing
            # (truth faults) is not scored against the previous cycle's truth.
            self._T_true = None
            e_raw = T_meas - T_true
            e_filt = T_filtered - T_true
            self.n += 1
            self._sum_true2 += T_true * T_true
            self._sum_raw2 += e_raw * e_raw
            self._sum_filt2 += e_filt * e_filt
            self._max_raw = max(self._max_raw, abs(e_raw))
            self._max_filt = max(self._max_filt, abs(e_filt))
            if self._block_start is None:  # blocks count from the first scored frame
                self._block_start = msg.timestamp
                self._block_end = msg.timestamp + self.block_s
            elif msg.timestamp >= self._block_end:
                self._close_block()
                passed = (msg.timestamp - self._block_start) // self.block_s
                self._block_end = self._block_start + (passed + 1) * self.block_s
            self._block_sum += e_filt * e_filt
            self._block_n += 1

    #: :meth:`on_frames` takes :class:`FrameGroup` items (:class:`hdhil.can.traces.tap.
    #: BusTap`).
    takes_frame_groups = True

    def on_frames(self, frames: list[can.Message | FrameGroup]) -> None:
        """:meth:`on_message_received` for the telemetry and truth frames among ``frames``
        (and the truth frames of a frame group)."""
        keys = self._keys
        truth_key = self._truth_key
        truth_length = self._truth.length
        truth_decode = self._truth.decode
        tele_id = self._tele_key[0]
        for msg in frames:
            if msg.__class__ is FrameGroup:
                data = self._group_truth(msg)
                if data is not None and len(data) == truth_length:
                    self._T_true = truth_decode(data)[0]
                continue
            if not msg.is_extended_id and msg.arbitration_id != tele_id:
                continue  # most frames of a cycle: not a scored base frame
            key = (msg.arbitration_id, msg.is_extended_id)
            if key in keys:
                if key == truth_key and len(msg.data) == truth_length:  # the common case
                    self._T_true = truth_decode(msg.data)[0]
                else:
                    self.on_message_received(msg)

    def _group_truth(self, group: FrameGroup) -> bytes | None:
        """The payload of the truth frame in ``group``, or None."""
        ids = group.ids
        if ids is not self._group_ids:  # the drive sends the same tuple every cycle
            key_id = self._truth_key[0]
            self._group_at = ids.index(key_id) if key_id in ids else None
            self._group_ids = ids
        at = self._group_at
        return group.payloads[at] if at is not None and group.extended else None

    def _close_block(self) -> None:
        if self._block_n:
            self.block_rms.append(math.sqrt(self._block_sum / self._block_n))
        self._block_sum = 0.0
        self._block_n = 0

    def result(self) -> TorqueScore:
        """Totals so far; full blocks only in ``block_rms`` (a partial last block is left out)."""
        n = self.n
        if not n:
            return TorqueScore(0, math.nan, math.nan, math.nan, math.nan, math.nan)
        return TorqueScore(
            samples=n,
            rms_true=math.sqrt(self._sum_true2 / n),
            rms_error_raw=math.sqrt(self._sum_raw2 / n),
            rms_error_filtered=math.sqrt(self._sum_filt2 / n),
            max_error_raw=self._max_raw,
            max_error_filtered=self._max_filt,
        )


#: [Vertechy] §VI ([Vertechy]), the experiment: "the proposed controller
#: is able to keep the torque sensor tracking error e within ±0.5 Nm" (Nm).
TRACKING_GOAL_NM = 0.5


@dataclass(frozen=True)
class TrackingScore:
    """Joint-torque tracking against truth ([Vertechy] §VI).

    - ``max_abs_error`` / ``rms_error``: ``e = T_true − T_desired`` (the seed's tracking
      error e; Fig. 8, third panel: "within ±0.5 Nm");
    - ``rms_disturbance_error``: the observer's third state against its truth: ``τlgd =
      τl + τg − τd Jl/Jm`` (Eq. 4), or ``τlg = τl + τg`` with friction compensation
      (Eq. 5, seed §V);
    - ``max_external_error`` / ``rms_external_error``: the same estimate against the
      handle torque ``τl^m`` (plus ``τg``), what a sensor in the handle measures:
      ``TRUTH_JOINT.tau_ext`` less the friction of the output-shaft bearings between
      the torque sensor and the handle (``[plant.link] bearing_coulomb_Nm``) at the
      link velocity ``TRUTH_MOTION.omega_output``, ``tau_ext`` itself where there is
      none (Fig. 8 second and third panels: "roughly ±3 Nm" in the seed);
    - ``max_abs_tau_m``: the envelope of the commanded motor torque (Fig. 8 bottom
      panel: "within ±40 Nm");
    - ``share_within_goal``: the share of samples with ``|e| <= 0.5`` Nm
      (:data:`TRACKING_GOAL_NM`, the seed's experimental result).
    """

    samples: int
    max_abs_error: float
    rms_error: float
    rms_disturbance_error: float  # estimated tau_lgd (tau_lg with Eq. 5) vs its truth
    max_external_error: float = math.nan
    rms_external_error: float = math.nan
    max_abs_tau_m: float = math.nan
    share_within_goal: float = math.nan
    #: e on the measured torque, ``T_meas − T_desired`` (``CTRL_TPDO1.T_meas``: what an
    #: experiment can plot, noise included), and on the observer's estimate ``e_hat =
    #: τ̂s − τsD`` (``CTRL_TPDO2.e_hat``): maximum, RMS and share within the goal.
    max_abs_error_measured: float = math.nan
    rms_error_measured: float = math.nan
    share_within_goal_measured: float = math.nan
    max_abs_error_estimated: float = math.nan
    rms_error_estimated: float = math.nan
    share_within_goal_estimated: float = math.nan

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


class TrackingScorer(can.Listener):
    """Tracking error of a torque control law, from the buses (or a trace of them).

    Pairs the controller's ``CTRL_TPDO2`` (desired torque ``tau_sD`` and the estimated
    lumped disturbance ``tau_lgd_hat``) with the truth of the same sample instant
    (``TRUTH_TORQUE.T_true``, ``TRUTH_JOINT.tau_ext``, ``tau_d`` and ``tau_m_cmd``).  The
    true lumped disturbance of [Vertechy] Eq. 3 is tau_lgd = tau_l + tau_g − tau_d·Jl/Jm,
    so ``jl_over_jm`` is the joint's inertia ratio; with ``friction_compensated`` (Eq. 5)
    the observer estimates tau_lg = tau_l + tau_g instead.  Only telemetry at or after
    ``skip_s`` counts, from the first telemetry frame (the first sample in operation).
    The measured torque of the same sample comes from ``CTRL_TPDO1`` (sent before
    ``CTRL_TPDO2``; none when the cycle has no ``CTRL_TPDO1``, as with decimated
    telemetry whose two frames go in different cycles), the estimate's error from
    ``CTRL_TPDO2.e_hat``.  Decimated telemetry is scored from the frames present, each
    against the truth of its own cycle (truth frames come every cycle).
    ``handle`` (the scenario's :class:`~hdhil.hostsim.plant.LinkMotionConfig`) gives
    the handle torque the external-torque estimate is scored against
    (:meth:`~hdhil.hostsim.plant.LinkMotionConfig.handle_torque`); None: ``tau_ext``.
    Everything else it needs is on the two buses, so a trace and its scenario score a
    run (``hdhil evaluate TRACE``).
    """

    def __init__(
        self,
        jl_over_jm: float,
        skip_s: float = 0.0,
        friction_compensated: bool = False,
        sample_period_s: float = 1e-3,
        handle: LinkMotionConfig | None = None,
        controller_node_id: int = 1,
        *,
        telemetry_ids: tuple[int, int] | None = None,
        joint_index: int = 0,
    ) -> None:
        self.sample_period_s = sample_period_s
        self.skip_s = skip_s
        self.jl_over_jm = jl_over_jm
        self.friction_compensated = friction_compensated
        #: the link whose bearing friction separates tau_ext from the handle torque
        self.handle = handle if handle is not None and handle.bearing_coulomb_Nm else None
        self._tele = codec("control", "CTRL_TPDO2").expect(
            "dtau_s_hat", "tau_lgd_hat", "tau_sD", "e_hat"
        )
        self._truth = codec("truth", "TRUTH_TORQUE").expect("T_true", "T_ripple")
        self._joint = codec("truth", "TRUTH_JOINT").expect("tau_ext", "tau_d", "tau_m", "tau_m_cmd")
        self._meas = codec("control", "CTRL_TPDO1").expect(
            "T_meas", "T_filtered", "velocity", "current"
        )
        tpdo1, tpdo2 = telemetry_ids or (
            _telemetry_id(1, controller_node_id),
            _telemetry_id(2, controller_node_id),
        )
        self._tele = self._tele.at(tpdo2)
        self._meas = self._meas.at(tpdo1)
        self._motion = codec("truth", "TRUTH_MOTION").expect(
            "theta_motor", "theta_output", "omega_motor", "omega_output"
        )
        self._truth = _truth_at(self._truth, joint_index)
        self._joint = _truth_at(self._joint, joint_index)
        self._motion = _truth_at(self._motion, joint_index)
        self._keys = {
            (self._meas.frame_id, False): self._on_measured,
            (self._tele.frame_id, False): self._on_tele,
            (self._truth.frame_id, True): self._on_truth,
            (self._joint.frame_id, True): self._on_joint,
        }
        if self.handle is not None:
            self._keys[self._motion.frame_id, True] = self._on_motion
        self._omega_l = 0.0
        self._t0: float | None = None
        self._T_true: float | None = None
        self._tau_lgd: float | None = None
        self._tau_ext = 0.0
        self._tau_m = 0.0
        self.n = 0
        self._sum_d2 = 0.0
        self._sum_x2 = 0.0
        self._max_x = 0.0
        self._max_m = 0.0
        self._T_meas: float | None = None
        self._true = _ErrorStats()
        self._measured = _ErrorStats()
        self._estimated = _ErrorStats()

    def on_message_received(self, msg: can.Message) -> None:
        handler = self._keys.get((msg.arbitration_id, msg.is_extended_id))
        if handler is not None and len(msg.data) == 8:
            handler(msg)

    def _on_truth(self, msg: can.Message) -> None:
        self._T_true = self._truth.decode(msg.data)[0]
        # a new cycle's truth: a measured torque of an earlier cycle is not this one's
        # (decimated telemetry can send CTRL_TPDO1 and CTRL_TPDO2 in different cycles)
        self._T_meas = None

    def _on_joint(self, msg: can.Message) -> None:
        tau_ext, tau_d, _tau_m, tau_m_cmd = self._joint.decode(msg.data)
        self._tau_ext = tau_ext
        self._tau_m = tau_m_cmd
        self._tau_lgd = tau_ext if self.friction_compensated else tau_ext - tau_d * self.jl_over_jm

    def _on_motion(self, msg: can.Message) -> None:
        self._omega_l = self._motion.decode(msg.data)[3]

    def _on_measured(self, msg: can.Message) -> None:
        self._T_meas = self._meas.decode(msg.data)[0]

    def _on_tele(self, msg: can.Message) -> None:
        # The controller sends this telemetry from its first interrupt in operation: that
        # frame is sample 0, so ``skip_s`` is counted as the evaluation counts it.
        if self._t0 is None:
            self._t0 = msg.timestamp
        if (
            self._T_true is None
            or self._tau_lgd is None
            # frames of one cycle go on the wire after a varying number of others:
            # within half a period of the boundary is the boundary's sample
            or msg.timestamp - self._t0 < self.skip_s - 0.5 * self.sample_period_s
        ):
            return
        _dtau, tau_lgd_hat, tau_sD, e_hat = self._tele.decode(msg.data)
        self._true.add(self._T_true - tau_sD)
        if self._T_meas is not None:  # each measured sample scores once
            self._measured.add(self._T_meas - tau_sD)
            self._T_meas = None
        self._estimated.add(e_hat)
        d = tau_lgd_hat - self._tau_lgd
        handle = self.handle
        if handle is None:
            x = tau_lgd_hat - self._tau_ext
        else:  # TRUTH_MOTION comes before TRUTH_JOINT: the same sample
            x = tau_lgd_hat - handle.handle_torque(self._tau_ext, self._omega_l)
        self.n += 1
        self._sum_d2 += d * d
        self._sum_x2 += x * x
        self._max_x = max(self._max_x, abs(x))
        self._max_m = max(self._max_m, abs(self._tau_m))

    def result(self) -> TrackingScore:
        n = self.n
        if not n:
            return TrackingScore(0, math.nan, math.nan, math.nan)
        max_e, rms_e, within = self._true.result()
        return TrackingScore(
            n,
            max_e,
            rms_e,
            math.sqrt(self._sum_d2 / n),
            self._max_x,
            math.sqrt(self._sum_x2 / n),
            self._max_m,
            within,
            *self._measured.result(),
            *self._estimated.result(),
        )


class _ErrorStats:
    """Maximum, RMS and share within :data:`TRACKING_GOAL_NM` of a stream of errors."""

    def __init__(self) -> None:
        self.n = 0
        self.sum2 = 0.0
        self.max = 0.0
        self.within = 0

    def add(self, e: float) -> None:
        self.n += 1
        self.sum2 += e * e
        a = abs(e)
        if a > self.max:
            self.max = a
        if a <= TRACKING_GOAL_NM:
            self.within += 1

    def result(self) -> tuple[float, float, float]:
        if not self.n:
            return math.nan, math.nan, math.nan
        return self.max, math.sqrt(self.sum2 / self.n), self.within / self.n


def trace_time_offset(trace: Path) -> float | None:
    """The time offset of a trace written by ``hdhil run`` (its metadata file's
    ``time_offset_s``: simulated time 0 as a wall-clock time), or None when it has no
    metadata (then its first frame is taken as time 0)."""
    from hdhil.can.traces.sidecar import read_metadata

    value = (read_metadata(trace) or {}).get("time_offset_s")
    return float(value) if isinstance(value, (int, float)) else None
