"""The built-in strain-gauge torque sensor of the flexspline ([Taghirad97] §2, Eqs. 1-4).

Eight gauges in four rosettes on the flexspline diaphragm, wired as a Wheatstone bridge:
each gauge reads the torsional strain plus the elliptical wave of the wave generator
(Hashimoto's model, [Taghirad97] Eq. 1); with perfect placement the wave terms cancel
(Eq. 3) and the bridge gives K ε_t E_sup (Eq. 4). Circumferential positioning errors and
per-gauge sensitivity errors leave a residual at twice the wave-generator angle, the
sensor's own ripple (§2, §4). A cubic nonlinearity and a Dahl hysteresis, small by
default, make the calibration of §3 realistic.

Pure numerics: no CAN, no I/O, no clock. The geometry, the sign convention and the
equations as ported are in ``docs/sensor-model.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hdhil.core.dataconf import check_fields

__all__ = [
    "BRIDGE_SIGN",
    "GAUGE_COUNT",
    "NOMINAL_ANGLE_DEG",
    "BridgeConfig",
    "GaugeHysteresis",
    "StrainGaugeBridge",
    "bridge_output_V",
]

GAUGE_COUNT = 8
#: Nominal angular position of gauges R1..R8 on the diaphragm ([Taghirad97] Fig. 2).
NOMINAL_ANGLE_DEG: tuple[float, ...] = (0.0, 0.0, 90.0, 90.0, 180.0, 180.0, 270.0, 270.0)
#: s_j = σ_j: +1 for odd gauges (R1, R3, ...), −1 for even ([Taghirad97] Eqs. 1 and 4).
BRIDGE_SIGN: tuple[int, ...] = (1, -1, 1, -1, 1, -1, 1, -1)


def bridge_output_V(
    strains: np.ndarray | list[float] | tuple[float, ...],
    gauge_factors: np.ndarray | list[float] | tuple[float, ...] | float,
    supply_V: float,
) -> float:
    """Bridge output voltage E_out for 4 or 8 gauge strains ([Taghirad97] Eq. 4).

    ``E_out = E_sup / n · Σ_j s_j K_j ε_j`` with s = (+, −, +, −, ...): for n = 4 and a
    common gauge factor K this is Eq. 4, ``K/4 (ε1 + ε3 − ε2 − ε4) E_sup``; for n = 8
    each arm holds two gauges in series (R1+R5, R2+R6, R3+R7, R4+R8).  Linear in the
    strains, as the seed's Eq. 4 (the small-strain form of the Wheatstone bridge).
    """
    eps = np.asarray(strains, dtype=float)
    n = eps.shape[-1]
    if n not in (4, 8):
        raise ValueError(f"a bridge of 4 or 8 gauges, got {n} strains")
    k = np.broadcast_to(np.asarray(gauge_factors, dtype=float), eps.shape)
    signs = np.asarray(BRIDGE_SIGN[:n], dtype=float)
    return float(supply_V / n * np.sum(signs * k * eps))


@dataclass(frozen=True)
class BridgeConfig:
    """The emulated torque sensor: gauges, bridge, amplifier ([Taghirad97] §2).

    - ``volt2Nm`` 6.62 Nm/V: the TRUE small-signal gain of the emulated chain (torque
      per volt at the amplifier output).  [Taghirad97] Table 1 measured 6.60 Nm/V; the
      emulator's sensor is deliberately a little different, so that a firmware that
      assumes 6.6 has a 0.3 % gain error until the sensor is calibrated (``hdhil
      calibrate``, [Taghirad97] §3).  The torsional strain per Nm follows from it
      (:attr:`StrainGaugeBridge.strain_per_Nm`): with perfect gauges and 6.6 Nm/V it is
      1 / (6.6 · 1000 · 2 · 10 V) = 7.58e-6 per Nm, i.e. 303 µε at the rated 40 Nm.
    - ``gauge_factor`` K = 2.0: a typical foil gauge (not given in the seed).
    - ``supply_V`` 10 V and ``amplifier_gain`` 1000: [Taghirad97] §2.
    - ``wave_normal_strain`` Ψ_n and ``wave_shear_strain`` Ψ_s, 150 µε each: the
      amplitudes of the strain the elliptical wave generator induces at a gauge (common
      and differential part, see the module docstring; Ψ_0 = 2 Ψ_s in Eq. 2).  Not
      given in the seed; of the order of the rated torsional strain, so that a single
      rosette pair would show a ±20 Nm modulation (why Hashimoto needs two pairs, §4).
    - ``position_error_deg``: circumferential positioning error of R1..R8 in degrees.
      Default: rosette B (R3, R4) 0.5° and rosette D (R7, R8) −0.2° off their 90°
      spacing (§2: "two Rosette strain-gauges are mounted in an angle different than
      90° from each other").
    - ``sensitivity_error`` δ_j of R1..R8: relative gauge-factor error, lumping the
      gauge-factor tolerance with the radial and angular positioning errors (§2).
      Default: within ±0.5 %.
    - ``nonlinearity``: cubic gauge nonlinearity, the reading error at the rated
      torque as a fraction of it (``rated_torque_Nm`` 40 Nm, [Taghirad97] §2):
      ``ΔT = nonlinearity · T_rated · (T / T_rated)³``.  Default 0.1 %.
    - ``hysteresis_Nm`` / ``hysteresis_span_Nm``: gauge hysteresis (Dahl model,
      :class:`GaugeHysteresis`): loop half-height 0.02 Nm (0.05 % of the rated
      torque), reached after a monotonic torque change of a few ``hysteresis_span_Nm``
      (0.5 Nm).

    With these defaults the residual 2β modulation is 0.073 Nm in amplitude
    (:attr:`StrainGaugeBridge.modulation_amplitude_Nm`): well below the 0.6 Nm
    gear-meshing ripple, which stays the dominant ripple ([Taghirad97] §4: "a small
    fraction of the torque ripples are caused by the non-ideal torque measurement").
    """

    volt2Nm: float = 6.62
    gauge_factor: float = 2.0
    supply_V: float = 10.0
    amplifier_gain: float = 1000.0
    wave_normal_strain: float = 150e-6
    wave_shear_strain: float = 150e-6
    position_error_deg: tuple[float, ...] = (0.0, 0.0, 0.5, 0.5, 0.0, 0.0, -0.2, -0.2)
    sensitivity_error: tuple[float, ...] = (
        0.004,
        -0.003,
        0.002,
        -0.005,
        0.003,
        0.001,
        -0.002,
        0.004,
    )
    nonlinearity: float = 1e-3
    rated_torque_Nm: float = 40.0
    hysteresis_Nm: float = 0.02
    hysteresis_span_Nm: float = 0.5

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "volt2Nm": ">0",
                "gauge_factor": ">0",
                "supply_V": ">0",
                "amplifier_gain": ">0",
                "wave_normal_strain": ">=0",
                "wave_shear_strain": ">=0",
                "nonlinearity": "finite",
                "rated_torque_Nm": ">0",
                "hysteresis_Nm": ">=0",
                "hysteresis_span_Nm": ">0",
            },
        )
        for name, lo in (("position_error_deg", -45.0), ("sensitivity_error", -0.5)):
            values = getattr(self, name)
            if not isinstance(values, tuple) or len(values) != GAUGE_COUNT:
                raise ValueError(
                    f"BridgeConfig.{name} must list {GAUGE_COUNT} values (R1..R8), got {values!r}"
                )
            for i, v in enumerate(values):
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise ValueError(f"BridgeConfig.{name}[{i}] must be a number, got {v!r}")
                if not (math.isfinite(v) and lo < v < -lo):
                    raise ValueError(
                        f"BridgeConfig.{name}[{i}] must be within ({lo:g}, {-lo:g}), got {v!r}"
                    )

    @classmethod
    def perfect(cls, **changes: float) -> BridgeConfig:
        """A bridge with perfectly placed, identical, ideal gauges (no residual ripple)."""
        base = {
            "position_error_deg": (0.0,) * GAUGE_COUNT,
            "sensitivity_error": (0.0,) * GAUGE_COUNT,
            "nonlinearity": 0.0,
            "hysteresis_Nm": 0.0,
        }
        base.update(changes)
        return cls(**base)  # type: ignore[arg-type]


class StrainGaugeBridge:
    """Eight gauges, the Wheatstone bridge and its amplifier ([Taghirad97] §2, Eqs. 1-4).

    Two equivalent evaluations:

    - gauge by gauge: :meth:`strains` (Eq. 1 for each of R1..R8) and
      :meth:`amplified_V` (Eq. 4 through :func:`bridge_output_V`, times the amplifier
      gain) — the reference;
    - closed form, for the plant's 1 kHz sensor loop: the bridge is linear, so its
      output is ``T / volt2Nm + a cos 2β + b sin 2β`` exactly, with ``a`` and ``b``
      summed once from the gauges (:meth:`modulation_V`).
    """

    def __init__(self, cfg: BridgeConfig) -> None:
        self.cfg = cfg
        self.angles_rad = np.radians(
            np.asarray(NOMINAL_ANGLE_DEG) + np.asarray(cfg.position_error_deg, dtype=float)
        )
        self.gauge_factors = cfg.gauge_factor * (1.0 + np.asarray(cfg.sensitivity_error))
        self.signs = np.asarray(BRIDGE_SIGN, dtype=float)
        # amplifier volts per unit of Σ s_j K_j ε_j
        self._volts_per_sum = cfg.amplifier_gain * cfg.supply_V / GAUGE_COUNT
        # Torsion: s_j σ_j = 1, so V = G E/8 · ε_t · Σ K_j; pick ε_t per Nm for volt2Nm.
        self.strain_per_Nm = float(
            1.0 / (cfg.volt2Nm * self._volts_per_sum * self.gauge_factors.sum())
        )
        # Wave generator: Σ s_j K_j [Ψ_n cos 2(β−α_j) + s_j Ψ_s sin 2(β−α_j)] = A cos 2β + B sin 2β
        c2, s2 = np.cos(2.0 * self.angles_rad), np.sin(2.0 * self.angles_rad)
        k, s = self.gauge_factors, self.signs
        psi_n, psi_s = cfg.wave_normal_strain, cfg.wave_shear_strain
        a = float(np.sum(k * (s * psi_n * c2 - psi_s * s2)))
        b = float(np.sum(k * (s * psi_n * s2 + psi_s * c2)))
        self._mod_cos_V = a * self._volts_per_sum
        self._mod_sin_V = b * self._volts_per_sum
        self._nl = cfg.nonlinearity / (cfg.rated_torque_Nm * cfg.rated_torque_Nm)

    # ------------------------------------------------------------------ gauge by gauge
    def strains(self, torque_Nm: float, beta_rad: float) -> np.ndarray:
        """Strains of R1..R8 ([Taghirad97] Eq. 1, see the module docstring).

        ``torque_Nm``: the torque whose torsional strain the gauges see; ``beta_rad``:
        the wave generator's angle relative to the gauges.
        """
        cfg = self.cfg
        phase = 2.0 * (beta_rad - self.angles_rad)
        eps_t = self.strain_per_Nm * torque_Nm
        return (
            self.signs * eps_t
            + cfg.wave_normal_strain * np.cos(phase)
            + self.signs * cfg.wave_shear_strain * np.sin(phase)
        )

    def bridge_V(self, torque_Nm: float, beta_rad: float) -> float:
        """E_out of the bridge (before the amplifier) from the eight strains (Eq. 4)."""
        return bridge_output_V(
            self.strains(torque_Nm, beta_rad), self.gauge_factors, self.cfg.supply_V
        )

    def amplified_V(self, torque_Nm: float, beta_rad: float) -> float:
        """Amplifier output (gain 1000, [Taghirad97] §2) from the eight strains."""
        return self.cfg.amplifier_gain * self.bridge_V(torque_Nm, beta_rad)

    # ------------------------------------------------------------------ closed form
    def modulation_V(self, beta_rad: float) -> float:
        """The wave generator's residual at the amplifier output (V): ``a cos 2β + b sin 2β``.

        Zero for a perfect bridge (Eq. 3); exactly what :meth:`amplified_V` adds to
        ``torque / volt2Nm``.
        """
        two_beta = 2.0 * beta_rad
        return self._mod_cos_V * math.cos(two_beta) + self._mod_sin_V * math.sin(two_beta)

    def modulation_Nm(self, beta_rad: float) -> float:
        """:meth:`modulation_V` as a torque-equivalent at the true gain (Nm)."""
        return self.modulation_V(beta_rad) * self.cfg.volt2Nm

    @property
    def modulation_amplitude_Nm(self) -> float:
        """Amplitude of the residual 2β modulation, torque-equivalent (Nm)."""
        return math.hypot(self._mod_cos_V, self._mod_sin_V) * self.cfg.volt2Nm

    @property
    def modulation_coefficients_V(self) -> tuple[float, float]:
        """(a, b) of ``a cos 2β + b sin 2β`` at the amplifier output (V)."""
        return self._mod_cos_V, self._mod_sin_V

    @property
    def volt2Nm(self) -> float:
        """Analytic small-signal gain of the chain, Nm per amplifier volt.

        ``1 / (G · E_sup/8 · strain_per_Nm · Σ_j K_j)``, from the gauge factors and the
        torsional strain (Eq. 4); equals ``cfg.volt2Nm`` by construction of
        ``strain_per_Nm``.  This is what the calibration of §3 must recover.
        """
        return float(1.0 / (self._volts_per_sum * self.strain_per_Nm * self.gauge_factors.sum()))

    def nonlinearity_Nm(self, torque_Nm: float) -> float:
        """Cubic gauge nonlinearity, ``nonlinearity · T_rated · (T / T_rated)³`` (Nm)."""
        return self._nl * torque_Nm * torque_Nm * torque_Nm


class GaugeHysteresis:
    """Rate-independent gauge hysteresis (Dahl model), as a torque-equivalent.

    Not in the seed.  State z in (−1, 1); the reading error is ``−height_Nm · z``.  A
    monotonic change of the input torque by ΔT (direction s = sign ΔT) moves z
    exponentially towards s::

        z ← s + (z − s) · exp(−|ΔT| / span_Nm)

    which is the exact solution of Dahl's ``dz/dT = (1 − s z) / span`` over a monotonic
    segment, so the result does not depend on how finely a monotonic path is sampled.
    A loading/unloading cycle much wider than ``span_Nm`` traces a loop of half-height
    ``height_Nm``: the reading lags the load, ``height_Nm`` low while the torque rises
    and as much high while it falls (the unloading curve above the loading curve, as
    usual for strain-gauge sensors).
    """

    __slots__ = ("_last", "_z", "height_Nm", "span_Nm")

    def __init__(self, height_Nm: float, span_Nm: float) -> None:
        if not (math.isfinite(height_Nm) and height_Nm >= 0.0):
            raise ValueError(f"hysteresis height must be >= 0, got {height_Nm!r}")
        if not (math.isfinite(span_Nm) and span_Nm > 0.0):
            raise ValueError(f"hysteresis span must be > 0, got {span_Nm!r}")
        self.height_Nm = height_Nm
        self.span_Nm = span_Nm
        self._z = 0.0
        self._last = 0.0

    @property
    def z(self) -> float:
        """The internal state in (−1, 1)."""
        return self._z

    @property
    def value_Nm(self) -> float:
        """The present reading error ``−height_Nm · z`` (Nm)."""
        return -self.height_Nm * self._z

    def update(self, torque_Nm: float) -> float:
        """Move the input to ``torque_Nm`` (monotonically from the last input); new error."""
        delta = torque_Nm - self._last
        self._last = torque_Nm
        if delta != 0.0:
            s = 1.0 if delta > 0.0 else -1.0
            self._z = s + (self._z - s) * math.exp(-abs(delta) / self.span_Nm)
        return -self.height_Nm * self._z
