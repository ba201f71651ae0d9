"""The reference generator: the amplifier voltage (or desired torque) at each sample.

Ports ``ref_fl = reference_generation(wavetype)`` of [Taghirad97], listing A.1, whose
body the paper does not print: the waves are ours, defined on :class:`ReferenceGenerator`,
with the chirp of [Vertechy] Fig. 5.  The value is computed from the sample index, so no
accumulated phase drifts.
"""

from __future__ import annotations

import math

from hdhil.firmware.config import ReferenceConfig, SpeedLoopConfig, Wave

__all__ = [
    "ReferenceGenerator",
    "SpeedLoop",
]


# The waves ReferenceGenerator.value tells apart, as module globals: an attribute of an
# Enum class (``Wave.SINE``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global (the LQG stage evaluates its desired
# torque wave three times per sample).
_NONE, _STEP, _SINE, _CHIRP, _SQUARE, _TRIANGLE = (
    Wave.NONE,
    Wave.STEP,
    Wave.SINE,
    Wave.CHIRP,
    Wave.SQUARE,
    Wave.TRIANGLE,
)


class ReferenceGenerator:
    """The reference voltage for the servo amplifier at sample k (t = k·Ts).

    Ports ``ref_fl = reference_generation(wavetype)`` ([Taghirad97], listing A.1,
    ``c_int10``; parameters from the ``main()`` mailboxes).  The body of
    ``reference_generation`` (``servo_refgen.h``) is NOT printed in [Taghirad97], so
    these definitions are ours, with b = bias, A = amplitude, f = frequency,
    p = frac(f t) the phase in cycles:

    - NONE:     b (the listing's default ``wavetype = 0``, "no wave generation")
    - SINE:     b + A sin(2π f t)
    - SQUARE:   b + A if p < duty else b − A
    - TRIANGLE: b + A·tri(p), tri rising from 0 at p = 0 to +1 at p = 1/4, falling to
      −1 at p = 3/4 and back to 0 at p = 1 (in phase with the sine)
    - SAWTOOTH: b + A (2p − 1)
    - CHIRP:    b + A sin(2π (f t' + (f1 − f) t'² / (2 T))), t' = t mod T: a linear
      sweep from f = ``frequency_Hz`` to f1 = ``chirp_end_Hz`` over T =
      ``chirp_duration_s``, then again from f (continuous when (f + f1) T / 2 is a
      whole number of cycles).  Starts at b with a rising slope, like the sine.  [Vertechy]
      Fig. 5 identifies the joint "by commanding tau_m with a chirp function"; the
      paper gives no sweep parameters.  Both frequencies must lie below Nyquist.
    - STEP:     b for t < step_time, b + A from then on.  The step sample is the
      first k with k·Ts >= step_time (to within 1e-9 of a sample, so that 0.1 s at
      1 ms steps at k = 100 despite rounding).
    """

    __slots__ = (
        "_amplitude",
        "_bias",
        "_chirp",
        "_duty",
        "_f_ts",
        "_k_step",
        "_wave",
        "cfg",
        "sample_period_s",
    )

    def __init__(self, cfg: ReferenceConfig, sample_period_s: float) -> None:
        if not (math.isfinite(sample_period_s) and sample_period_s > 0):
            raise ValueError(
                f"sample_period_s must be a finite number > 0, got {sample_period_s!r}"
            )
        self.cfg = cfg
        self.sample_period_s = sample_period_s
        self._wave = Wave(cfg.wave)
        self._bias = cfg.bias_V
        self._amplitude = cfg.amplitude_V
        self._duty = cfg.duty
        self._f_ts = cfg.frequency_Hz * sample_period_s  # cycles per sample
        self._k_step = math.ceil(round(cfg.step_time_s / sample_period_s, 9))
        # chirp: (f0, (f1 - f0) / (2 T), T)
        self._chirp = (
            cfg.frequency_Hz,
            (cfg.chirp_end_Hz - cfg.frequency_Hz) / (2.0 * cfg.chirp_duration_s),
            cfg.chirp_duration_s,
        )
        nyquist = 0.5 / sample_period_s
        if self._wave is Wave.CHIRP and max(cfg.frequency_Hz, cfg.chirp_end_Hz) >= nyquist:
            raise ValueError(
                f"reference: a chirp up to {max(cfg.frequency_Hz, cfg.chirp_end_Hz):g} Hz "
                f"does not fit below the {nyquist:g} Hz Nyquist frequency"
            )

    def phase(self, k: int) -> float:
        """p = frac(f·t) at sample k, in [0, 1)."""
        cycles = k * self._f_ts
        return cycles - math.floor(cycles)

    def value(self, k: int) -> float:
        """Reference voltage at sample ``k`` (t = k·Ts)."""
        wave = self._wave
        b = self._bias
        if wave is _NONE:
            return b
        A = self._amplitude
        if wave is _STEP:
            return b if k < self._k_step else b + A
        if wave is _SINE:
            return b + A * math.sin(2.0 * math.pi * k * self._f_ts)
        if wave is _CHIRP:
            f0, half_rate, period = self._chirp
            t = math.fmod(k * self.sample_period_s, period)
            return b + A * math.sin(2.0 * math.pi * t * (f0 + half_rate * t))
        p = self.phase(k)
        if wave is _SQUARE:
            return b + A if p < self._duty else b - A
        if wave is _TRIANGLE:
            if p < 0.25:
                tri = 4.0 * p
            elif p < 0.75:
                tri = 2.0 - 4.0 * p
            else:
                tri = 4.0 * p - 4.0
            return b + A * tri
        # Wave.SAWTOOTH
        return b + A * (2.0 * p - 1.0)


class SpeedLoop:
    """The motor-speed PI loop of :class:`~hdhil.firmware.config.SpeedLoopConfig` (not in
    the papers): ``step(k, velocity)`` is the voltage it adds to the reference at sample
    k, from the tachometer velocity (rad/s).  The integrator is clipped to the DAC's full
    scale (``limit_V``), so a saturated command does not wind it up."""

    __slots__ = ("_i", "_k_end", "_k_start", "_ki_ts", "_kp", "_limit", "_rate", "_setpoint")

    def __init__(self, cfg: SpeedLoopConfig, sample_period_s: float, limit_V: float) -> None:
        self._setpoint = cfg.setpoint_radps
        # the first sample at or after start_s (to within 1e-9 of a sample, as the step)
        self._k_start = math.ceil(cfg.start_s / sample_period_s - 1e-9)
        # the ramp: the set point rises by ``_rate`` per sample until sample ``_k_end``
        ramp = max(1, round(cfg.ramp_s / sample_period_s))
        self._k_end = self._k_start + ramp
        self._rate = math.pi / ramp  # the ramp's phase per sample
        self._kp = cfg.kp_V_per_radps
        self._ki_ts = cfg.ki_V_per_rad * sample_period_s
        self._limit = limit_V
        self._i = 0.0

    def reset(self) -> None:
        """Back to rest: the integrator emptied."""
        self._i = 0.0

    def step(self, k: int, velocity: float) -> float:
        """The loop's voltage at sample ``k`` for the measured ``velocity`` (rad/s)."""
        if k >= self._k_end:
            setpoint = self._setpoint
        elif k < self._k_start:
            setpoint = 0.0
        else:  # a raised cosine: the acceleration rises and falls smoothly
            setpoint = self._setpoint * 0.5 * (1.0 - math.cos((k - self._k_start + 1) * self._rate))
        error = setpoint - velocity
        if not math.isfinite(error):  # a skipped sample: hold the integrator
            return self._i
        out = self._i + self._kp * error
        limit = self._limit
        self._i = min(limit, max(-limit, self._i + self._ki_ts * error))
        return out
