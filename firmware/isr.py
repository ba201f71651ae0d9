"""The 1 kHz interrupt body ``c_int10`` of seed 000, listing A.1, stage by stage.

Seed: ``/work/shared/seeds/000_ae0a3dbe24949b7c.txt``, Appendix A.1 ``free_kalman.c``.
The handler, as printed (abridged)::

    DT1401Read( str_ch, end_ch, a2dsamples);
    Tacho = a2dsamples[DT140X_CH4]; MotorCurrOut = a2dsamples[DT140X_CH5];
    Torque = a2dsamples[DT140X_CH6];
    vel      = Tacho * volt2radps;
    acc      = Diff_filter( vel);
    T_meas   = Torque * volt2Nm ;
    T_mod    = J_load * acc / Gain;
    Delta_T  = T_meas - T_mod;
    Torque_f = T_meas - T_ripple;
    T_ripple = Kalman (Delta_T, vel, sample_period);
    ref_fl   = reference_generation(wavetype);
    write_dac0( ref_fl );
    copy(&T_meas ...); copy(&vel ...); copy(&MotorCurrOut ...); copy(&Torque_f ...);
    pcsample &= 0x0000ffff; ... ++samplecount;

Not ported: the timer read-out ``timecnt`` (cycle timing is measured by the host
loop) and the GRAM copies (the caller logs :class:`IsrOutput`).

The ripple filter is the listing's (``ripple.mode = "paper"``) or our recommended
angle-locked filter (``"recommended"``, the default), which also uses ``pcsample``,
the encoder count the listing reads, as the motor angle: see
:class:`TorqueFilterChain`.

The firmware never sees ground truth: its only input is :class:`AdcSample`, the raw
counts of the drive's sensor frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware.config import FirmwareConfig
from firmware.ripple import HarmonicKalman, RippleKalman
from firmware.stages import (
    Differentiator,
    EncoderUnwrap,
    ReferenceGenerator,
    VelocityIntegrator,
    adc_read,
    calibrate,
    dac_write,
    expected_torque,
    filtered_torque,
    torque_error,
)

__all__ = ["AdcSample", "InterruptHandler", "IsrOutput", "TorqueFilterChain"]


@dataclass(frozen=True)
class AdcSample:
    """Raw counts from the drive's sensor frame (listing ``DT1401Read`` channels
    CH6 torque bridge, CH4 tachometer, CH5 motor current monitor, and the quadrature
    decoder's 16-bit wrapping pulse count ``pcsample``)."""

    torque: int
    tacho: int
    current: int
    encoder: int


@dataclass(slots=True)
class IsrOutput:
    """What one interrupt produced.

    ``samplecount`` is the index k of the sample this output belongs to (the listing's
    ``samplecount`` before its ``++``); ``reference_V`` is the reference at k and
    ``dac_counts`` its DAC code.  ``ripple`` is the ripple subtracted at k, so
    ``T_filtered = T_meas - ripple`` exactly: in paper mode the prediction the Kalman
    filter made at k − 1 (listing ``T_ripple``), in recommended mode the learned ripple
    map at the angle measured at k.  ``encoder`` is the pulse count masked to 16 bits
    (listing ``pcsample &= 0x0000ffff``), so in 0..65535.  Units: Nm, rad/s, A, rad/s².
    """

    samplecount: int = 0
    dac_counts: int = 0
    reference_V: float = 0.0
    T_meas: float = 0.0
    velocity: float = 0.0
    current: float = 0.0
    acceleration: float = 0.0
    T_expected: float = 0.0
    delta_T: float = 0.0
    T_filtered: float = 0.0
    ripple: float = 0.0
    encoder: int = 0


class TorqueFilterChain:
    """The calibrated-signal part of ``c_int10``: from (T_meas, vel, encoder) to the
    filtered torque.

    Independent of ADC counts, so the same object filters a recorded CSV offline
    exactly as the interrupt handler does online.  The filter follows
    ``cfg.ripple.mode``:

    - ``"paper"``: listing A.1 line by line, :class:`firmware.ripple.RippleKalman`.
      ``Torque_f = T_meas - T_ripple`` with the prediction made at the previous sample,
      then ``T_ripple = Kalman(Delta_T, vel, sample_period)``.  The stored prediction
      starts at 0 like the listing's global ``float T_ripple = 0.0``, so the first
      filtered torque equals the first measured torque.  The encoder is ignored.
    - ``"recommended"``: :class:`firmware.ripple.HarmonicKalman`.  The motor angle is
      the unwrapped encoder count (:class:`firmware.stages.EncoderUnwrap`) times
      2π / ``calibration.encoder_counts_per_rev``, or, with ``phase_source = "tacho"``,
      the integrated velocity (:class:`firmware.stages.VelocityIntegrator`).  The ripple
      at the angle of sample k is subtracted at k, then the filter is updated.

    :meth:`step` returns ``(acceleration, T_expected, delta_T, T_filtered, ripple)``
    with ``T_filtered = T_meas - ripple`` in both modes.
    """

    def __init__(self, cfg: FirmwareConfig) -> None:
        self.cfg = cfg
        self.mode = cfg.ripple.mode
        self.differentiator = Differentiator(cfg.diff_tau_s, cfg.sample_period_s)
        self.kalman: RippleKalman | HarmonicKalman
        if self.mode == "paper":
            self.kalman = RippleKalman(cfg.ripple, cfg.sample_period_s, cfg.gear_ratio)
        else:
            self.kalman = HarmonicKalman(cfg.ripple, cfg.gear_ratio)
        self._paper = self.mode == "paper"
        self._use_encoder = cfg.ripple.phase_source == "encoder"
        self.encoder = EncoderUnwrap()
        self.integrator = VelocityIntegrator(cfg.sample_period_s)
        self._rad_per_count = 2.0 * math.pi / cfg.calibration.encoder_counts_per_rev
        self._J_load = cfg.J_load
        self._gear_ratio = cfg.gear_ratio
        self.T_ripple = 0.0  # listing: float T_ripple = 0.0;
        self.angle = 0.0  # recommended mode: motor angle of the last sample (rad)

    def step(
        self, T_meas: float, velocity: float, encoder: int | None = None
    ) -> tuple[float, float, float, float, float]:
        """One sample: measured torque (Nm), motor velocity (rad/s) and the raw 16-bit
        encoder count (needed in recommended mode with ``phase_source = "encoder"``,
        ignored otherwise).  Returns ``(acceleration, T_expected, delta_T, T_filtered,
        ripple)``.

        In paper mode ``self.T_ripple`` afterwards holds the prediction for the next
        sample (the listing's global).
        """
        acc = self.differentiator.step(velocity)  # acc = Diff_filter( vel);
        T_mod = expected_torque(acc, self._J_load, self._gear_ratio)  # T_mod = J_load*acc/Gain;
        Delta_T = torque_error(T_meas, T_mod)  # Delta_T = T_meas - T_mod;
        if self._paper:
            ripple = self.T_ripple
            Torque_f = filtered_torque(T_meas, ripple)  # Torque_f = T_meas - T_ripple;
            self.T_ripple = self.kalman.step(Delta_T, velocity)  # T_ripple = Kalman(...);
            return acc, T_mod, Delta_T, Torque_f, ripple
        if self._use_encoder:
            if encoder is None:
                raise ValueError(
                    "the recommended ripple filter with phase_source 'encoder' needs the "
                    "encoder count (use phase_source 'tacho' for data without an encoder)"
                )
            angle = self.encoder.step(encoder) * self._rad_per_count
        else:
            angle = self.integrator.step(velocity)
        self.angle = angle
        ripple = self.kalman.step(Delta_T, velocity, angle)  # type: ignore[call-arg]
        self.T_ripple = ripple
        return acc, T_mod, Delta_T, filtered_torque(T_meas, ripple), ripple

    def reset(self) -> None:
        """Back to power-on state: differentiator, angle sources and Kalman filter
        cleared, T_ripple = 0."""
        self.differentiator.reset()
        self.kalman.reset()
        self.encoder.reset()
        self.integrator.reset()
        self.T_ripple = 0.0
        self.angle = 0.0


class InterruptHandler:
    """``c_int10``: one call per sample period, :class:`AdcSample` in, :class:`IsrOutput`
    out.

    The returned :class:`IsrOutput` is one preallocated object, overwritten by every
    call (as the listing's locals are); copy it (``dataclasses.replace`` or
    ``dataclasses.astuple``) to keep a sample.
    """

    def __init__(self, cfg: FirmwareConfig) -> None:
        self.cfg = cfg
        self.chain = TorqueFilterChain(cfg)
        self.reference = ReferenceGenerator(cfg.reference, cfg.sample_period_s)
        self.samplecount = 0  # listing: int samplecount = 0;
        self._out = IsrOutput()

    @property
    def done(self) -> bool:
        """``numsamples`` reached (listing ``main``: ``while (samplecount < numsamples)``);
        never with ``num_samples = 0`` (run until stopped).  The handler itself keeps
        working if called again; stopping is the caller's job, as in ``main``."""
        n = self.cfg.num_samples
        return n > 0 and self.samplecount >= n

    @property
    def startup_dac_counts(self) -> int:
        """The code to output before the first interrupt (listing ``main``:
        ``write_dac0( Vbias )``)."""
        return dac_write(self.cfg.reference.bias_V, self.cfg.dac)

    @property
    def shutdown_dac_counts(self) -> int:
        """The code to output after the last interrupt (listing ``main``:
        ``write_dac0(0.0)``)."""
        return dac_write(0.0, self.cfg.dac)

    def reset(self) -> None:
        """Back to power-on state (samplecount 0, filters cleared).  The output object
        is kept (it is overwritten by the next call)."""
        self.chain.reset()
        self.samplecount = 0

    def __call__(self, sample: AdcSample) -> IsrOutput:
        cfg = self.cfg
        k = self.samplecount
        # DT1401Read(str_ch, end_ch, a2dsamples); Torque = CH6, Tacho = CH4, MotorCurrOut = CH5
        Torque, Tacho, MotorCurrOut = adc_read(sample.torque, sample.tacho, sample.current, cfg.adc)
        # vel = Tacho * volt2radps; T_meas = Torque * volt2Nm;
        T_meas, vel, current = calibrate(Torque, Tacho, MotorCurrOut, cfg.calibration)
        # acc = Diff_filter(vel); T_mod; Delta_T; Torque_f; T_ripple = Kalman(...);
        # (recommended mode: the motor angle from pcsample, the drive's encoder count)
        acc, T_mod, Delta_T, Torque_f, ripple = self.chain.step(T_meas, vel, sample.encoder)
        # ref_fl = reference_generation(wavetype);
        ref_fl = self.reference.value(k)
        # write_dac0( ref_fl );
        dac_counts = dac_write(ref_fl, cfg.dac)

        # copy(&T_meas ...); copy(&vel ...); copy(&MotorCurrOut ...); copy(&Torque_f ...);
        out = self._out
        out.samplecount = k
        out.dac_counts = dac_counts
        out.reference_V = ref_fl
        out.T_meas = T_meas
        out.velocity = vel
        out.current = current
        out.acceleration = acc
        out.T_expected = T_mod
        out.delta_T = Delta_T
        out.T_filtered = Torque_f
        out.ripple = ripple
        out.encoder = sample.encoder & 0xFFFF  # pcsample &= 0x0000ffff;

        self.samplecount = k + 1  # ++samplecount;
        return out
