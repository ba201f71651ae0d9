"""Motion signals of the handler: acceleration, low-pass, motor angle.

``Differentiator`` is the listing's ``Diff_filter`` ([Taghirad97], listing A.1), velocity
to acceleration for the expected torque; ``tustin_differentiator`` computes its
coefficients for any time constant and sample period.  ``LowPass`` is the basic low-pass
of the JTF laws ([Vertechy] §V).  ``EncoderUnwrap`` (the 16-bit ``pcsample`` count) and
``VelocityIntegrator`` (the tachometer) give the motor angle the recommended ripple
filter locks its harmonics to; neither is in the listing.  Each keeps only its own state.
"""

from __future__ import annotations

import math

_isfinite = math.isfinite

__all__ = [
    "Differentiator",
    "EncoderUnwrap",
    "LowPass",
    "VelocityIntegrator",
    "tustin_differentiator",
]


def tustin_differentiator(
    tau_s: float, sample_period_s: float
) -> tuple[tuple[float, float], tuple[float, float]]:
    """``H(s) = s / (tau s + 1)`` discretised by the Tustin (bilinear) method at
    ``fs = 1 / Ts``: ``((nd0, nd1), (1, dd1))`` of ``a = nd0 v + nd1 v_1 - dd1 a_1``.

    ``s = 2 fs (z - 1) / (z + 1)`` gives ``H(z) = 2 fs (z - 1) / ((2 fs tau + 1) z +
    (1 - 2 fs tau))``.  The arithmetic is that of ``scipy.signal.bilinear`` for this
    first-order case (the factor ``2 fs`` split as ``sqrt(2 fs)`` between numerator and
    denominator, then normalised by the leading denominator coefficient), so the
    coefficients are the same floats (a test compares them bit for bit) without
    importing scipy.signal, which is slow to import, when a firmware node starts.
    """
    fac = math.sqrt(2.0 / sample_period_s)
    inv = 1.0 / fac
    d0 = inv + tau_s * fac
    return (fac / d0, -fac / d0), (1.0, (inv - tau_s * fac) / d0)


class Differentiator:
    """Band-limited differentiator, velocity to acceleration (listing ``Diff_filter``).

    [Taghirad97], listing A.1, ``Diff_filter``: "Discretized Differentiator Filter
    H(s) = s / (0.005 s + 1), discretized by tustin method for Ts = 1 ms", with
    ``nd = {181.818181818182, -181.818181818182}``, ``dd = {1.0, -0.81818181818182}``
    and the difference equation ``a = nd[0]*v + nd[1]*v_1 - dd[1]*a_1``.

    Here the coefficients come from :func:`tustin_differentiator` for any τ and Ts
    (at τ = 5 ms, Ts = 1 ms they are the listing's).  The state ``v_1``, ``a_1``
    starts at 0 like the listing's globals ``float v_1 = 0.0, a_1 = 0.0``; note that
    the first call therefore sees a step from 0 to the first velocity.

    Robustness (not in the listing): a non-finite velocity (possible in recorded data,
    never from the ADC) returns NaN and leaves the state alone, so one bad sample
    cannot poison every later acceleration.  ``limit`` (rad/s², default unlimited as in
    the listing) clamps the output, and the clamped value is what ``a_1`` keeps; the
    plausibility stage sets it to the joint's largest acceleration
    (:class:`firmware.config.PlausibilityConfig`).  :meth:`reseed` moves ``v_1`` to a
    new velocity level, so that a level accepted after a jump the joint cannot make
    gives no acceleration impulse.
    """

    __slots__ = ("_dd1", "_nd0", "_nd1", "a_1", "limit", "v_1")

    def __init__(self, tau_s: float = 0.005, sample_period_s: float = 1e-3) -> None:
        if not (math.isfinite(tau_s) and tau_s > 0):
            raise ValueError(f"tau_s must be a finite number > 0, got {tau_s!r}")
        if not (math.isfinite(sample_period_s) and sample_period_s > 0):
            raise ValueError(
                f"sample_period_s must be a finite number > 0, got {sample_period_s!r}"
            )
        self.nd, self.dd = tustin_differentiator(tau_s, sample_period_s)
        self.v_1 = 0.0
        self.a_1 = 0.0
        self.limit = math.inf

    # The coefficients are kept as three floats (the step runs every interrupt and would
    # otherwise index two tuples three times); ``nd`` and ``dd`` read and set them.
    @property
    def nd(self) -> tuple[float, float]:
        """Numerator ``(nd[0], nd[1])``."""
        return (self._nd0, self._nd1)

    @nd.setter
    def nd(self, nd: tuple[float, float]) -> None:
        self._nd0, self._nd1 = nd

    @property
    def dd(self) -> tuple[float, float]:
        """Denominator ``(1, dd[1])``."""
        return (1.0, self._dd1)

    @dd.setter
    def dd(self, dd: tuple[float, float]) -> None:
        if dd[0] != 1.0:
            raise ValueError(f"the denominator must be normalised (dd[0] = 1), got {dd!r}")
        self._dd1 = dd[1]

    def step(self, v: float) -> float:
        """One sample: ``a = nd[0]*v + nd[1]*v_1 - dd[1]*a_1`` clamped to ±``limit``;
        ``v_1 = v; a_1 = a``."""
        if not _isfinite(v):
            return math.nan
        a = self._nd0 * v + self._nd1 * self.v_1 - self._dd1 * self.a_1
        limit = self.limit
        if a > limit:
            a = limit
        elif a < -limit:
            a = -limit
        self.v_1 = v
        self.a_1 = a
        return a

    def reseed(self, v: float) -> None:
        """Take ``v`` as the previous velocity: the next :meth:`step` with ``v`` adds no
        impulse (``a = -dd[1]*a_1``, the old acceleration decaying)."""
        self.v_1 = v

    def reset(self) -> None:
        """Back to the listing's initial state ``v_1 = a_1 = 0``."""
        self.v_1 = 0.0
        self.a_1 = 0.0


class LowPass:
    """First-order low-pass ``1 / (s/ωc + 1)``, Tustin at Ts (not in the papers' listings).

    The "basic low-pass filter" through which the JTF laws of the literature feed the
    torque sensor measurement ([Vertechy] §V: "the estimates
    τ̂s and τ̂s' are obtained by simply feeding the torque sensor measurement y through
    basic low-pass and derivative filters").  ``y = b (x + x_1) + a y_1`` with ``a =
    (2τ - Ts) / (2τ + Ts)``, ``b = Ts / (2τ + Ts)``, ``τ = 1 / (2π cutoff)``; unity gain
    at DC.  The state starts at the first input (no start-up step from 0).
    """

    __slots__ = ("_a", "_b", "_x1", "_y1")

    def __init__(self, cutoff_Hz: float, sample_period_s: float) -> None:
        if not (math.isfinite(cutoff_Hz) and 0.0 < cutoff_Hz < 0.5 / sample_period_s):
            raise ValueError(
                f"low-pass cut-off must lie in (0, {0.5 / sample_period_s:g}) Hz, got {cutoff_Hz!r}"
            )
        tau = 1.0 / (2.0 * math.pi * cutoff_Hz)
        self._a = (2.0 * tau - sample_period_s) / (2.0 * tau + sample_period_s)
        self._b = sample_period_s / (2.0 * tau + sample_period_s)
        self._x1: float | None = None
        self._y1 = 0.0

    def step(self, x: float) -> float:
        """One sample."""
        if self._x1 is None:
            self._x1 = self._y1 = x
            return x
        y = self._b * (x + self._x1) + self._a * self._y1
        self._x1, self._y1 = x, y
        return y

    def reset(self) -> None:
        """Forget the history."""
        self._x1 = None
        self._y1 = 0.0


class EncoderUnwrap:
    """Unwraps the 16-bit wrapping encoder count (listing ``pcsample``) into a count that
    keeps growing: the motor angle for the recommended ripple filter.

    [Taghirad97], listing A.1, ``c_int10``: ``copy(PB_LAT_RD_ADDR, &pcsample, ...)`` reads
    the quadrature decoder's 16-bit count and ``pcsample &= 0x0000ffff`` stores it; the
    listing never unwraps it.  Unwrapping is ours: each sample adds the difference of
    successive counts taken as a signed 16-bit number (int16 arithmetic), so crossing
    65535 -> 0 forwards or 0 -> 65535 backwards adds +1 or -1.

    Limit: the motor must move less than 32768 counts per sample (half the counter
    range); faster motion aliases.  With 8000 counts per revolution at 1 ms that is
    4.1 revolutions per sample, 25 700 rad/s, far above any harmonic drive's motor.

    The first count is taken as it is (0..65535), so if the drive counts from 0 at
    power-on and has not wrapped yet, ``count * 2 pi / counts_per_rev`` is the true motor
    angle; any other constant offset only rotates the learned ripple coefficients.
    The count is a Python int (exact forever).
    """

    __slots__ = ("_last", "count")

    BITS = 16
    _MASK = (1 << BITS) - 1
    _HALF = 1 << (BITS - 1)

    def __init__(self) -> None:
        self.count = 0
        self._last: int | None = None

    def step(self, raw: int) -> int:
        """One sample: the raw count (only its low 16 bits are used) to the unwrapped
        count."""
        raw &= self._MASK
        last = self._last
        if last is None:
            self.count = raw
        else:
            delta = (raw - last) & self._MASK
            if delta >= self._HALF:
                delta -= 1 << self.BITS
            self.count += delta
        self._last = raw
        return self.count

    def reset(self) -> None:
        """Forget the history: the next count starts the unwrapped count afresh."""
        self.count = 0
        self._last = None


class VelocityIntegrator:
    """Motor angle integrated from the tachometer velocity: the fallback phase source of
    the recommended ripple filter for data without an encoder (not in the papers).

    Trapezoidal rule, φ(0) = 0, φ(k) = φ(k−1) + Ts (ω(k) + ω(k−1)) / 2.  It needs only
    the velocity measured up to k, so φ(k) is available at k.  (The paper filter's
    oscillators advance by ω(k)·Ts from k to k+1, i.e. forward Euler.)  A non-finite
    velocity is skipped: φ is held and the last finite velocity kept.  The angle
    inherits the tachometer's errors: its noise integrates into a random walk and a
    quantisation bias (0.27 rad/s per ADC count on the listing's channel) into a phase
    drift, which the filter has to follow by adapting its coefficients.
    """

    __slots__ = ("_half_Ts", "_last", "angle")

    def __init__(self, sample_period_s: float) -> None:
        if not (math.isfinite(sample_period_s) and sample_period_s > 0):
            raise ValueError(
                f"sample_period_s must be a finite number > 0, got {sample_period_s!r}"
            )
        self._half_Ts = 0.5 * sample_period_s
        self.angle = 0.0
        self._last: float | None = None

    def step(self, velocity: float) -> float:
        """One sample: motor velocity (rad/s) to motor angle (rad)."""
        if not math.isfinite(velocity):
            return self.angle
        last = self._last
        if last is not None:
            self.angle += self._half_Ts * (velocity + last)
        self._last = velocity
        return self.angle

    def reset(self) -> None:
        """Back to φ = 0 with no history."""
        self.angle = 0.0
        self._last = None
