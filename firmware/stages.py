"""The pure stages of the 1 kHz interrupt handler ``c_int10`` ([Taghirad97], listing A.1).

Source: [Taghirad97], Appendix A.1 ``free_kalman.c``.
Each function or class here ports one line (or one helper function) of ``c_int10``;
none touches a bus, a clock or any global state.  The torque-ripple Kalman filter is
in :mod:`firmware.ripple`, the sequencing of the stages in :mod:`firmware.isr`.

The listing computes in 32-bit ``float`` on a TMS320C30; the port uses Python floats
(IEEE double), so results agree with the listing to single precision, not bit for bit.
"""

from __future__ import annotations

import math

from hdhil.core.converter import Converter
from hdhil.firmware.config import Calibration, PlausibilityConfig, ReferenceConfig, Wave

__all__ = [
    "AdcSource",
    "CstSource",
    "Differentiator",
    "EncoderUnwrap",
    "LowPass",
    "ReferenceGenerator",
    "SensorPlausibility",
    "VelocityIntegrator",
    "adc_read",
    "calibrate",
    "dac_write",
    "expected_torque",
    "filtered_torque",
    "torque_command_per_mille",
    "torque_error",
]


def adc_read(torque: int, tacho: int, current: int, adc: Converter) -> tuple[float, float, float]:
    """ADC counts to volts: ``(torque_V, tacho_V, current_V)``.

    Ports ``DT1401Read(str_ch, end_ch, a2dsamples)`` and the channel picks
    ``Tacho = a2dsamples[DT140X_CH4]; MotorCurrOut = a2dsamples[DT140X_CH5];
    Torque = a2dsamples[DT140X_CH6]`` ([Taghirad97], listing A.1, ``c_int10``).  On the
    DT1401 the driver returns volts; on our CAN link the drive sends counts, which
    ``adc`` (12 bit, +/-10 V) turns back into volts.
    """
    return adc.to_volts(torque), adc.to_volts(tacho), adc.to_volts(current)


def calibrate(
    torque_V: float, tacho_V: float, current_V: float, cal: Calibration
) -> tuple[float, float, float]:
    """Volts to physical units: ``(T_meas [Nm], vel [rad/s], current [A])``.

    Ports ``vel = Tacho * volt2radps`` and ``T_meas = Torque * volt2Nm`` ([Taghirad97],
    listing A.1, ``c_int10``; gains 56.2565 rad/s/V and 6.6 Nm/V, Table 1).  The
    torque offset is subtracted before scaling (not in the listing).  The listing
    logs ``MotorCurrOut`` in volts; ``cal.volt2amp`` (default 1) scales it to amperes.
    """
    T_meas = (torque_V - cal.torque_offset_V) * cal.volt2Nm
    vel = tacho_V * cal.volt2radps
    current = current_V * cal.volt2amp
    return T_meas, vel, current


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

    __slots__ = ("a_1", "dd", "limit", "nd", "v_1")

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

    def step(self, v: float) -> float:
        """One sample: ``a = nd[0]*v + nd[1]*v_1 - dd[1]*a_1`` clamped to ±``limit``;
        ``v_1 = v; a_1 = a``."""
        if not math.isfinite(v):
            return math.nan
        a = self.nd[0] * v + self.nd[1] * self.v_1 - self.dd[1] * self.a_1
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


class AdcSource:
    """Sensor source of the raw mapping: the listing's ``DT1401Read`` and the
    calibration lines ([Taghirad97], listing A.1, ``c_int10``: ``Tacho = a2dsamples[CH4];
    MotorCurrOut = a2dsamples[CH5]; Torque = a2dsamples[CH6]; vel = Tacho *
    volt2radps; T_meas = Torque * volt2Nm``), on the counts of the drive's sensor frame
    (:class:`firmware.interrupt.AdcSample`).

    Returns ``(T_meas, vel, current, encoder, torque_V, tacho_V)``: the calibrated
    torque (Nm), motor velocity (rad/s) and current (A), the 16-bit encoder count
    ``pcsample``, and the two channels in volts for the stuck-channel check.
    """

    name = "adc"

    __slots__ = ("adc", "cal")

    def __init__(self, adc: Converter, cal: Calibration) -> None:
        self.adc = adc
        self.cal = cal

    def __call__(self, sample: object) -> tuple[float, float, float, int, float, float]:
        s = sample  # AdcSample
        Torque, Tacho, MotorCurrOut = adc_read(s.torque, s.tacho, s.current, self.adc)  # type: ignore[attr-defined]
        T_meas, vel, current = calibrate(Torque, Tacho, MotorCurrOut, self.cal)
        return T_meas, vel, current, s.encoder, Torque, Tacho  # type: ignore[attr-defined]


class CstSource:
    """Sensor source of the CiA 402 cyclic synchronous torque mapping, in place of the
    ADC read and calibration: the drive's torque actual value 0x6077 and position actual
    value 0x6064 (:class:`firmware.interrupt.CstSample`).  Not in the papers.

    - ``T_meas = 0x6077 * 1e-3 * rated_torque_Nm``: CiA 402 scales 0x6077 in per mille
      of 0x6076 motor rated torque, which the controller reads from the drive by SDO at
      boot (:attr:`rated_torque_Nm`).  It is the torque the amplifier produces (from its
      current), not the strain-gauge bridge: the torque ripple and misalignment the
      gauges see are not in it, and neither is the motor's own inertia and friction
      torque, which the gauges on the flexspline do not see either.
    - motor angle ``phi = 0x6064 * 2 pi / encoder_counts_per_rev``; there is no tacho,
      so ``vel`` is the angle through the firmware's own band-limited differentiator
      (:class:`Differentiator`, listing ``Diff_filter``, ``diff_tau_s``), primed with
      the first angle so the first sample gives no velocity step.
    - the encoder count handed to the ripple filter's phase is ``0x6064 & 0xFFFF``, the
      16 bits the raw mapping carries (``EncoderUnwrap`` unwraps it again).
    - there is no current channel: ``current`` is 0.

    Returns the tuple :class:`AdcSource` returns, with ``T_meas`` and ``vel`` in place
    of the channels in volts.
    """

    name = "cst"

    __slots__ = ("_rad_per_count", "differentiator", "primed", "rated_torque_Nm")

    def __init__(
        self,
        rated_torque_Nm: float,
        counts_per_rev: int,
        diff_tau_s: float,
        sample_period_s: float,
    ) -> None:
        if not (math.isfinite(rated_torque_Nm) and rated_torque_Nm > 0):
            raise ValueError(f"rated torque must be > 0 Nm, got {rated_torque_Nm!r}")
        self.rated_torque_Nm = rated_torque_Nm
        self._rad_per_count = 2.0 * math.pi / counts_per_rev
        self.differentiator = Differentiator(diff_tau_s, sample_period_s)
        self.primed = False

    def __call__(self, sample: object) -> tuple[float, float, float, int, float, float]:
        s = sample  # CstSample
        T_meas = s.torque_actual * 1e-3 * self.rated_torque_Nm  # type: ignore[attr-defined]
        angle = s.position * self._rad_per_count  # type: ignore[attr-defined]
        if not self.primed:
            self.differentiator.reseed(angle)
            self.primed = True
        vel = self.differentiator.step(angle)
        return T_meas, vel, 0.0, s.position & 0xFFFF, T_meas, vel  # type: ignore[attr-defined]

    def reset(self) -> None:
        self.differentiator.reset()
        self.primed = False


def torque_command_per_mille(volts: float, torque_per_volt: float, rated_torque_Nm: float) -> int:
    """The command as CiA 402 target torque 0x6071 (INTEGER16, per mille of 0x6076), in
    place of ``write_dac0`` in the standard mapping: the amplifier voltage the handler
    computed times the actuator calibration ``torque_per_volt`` (output-referred Nm per
    V), over the drive's rated torque, rounded and clamped to INTEGER16."""
    if not math.isfinite(volts):
        return 0
    value = round(volts * torque_per_volt / rated_torque_Nm * 1e3)
    return -32768 if value < -32768 else 32767 if value > 32767 else value


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
        "_last",
        "_moved",
        "_periods",
        "_rad_per_count",
        "_raw_last",
        "_run",
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

    _MASK = 0xFFFF
    _HALF = 0x8000
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
        self._last: list[float | None] = [None, None]
        self._run = [0, 0]
        self._moved = [0.0, 0.0]
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
        channels' voltages (for the saturation exclusion)."""
        periods, self._since = self._since, 1
        if encoder is None:
            return
        raw = encoder & self._MASK
        last_raw = self._raw_last
        self._raw_last = raw
        signed = 0
        if last_raw is not None:
            signed = (raw - last_raw) & self._MASK
            if signed >= self._HALF:
                signed -= 0x10000
        d = abs(signed)
        judged = ((torque, torque_V), (velocity, tacho_V)) if self._Ts else ((torque, torque_V),)
        for i, (value, volts) in enumerate(judged):
            if value != self._last[i] or abs(volts) >= self._FULL_SCALE_V:
                self._last[i] = value
                self._run[i] = 0
                self._moved[i] = 0.0
                if i == 1:
                    self._signed = self._periods = 0
                if self._flag(i):
                    self._set(i, False)
                continue
            self._run[i] += 1
            self._moved[i] += d
            if i == 1:
                self._signed += signed
                self._periods += periods
            if (self._flag(i) or self._run[i] < self._samples
                    or self._moved[i] < self._counts_needed):  # fmt: skip
                continue
            if i == 1 and not self._tacho_disagrees(value):
                continue
            self._set(i, True)
            self.events += 1
            if i == 1:
                self.tacho_events += 1

    def _tacho_disagrees(self, velocity: float) -> bool:
        """Whether the encoder's mean velocity over the held reading's samples is further
        from ``velocity`` than the tolerance."""
        assert self._Ts is not None
        if self._periods <= 0:
            return False
        v_enc = self._signed * self._rad_per_count / (self._periods * self._Ts)
        return abs(v_enc - velocity) > self._tolerance + self._share * abs(v_enc)

    def _flag(self, i: int) -> bool:
        return self.torque_stuck if i == 0 else self.tacho_stuck

    def _set(self, i: int, on: bool) -> None:
        if i == 0:
            self.torque_stuck = on
        else:
            self.tacho_stuck = on
        self.revision += 1


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
    _MASK = 0xFFFF
    _HALF = 0x8000

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
        if v_ref is None or not math.isfinite(v):
            if math.isfinite(v):
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
        raw = encoder & self._MASK
        last = self._raw_last
        self._raw_last = raw
        v_prev = self._v_prev
        if math.isfinite(v):
            self._v_prev = v
            if last is not None and v_prev is not None:
                d = (raw - last) & self._MASK
                if d >= self._HALF:
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
        return v, (raw + self._shift) & self._MASK

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


def expected_torque(acc: float, J_load: float, gear_ratio: float) -> float:
    """The crude expected torque: the load's inertial torque.

    Ports ``T_mod = J_load * acc / Gain`` ([Taghirad97], listing A.1, ``c_int10``;
    §4: "the expected torque can be estimated simply by the inertial part of the
    output torque which is the load inertia multiplied to the load acceleration").
    ``acc`` is the motor acceleration, so ``acc / gear_ratio`` is the load's.
    """
    return J_load * acc / gear_ratio


def torque_error(T_meas: float, T_expected: float) -> float:
    """The Kalman filter's measurement y(k) = T_meas(k) − T_exp(k) ([Taghirad97], §4 text
    under Eq. 6; listing A.1 ``Delta_T = T_meas - T_mod``)."""
    return T_meas - T_expected


def filtered_torque(T_meas: float, ripple_predicted: float) -> float:
    """The ripple-free torque, ``Torque_f = T_meas - T_ripple`` ([Taghirad97], listing A.1).

    ``ripple_predicted`` is the ripple the Kalman filter predicted for this sample
    at the previous interrupt (prediction-type filter, Eq. 8; listing comment
    "Finding torque ripple for next iteration: Prediction-Type KF").
    """
    return T_meas - ripple_predicted


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


def dac_write(volts: float, dac: Converter) -> int:
    """The DAC code for a voltage: quantize (nearest) and saturate.

    Ports ``write_dac0(ref_fl)`` ([Taghirad97], listing A.1, ``c_int10``; "floatV for
    MAX-100 servo").  On our link the code travels in the command frame; NaN gives 0.
    """
    return dac.to_counts(volts)
