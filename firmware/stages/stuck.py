"""The stuck-channel check: a torque or tacho channel that holds one reading while the
encoder shows the motor turning (not in the papers).

A turning harmonic drive sweeps its torque ripple ([Taghirad97] §2) through many ADC
counts, and a turning motor moves its tacho; a reading that stays put meanwhile is a dead
sensor, which the controller announces by EMCY.  The encoder is the independent witness.
"""

from __future__ import annotations

import math

__all__ = [
    "StuckChannels",
]


class StuckChannels:
    """A torque or tacho channel stuck at one reading while the motor turns (not in the
    papers).

    **Torque.**  A torque bridge whose ADC reading does not change by a single count for
    ``stuck_samples`` samples in a row, while the encoder moved by at least
    ``stuck_motion_rad`` of motor angle over those samples, is stuck: a turning motor
    sweeps the torque ripple ([Taghirad97] §2: two and four times the motor angle) through
    many counts.  The controller sends EMCY 0x7300 "sensor error" with 1, the torque
    channel, in manufacturer byte 0.

    **Tacho.**  A constant tacho reading alone proves nothing: at a steady speed its noise
    (0.05 rad/s in the shipped scenarios) is below one count (0.27 rad/s), so the reading
    may well stay put.  The tacho is stuck when its reading has not changed for
    ``stuck_samples`` samples, the encoder moved by at least ``stuck_motion_rad`` over
    them, *and* the encoder's mean velocity over those samples (its signed count
    difference over the periods they span, lost samples included) differs from the held
    reading by more than ``tacho_tolerance_radps`` plus ``tacho_tolerance_share`` of
    that velocity: the motor turns at a speed the tacho does not show.  The encoder is
    the independent witness; the tacho's own history is not used.  The controller sends
    EMCY 0x7301 "tacho fault" with 2, the tacho channel, in manufacturer byte 0 (the
    plausibility stage's 0x7301 for an implausible jump carries no manufacturer byte).
    Judged only when ``sample_period_s`` is given.

    A reading at the ADC's full scale is saturation, not a stuck sensor, and is left to
    the drive's own check.  A flag (``torque_stuck``, ``tacho_stuck``) rises at the
    sample the condition is met (``events`` counts the rises of both, ``tacho_events``
    those of the tacho) and falls at the first changed reading.  Without an encoder
    nothing is judged.  ``revision`` changes whenever a flag does.
    """

    __slots__ = (
        "_Ts",
        "_counts_needed",
        "_last_T",
        "_last_v",
        "_moved_T",
        "_moved_v",
        "_periods",
        "_rad_per_count",
        "_raw_last",
        "_run_T",
        "_run_v",
        "_samples",
        "_share",
        "_signed",
        "_since",
        "_tolerance",
        "events",
        "revision",
        "tacho_events",
        "tacho_stuck",
        "torque_stuck",
    )  # fmt: skip

    #: A reading this close to the ADC's ends is saturation (volts, ±10 V converter).
    _FULL_SCALE_V = 9.99

    def __init__(
        self,
        samples: int,
        motion_rad: float,
        counts_per_rev: int,
        sample_period_s: float | None = None,
        tacho_tolerance_radps: float = 2.0,
        tacho_tolerance_share: float = 0.05,
    ) -> None:
        self._samples = samples
        self._counts_needed = motion_rad * counts_per_rev / (2.0 * math.pi)
        self._rad_per_count = 2.0 * math.pi / counts_per_rev
        self._Ts = sample_period_s
        self._tolerance = tacho_tolerance_radps
        self._share = tacho_tolerance_share
        self.reset()

    def reset(self) -> None:
        # Per channel (_T torque, _v tacho): the held reading, the samples it has been
        # held, and the encoder counts (unsigned) moved meanwhile.
        self._last_T: float | None = None
        self._last_v: float | None = None
        self._run_T = self._run_v = 0
        self._moved_T = self._moved_v = 0.0
        self._signed = 0  # encoder counts (signed) while the tacho reading was held
        self._periods = 0  # sample periods those counts span (lost samples included)
        self._since = 1  # periods since the last sample (1 + lost samples)
        self._raw_last: int | None = None
        self.torque_stuck = self.tacho_stuck = False
        self.events = 0
        self.tacho_events = 0
        self.revision = 0

    def missed(self) -> None:
        """A sample period passed without a sample (a lost sensor frame)."""
        self._since += 1

    def step(self, torque: float, velocity: float, encoder: int | None,
             torque_V: float, tacho_V: float) -> None:  # fmt: skip
        """One sample: calibrated torque and velocity, the raw encoder count and the two
        channels' voltages (for the saturation exclusion).

        The two channels are written out one after the other (not a loop over them):
        this runs in every interrupt, and a changed reading, the common case, is one
        comparison and three stores."""
        periods, self._since = self._since, 1
        if encoder is None:
            return
        raw = encoder & 0xFFFF
        last_raw = self._raw_last
        self._raw_last = raw
        signed = 0
        if last_raw is not None:
            signed = (raw - last_raw) & 0xFFFF
            if signed >= 0x8000:
                signed -= 0x10000
        d = -signed if signed < 0 else signed
        full_scale = self._FULL_SCALE_V
        # torque channel
        if torque != self._last_T or abs(torque_V) >= full_scale:
            self._last_T = torque
            self._run_T = 0
            self._moved_T = 0.0
            if self.torque_stuck:
                self.torque_stuck = False
                self.revision += 1
        else:
            run = self._run_T = self._run_T + 1
            moved = self._moved_T = self._moved_T + d
            if not self.torque_stuck and run >= self._samples and moved >= self._counts_needed:
                self.torque_stuck = True
                self.revision += 1
                self.events += 1
        if not self._Ts:
            return
        # tacho channel
        if velocity != self._last_v or abs(tacho_V) >= full_scale:
            self._last_v = velocity
            self._run_v = 0
            self._moved_v = 0.0
            self._signed = self._periods = 0
            if self.tacho_stuck:
                self.tacho_stuck = False
                self.revision += 1
        else:
            run = self._run_v = self._run_v + 1
            moved = self._moved_v = self._moved_v + d
            self._signed += signed
            self._periods += periods
            if (not self.tacho_stuck and run >= self._samples
                    and moved >= self._counts_needed
                    and self._tacho_disagrees(velocity)):  # fmt: skip
                self.tacho_stuck = True
                self.revision += 1
                self.events += 1
                self.tacho_events += 1

    def _tacho_disagrees(self, velocity: float) -> bool:
        """Whether the encoder's mean velocity over the held reading's samples is further
        from ``velocity`` than the tolerance."""
        assert self._Ts is not None
        if self._periods <= 0:
            return False
        v_enc = self._signed * self._rad_per_count / (self._periods * self._Ts)
        return abs(v_enc - velocity) > self._tolerance + self._share * abs(v_enc)
