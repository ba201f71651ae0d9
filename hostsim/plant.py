"""Physics of the emulated drive: servo amplifier, flexible harmonic-drive joint, sensors.

This module is pure numerics: no CAN, no I/O, no wall clock.  The drive node calls
:meth:`Plant.advance` once per SYNC period with the amplifier input voltage it
decoded from the DAC command, then :meth:`Plant.sample` for the ADC/encoder counts
it transmits, and reads the noise-free truth properties for the scoring channel.

Signal chain (seed 000, listing A.1: ``write_dac0`` drives the MAX-100 servo
amplifier, ``DT1401Read`` samples tacho, current monitor and torque bridge,
``pcsample`` is the quadrature count)::

    V_dac --amplifier--> i --Kt--> motor torque --harmonic drive--> load
                                    (two-mass flexible joint, seed 003 Eq. 1)
    T_true + T_ripple --bridge amp--> ADC_torque ; omega_m --tacho--> ADC_tacho
    i --monitor--> ADC_current ; theta_m --quadrature--> ENC_count

Conventions (all angles in rad, all velocities in rad/s, all torques in Nm):

* Positive amplifier voltage -> positive current -> positive motor torque ->
  positive motor and output rotation.
* "Motor side" quantities (``theta_motor``, ``omega_motor``, ``motor_torque``,
  the tachometer and the encoder) are at the motor shaft / wave generator.
* The mechanical model works with every inertia, stiffness, damping and friction
  **reduced to the output shaft** exactly as seed 003 Eq. 1, with the reduced motor
  angle ``q_m = theta_motor / N`` (N = gear ratio, ideal lossless transmission, so
  the motor torque reduced to the output is ``N * Kt * i``).
* ``T_true`` is the torque the flexspline transmits to the load, positive when the
  motor drives the load forward: ``T_true = k (q_m - q_l) + c (dq_m - dq_l)``.
  Seed 003 defines the sensor torque with the opposite sign,
  ``tau_s = k (theta_l - theta_m)``; for the spring part ``T_true = -tau_s``, and
  in full ``T_true = -(tau_s + c (dtheta_l - dtheta_m))``.  With that sign the
  load equation of Eq. 1 reads ``J_l ddq_l = T_true + tau_l + tau_g``, which is what
  the seed-000 firmware assumes when it models the free-motion torque as
  ``J_load * acc / Gain`` (listing A.1, ``T_mod``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from hdhil.converter import Converter
from hdhil.dataconf import check_fields

__all__ = [
    "AmplifierConfig",
    "DriveTrainConfig",
    "Plant",
    "PlantConfig",
    "RippleConfig",
    "SensorConfig",
    "continuous_model",
    "discrete_model",
]

TWO_PI = 2.0 * math.pi
ENCODER_MODULUS = 1 << 16  # 16-bit wrapping quadrature counter (seed 000: short pcsample)
_NOISE_BLOCK = 4096  # standard normals drawn from the generator at a time


@dataclass(frozen=True)
class AmplifierConfig:
    """Servo amplifier in current mode (seed 000 listing A.1: "floatV for MAX-100 servo").

    ``i_cmd = clip(gain_A_per_V * V_dac, -current_limit_A, +current_limit_A)``; the
    current follows ``i_cmd`` through a first-order lag of time constant
    ``current_lag_s`` (the closed current loop; 0 = ideal, i = i_cmd at once).  The
    motor torque at the motor shaft is ``torque_constant_Nm_per_A * i``.

    The seeds give no amplifier or motor data; all defaults are representative of a
    brushed servo motor on an RHS-20-class harmonic drive, not from the seeds
    (a 0.4 ms lag is a ~400 Hz current loop).
    """

    gain_A_per_V: float = 1.0
    current_lag_s: float = 4e-4
    current_limit_A: float = 6.0
    torque_constant_Nm_per_A: float = 0.06

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "gain_A_per_V": ">0",
                "current_lag_s": ">=0",
                "current_limit_A": ">0",
                "torque_constant_Nm_per_A": ">0",
            },
        )


@dataclass(frozen=True)
class DriveTrainConfig:
    """Two-mass flexible joint, everything reduced to the OUTPUT shaft (seed 003 Eq. 1).

    ``J_m ddq_m = tau_m + tau_d + k (q_l - q_m) + c (dq_l - dq_m)``
    ``J_l ddq_l = tau_l + tau_g - k (q_l - q_m) - c (dq_l - dq_m)``

    with ``q_m = theta_motor / gear_ratio``, ``tau_m = gear_ratio * Kt * i``, the motor
    disturbance ``tau_d = -b_motor dq_m - coulomb_motor tanh(dq_m / friction_smoothing)``
    (motor bearings + wave generator, seed 003: "friction and ripple effects of both
    motor and harmonic drive", here friction only, see :class:`RippleConfig`) and the
    load-side friction ``-b_load dq_l - coulomb_load tanh(dq_l / friction_smoothing)``
    added to the external ``tau_l + tau_g`` (:meth:`Plant.set_load_torque`).

    Defaults and their sources:

    * ``gear_ratio`` 100: seed 000 §2 (RHS series, 100:1) and listing (``Gain = 100``).
    * ``J_motor`` 0.3 kg m²: a 3e-5 kg m² rotor (+ wave generator) times 100²;
      representative of an RHS-20-class harmonic drive, not from the seeds.
    * ``b_motor`` 1.7 Nm s/rad and ``coulomb_motor`` 1.2 Nm (output-referred, i.e.
      0.017 Nm s/rad and 0.012 Nm at the motor): representative of an RHS-20-class
      harmonic drive, not from the seeds; tuned together with ``J_motor`` so that the
      free-motion step of seed 000 Fig. 8 settles to ~156 rad/s with a ~0.19 s
      mechanical time constant (flat from 0.8 s to 1.1 s).
    * ``friction_smoothing`` 0.01 rad/s at the output (1 rad/s at the motor): the
      width of the tanh Coulomb model; a numerical choice, not from the seeds.
    * ``k_flex`` 1.0e4 Nm/rad and ``c_flex`` 5 Nm s/rad: flexspline torsional stiffness
      and structural damping, representative of an RHS-20-class harmonic drive, not
      from the seeds (seed 003's 6.3 kNm/rad and 11.8 Nm s/rad belong to a different
      joint that includes a sensor hub).  With the default inertias the locked-free
      natural frequency ``sqrt(k (1/J_m + 1/J_l))`` is 783 rad/s (125 Hz).
    * ``J_load`` 1.725e-2 kg m²: seed 000 listing A.1 (``J_load``).
    * ``b_load`` 0.01 Nm s/rad and ``coulomb_load`` 0.05 Nm: output bearings of the
      free-motion test stand; representative, not from the seeds.
    """

    gear_ratio: float = 100.0
    J_motor: float = 0.3
    b_motor: float = 1.7
    coulomb_motor: float = 1.2
    friction_smoothing: float = 0.01
    k_flex: float = 1.0e4
    c_flex: float = 5.0
    J_load: float = 1.725e-2
    b_load: float = 0.01
    coulomb_load: float = 0.05

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "gear_ratio": ">0",
                "J_motor": ">0",
                "b_motor": ">=0",
                "coulomb_motor": ">=0",
                "friction_smoothing": ">0",
                "k_flex": ">0",
                "c_flex": ">=0",
                "J_load": ">0",
                "b_load": ">=0",
                "coulomb_load": ">=0",
            },
        )

    @property
    def natural_frequency_radps(self) -> float:
        """Undamped flexspline mode ``sqrt(k (1/J_m + 1/J_l))`` in rad/s (seed 003 Eq. 2)."""
        return math.sqrt(self.k_flex * (1.0 / self.J_motor + 1.0 / self.J_load))


@dataclass(frozen=True)
class RippleConfig:
    """Torque ripple and misalignment torque seen by the flexspline strain gauges.

    ``T_ripple = amp2 sin(2 theta_motor + phase2) + amp4 sin(4 theta_motor + phase4)
    + (misalignment_pp / 2) sin(theta_output + misalignment_phase)``

    * 2x and 4x MOTOR angle: gear meshing in two zones plus the bridge modulation
      ``Psi_0 sin(2 beta)`` of the elliptical flexspline (seed 000 §2 Eq. 2 and §4;
      Fig. 8: peaks at 312 and 624 rad/s at 156 rad/s).
    * OUTPUT angle: misalignment of drive shaft and load (seed 000 §5: frequency
      equals the output shaft velocity; 10 Nm p-p before re-assembly, < 2 Nm after).

    Modelling choice: the ripple is superimposed on the transmitted torque at the
    gauges (the measurement path) and does not drive the mechanics.  Seed 000 §4
    says part of it is a real torque oscillation; leaving it out of the dynamics keeps
    the ground truth exactly separable, ``T_meas_clean = T_true + T_ripple``, which is
    what the Kalman filter is scored against.  Being locked to angle, it is also
    present (as a static, position-dependent offset) at standstill.

    Default amplitudes (0.6 Nm and 0.25 Nm, about 19 and 8 LSB of the 12-bit torque
    channel at 6.6 Nm/V) and phases are chosen to look like seed 000 Fig. 8/9; the
    seed's text gives no numbers for them.  Misalignment is off by default.
    """

    amp2_Nm: float = 0.6
    phase2_rad: float = 0.4
    amp4_Nm: float = 0.25
    phase4_rad: float = 1.3
    misalignment_pp_Nm: float = 0.0
    misalignment_phase_rad: float = 0.0

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "amp2_Nm": ">=0",
                "phase2_rad": "finite",
                "amp4_Nm": ">=0",
                "phase4_rad": "finite",
                "misalignment_pp_Nm": ">=0",
                "misalignment_phase_rad": "finite",
            },
        )


@dataclass(frozen=True)
class SensorConfig:
    """Analog sensors ahead of the 12-bit ADC, and the motor encoder.

    * Torque: strain-gauge bridge through its amplifier (gain 1000, 10 V supply, seed
      000 §2), ``V = (T_true + T_ripple) / volt2Nm + torque_offset_V + noise``;
      ``volt2Nm`` 6.6 Nm/V is seed 000 Table 1.
    * Tachometer on the motor: ``V = omega_motor / volt2radps + noise``; 56.2565 rad/s
      per V is seed 000 listing A.1 (``volt2radps``).
    * Amplifier current monitor: ``V = i / current_monitor_A_per_V + noise``
      (representative, not from the seeds).
    * Quadrature encoder on the motor, ``encoder_counts_per_rev`` counts per motor
      revolution (8000 = 2000 lines x 4; representative, not from the seeds), read as
      a 16-bit wrapping count (seed 000 listing: ``short pcsample``).

    Noise standard deviations are in physical units (Nm, rad/s at the motor, A),
    white and Gaussian; representative values, not from the seeds.
    """

    volt2Nm: float = 6.6
    torque_offset_V: float = 0.0
    torque_noise_Nm: float = 0.02
    volt2radps: float = 56.2565
    tacho_noise_radps: float = 0.05
    current_monitor_A_per_V: float = 1.0
    current_noise_A: float = 0.0
    encoder_counts_per_rev: int = 8000

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "volt2Nm": ">0",
                "torque_offset_V": "finite",
                "torque_noise_Nm": ">=0",
                "volt2radps": ">0",
                "tacho_noise_radps": ">=0",
                "current_monitor_A_per_V": ">0",
                "current_noise_A": ">=0",
            },
        )
        cpr = self.encoder_counts_per_rev
        if isinstance(cpr, bool) or not isinstance(cpr, int) or cpr <= 0:
            raise ValueError(
                f"SensorConfig.encoder_counts_per_rev must be an integer > 0, got {cpr!r}"
            )


@dataclass(frozen=True)
class PlantConfig:
    """Everything the drive emulator's physics needs; buildable with ``dataconf.from_dict``.

    ``adc`` converts the three analog sensor voltages to counts, ``dac`` is the
    converter the drive node uses to turn received DAC counts into the amplifier
    voltage (``dac.to_volts``) before calling :meth:`Plant.advance`.  ``substeps`` is
    the number of internal integration steps per :meth:`Plant.advance` call.
    """

    amplifier: AmplifierConfig = field(default_factory=AmplifierConfig)
    drivetrain: DriveTrainConfig = field(default_factory=DriveTrainConfig)
    ripple: RippleConfig = field(default_factory=RippleConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    adc: Converter = field(default_factory=Converter)
    dac: Converter = field(default_factory=Converter)
    substeps: int = 4

    def __post_init__(self) -> None:
        for name, cls in (
            ("amplifier", AmplifierConfig),
            ("drivetrain", DriveTrainConfig),
            ("ripple", RippleConfig),
            ("sensors", SensorConfig),
            ("adc", Converter),
            ("dac", Converter),
        ):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"PlantConfig.{name} must be a {cls.__name__}")
        s = self.substeps
        if isinstance(s, bool) or not isinstance(s, int) or not 1 <= s <= 10_000:
            raise ValueError(f"PlantConfig.substeps must be an integer 1..10000, got {s!r}")


def continuous_model(cfg: PlantConfig) -> tuple[np.ndarray, np.ndarray]:
    """Linear part of amplifier + seed 003 Eq. 1 as ``dz/dt = A z + B u``.

    State ``z = [d, w_m, w_l, i, q_l]`` with the flexspline twist ``d = q_m - q_l``
    (output-referred), reduced motor velocity ``w_m = dq_m/dt``, load velocity ``w_l``,
    motor current ``i`` and load angle ``q_l``.  Input ``u = [i_cmd, tau_m_nl, tau_l_nl]``:
    commanded current (A) and the non-linear / external torques on the motor and
    load inertia (Nm at the output).  Viscous friction is in ``A``; Coulomb friction
    and external torques enter through ``tau_*_nl``.  With ``current_lag_s == 0`` the
    current row is zero and ``i_cmd`` drives the motor directly.
    """
    dt_cfg = cfg.drivetrain
    amp = cfg.amplifier
    jm, jl = dt_cfg.J_motor, dt_cfg.J_load
    k, c = dt_cfg.k_flex, dt_cfg.c_flex
    kt_out = dt_cfg.gear_ratio * amp.torque_constant_Nm_per_A  # Nm at the output per A
    a = np.zeros((5, 5))
    b = np.zeros((5, 3))
    # d' = w_m - w_l
    a[0, 1], a[0, 2] = 1.0, -1.0
    # J_m w_m' = N Kt i - b_m w_m - k d - c (w_m - w_l) + tau_m_nl
    a[1, 0] = -k / jm
    a[1, 1] = -(dt_cfg.b_motor + c) / jm
    a[1, 2] = c / jm
    b[1, 1] = 1.0 / jm
    # J_l w_l' = k d + c (w_m - w_l) - b_l w_l + tau_l_nl
    a[2, 0] = k / jl
    a[2, 1] = c / jl
    a[2, 2] = -(dt_cfg.b_load + c) / jl
    b[2, 2] = 1.0 / jl
    # i' = (i_cmd - i) / tau_i
    if amp.current_lag_s > 0.0:
        a[1, 3] = kt_out / jm
        a[3, 3] = -1.0 / amp.current_lag_s
        b[3, 0] = 1.0 / amp.current_lag_s
    else:
        b[1, 0] = kt_out / jm
    # q_l' = w_l
    a[4, 2] = 1.0
    return a, b


def discrete_model(cfg: PlantConfig, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation over ``h`` seconds: ``z+ = Ad z + Bd u``.

    ``expm([[A, B], [0, 0]] h) = [[Ad, Bd], [0, I]]`` (the augmented-matrix trick).
    With an ideal amplifier (no lag) the current after the step is ``i_cmd``.
    """
    a, b = continuous_model(cfg)
    n, m = b.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = a
    aug[:n, n:] = b
    e = expm(aug * h)
    ad, bd = e[:n, :n].copy(), e[:n, n:].copy()
    if cfg.amplifier.current_lag_s == 0.0:
        ad[3, :] = 0.0
        bd[3, :] = 0.0
        bd[3, 0] = 1.0
    return ad, bd


class Plant:
    """The drive emulator's physics, advanced in zero-order-hold steps.

    Integration (per sub-step of ``h = dt / substeps``): the linear part (current
    lag, both inertias, flexspline spring/damper, viscous friction) is advanced with
    its exact matrix exponential (:func:`discrete_model`), computed once per distinct
    ``h`` and applied as unrolled float arithmetic; the Coulomb friction (tanh) and
    the external load torque are held constant over each sub-step at their values at
    its start.  With Coulomb friction off the result is exact for any ``substeps``.
    """

    def __init__(self, cfg: PlantConfig, seed: int = 0) -> None:
        self.cfg = cfg
        self.seed = seed
        dt_cfg = cfg.drivetrain
        self._n = dt_cfg.gear_ratio
        self._substeps = cfg.substeps
        self._maps: dict[float, tuple[float, ...]] = {}
        # amplifier
        self._gain = cfg.amplifier.gain_A_per_V
        self._ilim = cfg.amplifier.current_limit_A
        # friction
        self._cm = dt_cfg.coulomb_motor
        self._cl = dt_cfg.coulomb_load
        self._inv_eps = 1.0 / dt_cfg.friction_smoothing
        # state: twist, reduced motor velocity, load velocity, current, load angle
        self._t = 0.0
        self._t_carry = 0.0  # Kahan compensation: time stays exact-ish over 1e6+ steps
        self._d = 0.0
        self._wm = 0.0
        self._wl = 0.0
        self._i = 0.0
        self._ql = 0.0
        self._tau_load = 0.0
        # sensors
        s = cfg.sensors
        self._rng = np.random.Generator(np.random.PCG64(seed))
        self._noise: list[float] = []
        self._noise_pos = 0
        self._sig_torque_V = s.torque_noise_Nm / s.volt2Nm
        self._sig_tacho_V = s.tacho_noise_radps / s.volt2radps
        self._sig_current_V = s.current_noise_A / s.current_monitor_A_per_V
        self._cpr_per_rad = s.encoder_counts_per_rev / TWO_PI

    # ------------------------------------------------------------------ dynamics
    def set_load_torque(self, torque_Nm: float) -> None:
        """External torque on the load, ``tau_l + tau_g`` of seed 003 Eq. 1 (Nm, output).

        Positive drives the load forward.  Held until changed; 0 is free motion.
        """
        if not math.isfinite(torque_Nm):
            raise ValueError(f"load torque must be finite, got {torque_Nm!r}")
        self._tau_load = float(torque_Nm)

    @property
    def load_torque(self) -> float:
        """The external load torque set with :meth:`set_load_torque` (Nm, output)."""
        return self._tau_load

    def _map(self, dt: float) -> tuple[float, ...]:
        m = self._maps.get(dt)
        if m is None:
            ad, bd = discrete_model(self.cfg, dt / self._substeps)
            # rows d, w_m, w_l, q_l depend on (d, w_m, w_l, i) and (i_cmd, tau_m, tau_l);
            # row i depends on i and i_cmd only.
            coeffs: list[float] = []
            for r in (0, 1, 2, 4):
                coeffs += [float(ad[r, j]) for j in range(4)]
                coeffs += [float(bd[r, j]) for j in range(3)]
            coeffs += [float(ad[3, 3]), float(bd[3, 0])]
            m = tuple(coeffs)
            if len(self._maps) >= 16:  # a caller with ever-changing dt: do not grow
                self._maps.clear()
            self._maps[dt] = m
        return m

    def advance(self, volts: float, dt: float) -> None:
        """Integrate from ``time`` to ``time + dt`` with the amplifier input held at ``volts``.

        ``volts`` is the amplifier input (the DAC output voltage); ``dt`` in seconds.
        """
        if not dt > 0.0 or volts != volts:
            raise ValueError(f"advance needs dt > 0 and a number of volts, got {volts!r}, {dt!r}")
        (
            dd, dm, dl, di, du, dtm, dtl,
            md, mm, ml, mi, mu, mtm, mtl,
            ld, lm, ll, li, lu, ltm, ltl,
            qd, qm, ql, qi, qu, qtm, qtl,
            ii, iu,
        ) = self._map(dt)  # fmt: skip
        # coefficient <row><column>: rows d (twist), m (w_m), l (w_l), q (q_l), i (current);
        # columns d, m, l, i (state), u (i_cmd), tm / tl (motor / load non-linear torque)
        i_cmd = self._gain * volts
        if i_cmd > self._ilim:
            i_cmd = self._ilim
        elif i_cmd < -self._ilim:
            i_cmd = -self._ilim
        # constant-over-the-step input terms
        du *= i_cmd
        mu *= i_cmd
        lu *= i_cmd
        qu *= i_cmd
        iu *= i_cmd
        cm, cl, inv_eps, tau_load = self._cm, self._cl, self._inv_eps, self._tau_load
        tanh = math.tanh
        d, wm, wl, i, q_out = self._d, self._wm, self._wl, self._i, self._ql
        for _ in range(self._substeps):
            tm = -cm * tanh(wm * inv_eps)
            tl = tau_load - cl * tanh(wl * inv_eps)
            d, wm, wl, q_out, i = (
                dd * d + dm * wm + dl * wl + di * i + du + dtm * tm + dtl * tl,
                md * d + mm * wm + ml * wl + mi * i + mu + mtm * tm + mtl * tl,
                ld * d + lm * wm + ll * wl + li * i + lu + ltm * tm + ltl * tl,
                q_out + qd * d + qm * wm + ql * wl + qi * i + qu + qtm * tm + qtl * tl,
                ii * i + iu,
            )
        self._d, self._wm, self._wl, self._i, self._ql = d, wm, wl, i, q_out
        y = dt - self._t_carry
        t = self._t + y
        self._t_carry = (t - self._t) - y
        self._t = t

    # ------------------------------------------------------------------ sensors
    def sample(self) -> tuple[int, int, int, int]:
        """Sensor read-out at the current time: (ADC_torque, ADC_tacho, ADC_current, ENC_count).

        The three analog channels go through ``cfg.adc.to_counts`` (round to nearest,
        saturate at the code range); the encoder count is
        ``floor(theta_motor_unwrapped / 2 pi * cpr) mod 65536``.

        Noise: standard normals from ``numpy.random.Generator(PCG64(seed))``, drawn in
        blocks of 4096 and scaled by the configured standard deviations.  Every call
        consumes exactly three (torque, tacho, current) even when a deviation is 0, so
        a given seed gives the same noise sequence whatever the noise settings.
        """
        pos = self._noise_pos
        if pos + 3 > len(self._noise):
            self._noise = self._rng.standard_normal(_NOISE_BLOCK).tolist()
            pos = 0
        n_torque, n_tacho, n_current = self._noise[pos : pos + 3]
        self._noise_pos = pos + 3
        s = self.cfg.sensors
        to_counts = self.cfg.adc.to_counts
        torque_V = (
            (self.T_true + self.T_ripple) / s.volt2Nm
            + s.torque_offset_V
            + self._sig_torque_V * n_torque
        )
        tacho_V = self._n * self._wm / s.volt2radps + self._sig_tacho_V * n_tacho
        current_V = self._i / s.current_monitor_A_per_V + self._sig_current_V * n_current
        enc = math.floor(self.theta_motor_unwrapped * self._cpr_per_rad) % ENCODER_MODULUS
        return to_counts(torque_V), to_counts(tacho_V), to_counts(current_V), enc

    # ------------------------------------------------------------------ truth
    @property
    def time(self) -> float:
        """Simulated time in s (sum of the ``dt`` of all :meth:`advance` calls)."""
        return self._t

    @property
    def T_true(self) -> float:
        """Transmitted flexspline torque ``k (q_m - q_l) + c (dq_m - dq_l)`` (Nm, output).

        Positive when the motor drives the load forward; ``-tau_s`` of seed 003 for
        the spring part (see the module docstring).  Noise- and ripple-free.
        """
        dt_cfg = self.cfg.drivetrain
        return dt_cfg.k_flex * self._d + dt_cfg.c_flex * (self._wm - self._wl)

    @property
    def T_ripple(self) -> float:
        """Ripple + misalignment torque added at the gauges (Nm); see :class:`RippleConfig`."""
        r = self.cfg.ripple
        th_m = self.theta_motor_unwrapped
        return (
            r.amp2_Nm * math.sin(2.0 * th_m + r.phase2_rad)
            + r.amp4_Nm * math.sin(4.0 * th_m + r.phase4_rad)
            + 0.5 * r.misalignment_pp_Nm * math.sin(self._ql + r.misalignment_phase_rad)
        )

    @property
    def theta_motor_unwrapped(self) -> float:
        """Motor (wave generator) angle in rad at the motor shaft, not wrapped."""
        return self._n * (self._ql + self._d)

    @property
    def theta_motor(self) -> float:
        """Motor (wave generator) angle in rad, wrapped to [0, 2 pi)."""
        return self.theta_motor_unwrapped % TWO_PI

    @property
    def omega_motor(self) -> float:
        """Motor velocity in rad/s at the motor shaft (what the tachometer sees)."""
        return self._n * self._wm

    @property
    def theta_output_unwrapped(self) -> float:
        """Output (load) angle in rad, not wrapped."""
        return self._ql

    @property
    def theta_output(self) -> float:
        """Output (load) angle in rad, wrapped to [0, 2 pi)."""
        return self._ql % TWO_PI

    @property
    def omega_output(self) -> float:
        """Output (load) velocity in rad/s."""
        return self._wl

    @property
    def current(self) -> float:
        """Motor current in A (positive drives forward)."""
        return self._i

    @property
    def motor_torque(self) -> float:
        """Electromagnetic motor torque ``Kt i`` in Nm at the MOTOR shaft (x N at the output)."""
        return self.cfg.amplifier.torque_constant_Nm_per_A * self._i
