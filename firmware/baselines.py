"""Baseline torque filters to compare the Kalman ripple filters against.

Both are stages in the style of :mod:`firmware.stages`: :meth:`step` filters one sample
(as firmware would, every interrupt), :meth:`filter` a whole numpy array offline.  The
two paths run the same recursion from the same state and leave the same state behind,
so they can be mixed.  Neither is the ripple filter of [Taghirad97]; they are what a
designer would try first, which is why they are the baselines.

- :class:`ButterworthLowPass`: the filter listing A.1's revision notes name ("01/11/95
  hdt Butterworth filter for torque", replaced by the Kalman filter); its code is not
  printed, so order and cut-off are ours.
- :class:`TrackingNotchBank`: second-order IIR notches whose centre frequencies follow
  2x and 4x the measured motor velocity, where the ripple of [Taghirad97] §4 sits.  Not
  in the papers.

Non-finite samples are not skipped: like any IIR filter a NaN input poisons the state
until :meth:`reset` (the Kalman filters skip and count them instead).

No scipy here: ``hdhil run`` scores every run against these baselines, and importing
:mod:`scipy.signal` takes longer than the whole evaluation.  The Butterworth design is
:func:`butterworth_lowpass`, the computation of ``scipy.signal.butter`` written out, and
the recursions are loops over Python floats; the tests hold both to scipy's
``butter``/``lfilter``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["ButterworthLowPass", "TrackingNotchBank", "butterworth_lowpass"]


def _check_period(sample_period_s: float) -> float:
    if not (math.isfinite(sample_period_s) and sample_period_s > 0):
        raise ValueError(f"sample_period_s must be a finite number > 0, got {sample_period_s!r}")
    return float(sample_period_s)


def butterworth_lowpass(
    order: int, cutoff_Hz: float, sample_rate_Hz: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(b, a)`` of the digital Butterworth low-pass (``a[0] = 1``), the design of
    ``scipy.signal.butter(order, cutoff_Hz, fs=sample_rate_Hz)`` step by step
    (``iirfilter`` with ``buttap``, ``lp2lp_zpk``, ``bilinear_zpk``, ``zpk2tf``; S. Butterworth,
    "On the theory of filter amplifiers", 1930, for the prototype):

    1. analog prototype, cut-off 1 rad/s: poles ``-exp(jπm / 2N)``, m = -N+1, -N+3, ..., N-1,
       no zeros, gain 1;
    2. pre-warping, in scipy's frequency unit (half-cycles per sample, fs = 2):
       ``wo = 4 tan(π Wn / 2)`` with ``Wn = cutoff / (sample_rate / 2)``, so that the
       bilinear transform puts the -3 dB point exactly at the cut-off; poles ``wo p``,
       gain ``wo^N``;
    3. bilinear transform ``s = 4 (z - 1) / (z + 1)``: poles ``(4 + p) / (4 - p)``, the N
       zeros at infinity to z = -1, gain ``k / Re Π(4 - p)``;
    4. ``b = k Π(z + 1)`` (binomial coefficients times k), ``a = Re Π(z - p_z)`` (the poles
       come in conjugate pairs, so the imaginary parts are round-off).
    """
    N = order
    Wn = np.float64(cutoff_Hz) / (np.float64(sample_rate_Hz) / 2)
    m = np.arange(-N + 1, N, 2, dtype=np.float64)
    p = -np.exp(1j * np.pi * m / (2 * N))  # 1: the middle pole (odd N) is exactly -1
    warped = 2 * 2.0 * np.tan(np.pi * Wn / 2.0)  # 2
    p = warped * p
    k = 1.0 * float(warped) ** N
    p_z = (4.0 + p) / (4.0 - p)  # 3
    k_z = k * np.real(1.0 / np.prod(4.0 - p))
    b = k_z * _poly(-np.ones(N))  # 4
    a = np.real(_poly(p_z)).copy()
    return np.asarray(b, dtype=np.float64), np.asarray(a, dtype=np.float64)


def _poly(roots: np.ndarray) -> np.ndarray:
    """Coefficients of Π(z - r) over ``roots``, highest power first (``numpy.poly``'s
    repeated convolution)."""
    a = np.ones((1,), dtype=roots.dtype)
    for r in roots:
        a = np.convolve(a, np.stack((np.ones_like(r), -r)), mode="full")
    return a


class ButterworthLowPass:
    """Butterworth low-pass, ``order`` poles at ``cutoff_Hz`` (-3 dB), sampled at Ts.

    Provenance: [Taghirad97], listing A.1 revision note "01/11/95 hdt Butterworth filter
    for torque" (the filter itself is not printed).  Design:
    :func:`butterworth_lowpass`, i.e. ``scipy.signal.butter(order, cutoff_Hz, fs=1/Ts)``
    (bilinear transform with pre-warping, so the -3 dB point is exactly at
    ``cutoff_Hz``); unity gain at DC.

    Structure: direct form II transposed, the structure of ``scipy.signal.lfilter``,
    whose delay-line state ``z`` (length ``order``, ``lfilter``'s ``zi``) :meth:`step`
    and :meth:`filter` update with the same operations in the same order::

        y    = z[0] + b[0] x
        z[i] = z[i+1] + b[i+1] x - a[i+1] y      (i = 0 .. order-2)
        z[-1] = b[order] x - a[order] y

    Its price is lag: a 2nd-order Butterworth delays low frequencies by about
    sqrt(2) / (2π f_c) (22 ms at 10 Hz), and it cannot remove the ripple below the
    cut-off, i.e. at low motor speed.
    """

    def __init__(self, cutoff_Hz: float, sample_period_s: float, order: int = 2) -> None:
        Ts = _check_period(sample_period_s)
        nyquist = 0.5 / Ts
        if not (math.isfinite(cutoff_Hz) and 0.0 < cutoff_Hz < nyquist):
            raise ValueError(
                f"cutoff_Hz must be within (0, {nyquist:g}) Hz (the Nyquist frequency), "
                f"got {cutoff_Hz!r}"
            )
        if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 8:
            raise ValueError(f"order must be an integer 1..8, got {order!r}")
        self.cutoff_Hz = float(cutoff_Hz)
        self.sample_period_s = Ts
        self.order = order
        b, a = butterworth_lowpass(order, self.cutoff_Hz, 1.0 / Ts)
        #: Numerator and denominator coefficients (``a[0] = 1``), as scipy designs them.
        self.b: np.ndarray = np.asarray(b, dtype=np.float64)
        self.a: np.ndarray = np.asarray(a, dtype=np.float64)
        self._b = tuple(float(v) for v in self.b)
        self._a = tuple(float(v) for v in self.a)
        self._z = [0.0] * order

    @property
    def state(self) -> np.ndarray:
        """A copy of the direct-form-II-transposed state (``lfilter``'s ``zi``)."""
        return np.array(self._z)

    def reset(self, value: float | None = None) -> None:
        """Back to rest (z = 0), or, with ``value``, to the steady state of a constant
        input ``value`` (what ``scipy.signal.lfilter_zi`` gives, times ``value``), which
        avoids the start-up transient from 0 to a torque offset.  In the steady state
        x and y are constant, y = (Σb / Σa) x (the DC gain), and the recursion of
        :meth:`step` solves backwards: z[i] = Σ_{j>i} (b[j] x - a[j] y)."""
        if value is None:
            self._z = [0.0] * self.order
            return
        x = float(value)
        y = sum(self._b) / sum(self._a) * x
        z = [0.0] * self.order
        acc = 0.0
        for i in range(self.order - 1, -1, -1):
            acc += x * self._b[i + 1] - y * self._a[i + 1]
            z[i] = acc
        self._z = z

    def step(self, x: float) -> float:
        """One sample in, one filtered sample out."""
        b, a, z = self._b, self._a, self._z
        y = z[0] + b[0] * x
        last = self.order - 1
        for i in range(last):
            z[i] = z[i + 1] + x * b[i + 1] - y * a[i + 1]
        z[last] = x * b[last + 1] - y * a[last + 1]
        return y

    def filter(self, x: np.ndarray | Sequence[float]) -> np.ndarray:
        """A whole array through the recursion of :meth:`step` (the same operations,
        so the same numbers), continuing from and updating its state; what
        ``scipy.signal.lfilter(b, a, x, zi=state)`` computes, as a loop over Python
        floats."""
        data = np.asarray(x, dtype=np.float64)
        if data.ndim != 1:
            raise ValueError(f"filter expects a 1-D array, got shape {data.shape}")
        b, a = self._b, self._a
        out: list[float] = []
        append = out.append
        if self.order == 2:  # the default, unrolled
            b0, b1, b2 = b
            _, a1, a2 = a
            z0, z1 = self._z
            for xin in data.tolist():
                y = z0 + b0 * xin
                z0 = z1 + xin * b1 - y * a1
                z1 = xin * b2 - y * a2
                append(y)
            self._z = [z0, z1]
        else:
            step = self.step
            for xin in data.tolist():
                append(step(xin))
        return np.array(out, dtype=np.float64)


class TrackingNotchBank:
    """A cascade of second-order IIR notches at ``multiples`` x the measured motor
    velocity, retuned every sample.

    Provenance: not in the papers.  The ripple of [Taghirad97] §4 sits at 2x and 4x the
    motor velocity, so a notch that follows those frequencies is the obvious
    non-model-based alternative to the Kalman filter.  Each notch is the standard
    second-order notch (S. J. Orfanidis, *Introduction to Signal Processing*, 1996,
    §6.4; the design of ``scipy.signal.iirnotch``), zeros on the unit circle at ω0 and
    poles at radius ρ inside them::

        H(z) = β (1 - 2 cos(ω0 T) z⁻¹ + z⁻²) / (1 - 2 β cos(ω0 T) z⁻¹ + (2β - 1) z⁻²)
        β = 1 / (1 + tan(π B T)),  ρ² = 2β - 1

    with B = ``bandwidth_Hz`` the -3 dB bandwidth (ρ ≈ 1 − πBT: 0.9937 for 2 Hz at
    1 kHz; ρ = 0.98 corresponds to B ≈ 6.4 Hz).  Compared with the textbook form
    (1 − 2cos(ω0T) z⁻¹ + z⁻²)/(1 − 2ρcos(ω0T) z⁻¹ + ρ² z⁻²), the numerator is scaled
    by β and the pole angle is slightly off ω0 (cos θ_p = β cos(ω0 T) / ρ); together
    these make the gain exactly 1 at DC and at Nyquist whatever ω0, whereas the
    textbook form's DC gain drops well below 1 for a notch near DC (0.8 for a 6 Hz
    notch with ρ = 0.98).
    ω0 = multiple·|velocity| is recomputed every sample from the velocity measured at
    that sample; the structure is direct form I (the state is the last two inputs and
    outputs), so retuning does not disturb the state.

    Near zero speed: a notch centred near 0 Hz would remove the low-frequency torque
    itself (a notch of bandwidth B takes out everything within about B/2 of its
    centre).  So all notches are bypassed (output = input, state kept up to date)
    while ``|velocity| < min_speed_radps`` (default 5 rad/s: the 2x notch then sits at
    1.6 Hz), and a notch whose centre would be at or above Nyquist is bypassed too.
    At standstill the ripple is a constant, position-dependent offset that no
    frequency-selective filter can remove.
    """

    def __init__(
        self,
        multiples: Sequence[float] = (2.0, 4.0),
        sample_period_s: float = 1e-3,
        bandwidth_Hz: float = 2.0,
        min_speed_radps: float = 5.0,
    ) -> None:
        Ts = _check_period(sample_period_s)
        mults = tuple(float(m) for m in multiples)
        if not mults or not all(math.isfinite(m) and m > 0 for m in mults):
            raise ValueError(f"multiples must be one or more numbers > 0, got {multiples!r}")
        if not (math.isfinite(bandwidth_Hz) and 0.0 < bandwidth_Hz < 0.5 / Ts):
            raise ValueError(
                f"bandwidth_Hz must be within (0, {0.5 / Ts:g}) Hz, got {bandwidth_Hz!r}"
            )
        if not (math.isfinite(min_speed_radps) and min_speed_radps >= 0):
            raise ValueError(f"min_speed_radps must be a number >= 0, got {min_speed_radps!r}")
        self.multiples = mults
        self.sample_period_s = Ts
        self.bandwidth_Hz = float(bandwidth_Hz)
        self.min_speed_radps = float(min_speed_radps)
        #: β of the design above (the numerator gain); 2β - 1 = ρ².
        self.beta = 1.0 / (1.0 + math.tan(math.pi * self.bandwidth_Hz * Ts))
        self._wT = tuple(m * Ts for m in mults)  # ω0 T per rad/s of motor velocity
        self.reset()

    @property
    def pole_radius(self) -> float:
        """ρ = sqrt(2β - 1), the radius of every notch's poles."""
        return math.sqrt(2.0 * self.beta - 1.0)

    def reset(self) -> None:
        """All notch states to zero."""
        # per notch: [x(k-1), x(k-2), y(k-1), y(k-2)]
        self._state = [[0.0, 0.0, 0.0, 0.0] for _ in self.multiples]

    def coefficients(self, velocity: float) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """``(b, a)`` of each notch at motor ``velocity`` (``None``: bypassed)."""
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        beta = self.beta
        for wT in self._notch_angles(velocity):
            if wT is None:
                out.append(None)
                continue
            c = math.cos(wT)
            out.append(
                (
                    np.array([beta, -2.0 * beta * c, beta]),
                    np.array([1.0, -2.0 * beta * c, 2.0 * beta - 1.0]),
                )
            )
        return out

    def _notch_angles(self, velocity: float) -> list[float | None]:
        speed = abs(velocity)
        if not (math.isfinite(speed) and speed >= self.min_speed_radps):
            return [None] * len(self._wT)
        return [w * speed if w * speed < math.pi else None for w in self._wT]

    def step(self, x: float, velocity: float) -> float:
        """One sample: torque ``x`` through every notch, tuned to motor ``velocity``."""
        beta = self.beta
        a2 = 2.0 * beta - 1.0
        y = x
        for wT, st in zip(self._notch_angles(velocity), self._state, strict=True):
            x1, x2, y1, y2 = st
            if wT is None:
                out = y
            else:
                c2 = 2.0 * math.cos(wT)
                out = beta * (y - c2 * x1 + x2) + beta * c2 * y1 - a2 * y2
            st[0], st[1], st[2], st[3] = y, x1, out, y1
            y = out
        return y

    def filter(
        self, x: np.ndarray | Sequence[float], velocity: np.ndarray | Sequence[float]
    ) -> np.ndarray:
        """Whole arrays (torque, motor velocity) through the same recursion as
        :meth:`step` (same operations, so the same numbers), continuing from and
        updating its state.  The recursion is time-varying, so it runs as a loop over
        Python floats rather than through ``scipy.signal.lfilter``."""
        data = np.asarray(x, dtype=np.float64)
        vel = np.asarray(velocity, dtype=np.float64)
        if data.ndim != 1 or data.shape != vel.shape:
            raise ValueError(
                f"filter expects two 1-D arrays of equal length, got {data.shape} and {vel.shape}"
            )
        beta = self.beta
        a2 = 2.0 * beta - 1.0
        min_speed = self.min_speed_radps
        pi = math.pi
        cos = math.cos
        speeds = np.abs(vel).tolist()
        y = data.tolist()
        for w, st in zip(self._wT, self._state, strict=True):
            x1, x2, y1, y2 = st
            out = []
            append = out.append
            for xin, speed in zip(y, speeds, strict=True):
                # NaN speed fails the first test, infinite speed the second: bypass
                if speed >= min_speed and w * speed < pi:
                    c2 = 2.0 * cos(w * speed)
                    o = beta * (xin - c2 * x1 + x2) + beta * c2 * y1 - a2 * y2
                else:
                    o = xin
                x2, x1, y2, y1 = x1, xin, y1, o
                append(o)
            st[0], st[1], st[2], st[3] = x1, x2, y1, y2
            y = out
        return np.array(y, dtype=np.float64)
