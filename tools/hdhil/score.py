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

import can

from hdhil.dbc import codec


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
    the filter's start-up transient.  The default scores everything.
    """

    def __init__(self, skip_s: float = 0.0, block_s: float = 60.0) -> None:
        self.skip_s = skip_s
        #: RMS filtered error per ``block_s`` of telemetry time (whether it drifts).
        self.block_s = block_s
        self.block_rms: list[float] = []
        self._block_sum = 0.0
        self._block_n = 0
        self._block_end = block_s
        tele = codec("control", "CTRL_TPDO1")
        truth = codec("truth", "TRUTH_TORQUE")
        self._tele_key = (tele.frame_id, False)
        self._truth_key = (truth.frame_id, True)
        self._tele = tele
        self._truth = truth
        self._T_true: float | None = None
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
            if self._T_true is None or msg.timestamp < self.skip_s:
                return
            T_true = self._T_true
            e_raw = T_meas - T_true
            e_filt = T_filtered - T_true
            self.n += 1
            self._sum_true2 += T_true * T_true
            self._sum_raw2 += e_raw * e_raw
            self._sum_filt2 += e_filt * e_filt
            self._max_raw = max(self._max_raw, abs(e_raw))
            self._max_filt = max(self._max_filt, abs(e_filt))
            if msg.timestamp >= self._block_end:
                self._close_block()
                while msg.timestamp >= self._block_end:
                    self._block_end += self.block_s
            self._block_sum += e_filt * e_filt
            self._block_n += 1

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
