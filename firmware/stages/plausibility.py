"""The sensor plausibility stage: tacho spikes and encoder glitches replaced by the
prediction (not in the papers; [Taghirad97], listing A.1 uses every sample as read).

It runs right after calibration and bounds what one sample may change, from the joint's
largest acceleration and the tacho noise (:class:`firmware.config.PlausibilityConfig`),
so that one bad sample reaches neither the differentiator nor the ripple filter's phase,
and it never locks the firmware out: after a few rejections in a row the new level is
accepted.
"""

from __future__ import annotations

import math

from hdhil.firmware.config import PlausibilityConfig

__all__ = [
    "SensorPlausibility",
]

_isfinite = math.isfinite


class SensorPlausibility:
    """Bounds on what one sample may change: tacho spikes and encoder glitches are
    replaced by the prediction (not in the papers; the listing uses every sample as read).

    It runs right after ``calibrate`` ([Taghirad97], listing A.1: after ``vel = Tacho *
    volt2radps``, before ``acc = Diff_filter( vel)``) and never reads anything but the
    sensor frame's values.  Limits come from :class:`firmware.config.PlausibilityConfig`.

    **Velocity.**  A sample is implausible when it differs from the last accepted one,
    n samples back, by more than ``tacho_noise_radps + n * max_acceleration_radps2 *
    Ts``: the joint cannot change its speed faster than its motor torque allows, and the
    tacho noise band comes on top.  It is replaced by the last accepted velocity (hold).
    The bound grows with n, as what the joint may have done since grows.  The first
    sample has nothing to be compared against and is accepted as it is.

    **Encoder** (with ``check_encoder``, i.e. when the ripple filter locks its harmonics
    to the encoder).  The increment of the 16-bit count, taken as a signed 16-bit number
    (the wrap 65535 -> 0 is +1, as in :class:`EncoderUnwrap`), is compared with the one
    the accepted velocity predicts, ``Ts (v(k-1) + v(k)) / 2`` in counts (trapezoidal
    rule).  If they differ by more than ``encoder_tolerance_counts``, the predicted
    increment replaces the measured one: the stage returns the count shifted by the
    offset it has accumulated, so an encoder glitch (counts lost or gained for good)
    leaves the angle the filter sees continuous.  After g missed samples
    (:meth:`missed`, a lost sensor frame) the prediction spans 1 + g periods and the
    velocity bound grows by g periods too.

    **Late samples.**  A sensor frame carries no sample number, and one delayed or
    reordered past the next SYNC reaches the firmware in the next cycle, after a period
    it counted as missed; the firmware runs it as that cycle's sample and skips the
    cycle's own frame.  So after g missed periods, and b periods by which the last sample
    lagged the firmware's cycles, the increment may span any whole number of periods n
    from 1 to 1 + g + b: it passes when it is within the tolerance of one of them, and
    1 + g + b - n (at most :attr:`MAX_BEHIND`) is the new lag.  Without a gap or a lag
    the check is the one-period check above.

    **No lock-out.**  At most ``max_rejections`` implausible samples in a row are
    replaced per channel; the next one is accepted as the new level (a real jump, or a
    sensor that stays off: the velocity reference is re-seeded, or the encoder is
    followed again).  The ``max_rejections``-th replacement in a row sets the channel's
    error flag (``tacho_error`` / ``encoder_error``), which the controller announces by
    EMCY; the flag clears after as many plausible samples in a row.  An isolated spike
    or glitch therefore raises no error.

    After :meth:`step`: ``rejected`` is True when a value was replaced this sample
    (:class:`firmware.isr.TorqueFilterChain` then keeps the sample out of the Kalman
    filter's learning) and ``reseeded`` when the velocity was accepted as a new level.
    Counters: ``tacho_rejections``, ``encoder_rejections`` (values replaced),
    ``tacho_reseeds``, ``encoder_reseeds`` (implausible values accepted as the new
    level), ``errors_raised``; ``revision`` changes whenever any of them or an error
    flag does.  A non-finite velocity is passed on unchecked (the later stages skip it)
    and skips the encoder check.
    """

    __slots__ = (
        "_behind",
        "_dv_max",
        "_e_bad",
        "_e_good",
        "_gap",
        "_half_Ts_counts",
        "_limit",
        "_noise",
        "_offset",
        "_raw_last",
        "_shift",
        "_since",
        "_tolerance",
        "_v_bad",
        "_v_good",
        "_v_prev",
        "_v_ref",
        "check_encoder",
        "encoder_error",
        "encoder_rejections",
        "encoder_reseeds",
        "errors_raised",
        "rejected",
        "reseeded",
        "revision",
        "tacho_error",
        "tacho_rejections",
        "tacho_reseeds",
    )

    #: Periods a sample may lag the firmware's cycles (late frames) and still pass.
    MAX_BEHIND = 2

    def __init__(
        self,
        cfg: PlausibilityConfig,
        sample_period_s: float,
        counts_per_rev: int,
        check_encoder: bool = True,
    ) -> None:
        if not (math.isfinite(sample_period_s) and sample_period_s > 0):
            raise ValueError(
                f"sample_period_s must be a finite number > 0, got {sample_period_s!r}"
            )
        if counts_per_rev <= 0:
            raise ValueError(f"counts_per_rev must be > 0, got {counts_per_rev!r}")
        self._dv_max = cfg.max_acceleration_radps2 * sample_period_s
        self._noise = cfg.tacho_noise_radps
        self._tolerance = cfg.encoder_tolerance_counts
        self._limit = cfg.max_rejections
        self._half_Ts_counts = 0.5 * sample_period_s * counts_per_rev / (2.0 * math.pi)
        self.check_encoder = check_encoder
        self.reset()

    def reset(self) -> None:
        """Forget the history and zero the counters (power-on)."""
        self._v_ref: float | None = None
        self._v_prev: float | None = None
        self._since = 1
        self._gap = 0  # sample periods missed since the last step
        self._behind = 0  # periods the last sample lagged the firmware's cycles (late)
        self._v_bad = self._v_good = 0
        self._raw_last: int | None = None
        self._offset = 0.0  # replaced minus measured increments (counts)
        self._shift = 0  # its nearest integer, added to every raw count
        self._e_bad = self._e_good = 0
        self.rejected = self.reseeded = False
        self.tacho_error = self.encoder_error = False
        self.tacho_rejections = self.encoder_rejections = 0
        self.tacho_reseeds = self.encoder_reseeds = 0
        self.errors_raised = 0
        self.revision = 0

    def set_encoder_check(self, on: bool) -> None:
        """Check the encoder from now on (or not); its history restarts."""
        self.check_encoder = on
        self._raw_last = None
        self._v_prev = None

    def missed(self) -> None:
        """A sample period passed without a sample (a lost sensor frame): the next
        velocity bound and encoder prediction span it."""
        self._gap += 1
        self._since += 1

    def step(self, velocity: float, encoder: int | None) -> tuple[float, int | None]:
        """One sample: calibrated velocity (rad/s) and raw encoder count (None: no
        encoder) to the velocity and 16-bit count the later stages use."""
        self.rejected = self.reseeded = False
        gap = self._gap
        v = velocity
        v_ref = self._v_ref
        finite = _isfinite(v)  # a replacement below is finite too
        if v_ref is None or not finite:
            if finite:
                self._v_ref = v
        else:
            bound = self._noise + self._since * self._dv_max
            if -bound <= v - v_ref <= bound:
                self._v_ref = v
                self._since = 1
                self._v_bad = 0
                if self.tacho_error:
                    self._tacho_good()
            else:
                v = self._tacho_implausible(v, v_ref)
        if gap:
            self._gap = 0
        if encoder is None or not self.check_encoder:
            return v, encoder
        raw = encoder & 0xFFFF
        last = self._raw_last
        self._raw_last = raw
        v_prev = self._v_prev
        if finite:
            self._v_prev = v
            if last is not None and v_prev is not None:
                d = (raw - last) & 0xFFFF  # the increment as a signed 16-bit number
                if d >= 0x8000:
                    d -= 0x10000
                predicted = (v_prev + v) * self._half_Ts_counts * (1 + gap)
                tol = self._tolerance
                span = gap + self._behind
                if span:
                    # A sensor frame carries no sample number: the sample that ends a
                    # gap may be the late frame of its first period, and the one after
                    # a late sample spans the period it lagged too.  Any whole number of
                    # periods from one to 1 + gap + behind passes; the periods it
                    # matched tell how far this sample lags the firmware's cycles.
                    one = (v_prev + v) * self._half_Ts_counts
                    n = 1 + span
                    lo, hi = (one, one * n) if one >= 0 else (one * n, one)
                    plausible = lo - tol <= d <= hi + tol
                    if plausible and abs(one) > tol:
                        periods = min(n, max(1, round(d / one)))
                        predicted = one * periods
                        self._behind = min(self.MAX_BEHIND, n - periods)
                    elif plausible:
                        predicted = one * n
                        self._behind = 0
                    plausible = plausible and -tol <= d - predicted <= tol
                else:
                    plausible = -tol <= d - predicted <= tol
                if plausible:
                    self._e_bad = 0
                    if self.encoder_error:
                        self._encoder_good()
                else:
                    self._encoder_implausible(d, predicted)
        return v, (raw + self._shift) & 0xFFFF

    def _tacho_implausible(self, v: float, v_ref: float) -> float:
        """An implausible velocity: the held reference (the error is raised at the
        ``max_rejections``-th in a row), or after that many the new level."""
        bad = self._v_bad = self._v_bad + 1
        self._v_good = 0
        self.revision += 1
        if bad > self._limit:
            self.reseeded = True
            self.tacho_reseeds += 1
            self._v_ref = v
            self._since = 1
            return v
        self.rejected = True
        self.tacho_rejections += 1
        self._since += 1
        if bad == self._limit and not self.tacho_error:
            self.tacho_error = True
            self.errors_raised += 1
        return v_ref

    def _tacho_good(self) -> None:
        self._v_good += 1
        if self._v_good >= self._limit:
            self.tacho_error = False
            self.revision += 1

    def _encoder_implausible(self, d: int, predicted: float) -> None:
        """An implausible increment: replaced by the predicted one (the error is raised
        at the ``max_rejections``-th in a row), or after that many taken as measured."""
        bad = self._e_bad = self._e_bad + 1
        self._e_good = 0
        self.revision += 1
        if bad > self._limit:
            self.encoder_reseeds += 1
            return
        self.rejected = True
        self.encoder_rejections += 1
        self._offset += predicted - d
        self._shift = round(self._offset)
        if bad == self._limit and not self.encoder_error:
            self.encoder_error = True
            self.errors_raised += 1

    def _encoder_good(self) -> None:
        self._e_good += 1
        if self._e_good >= self._limit:
            self.encoder_error = False
            self.revision += 1
