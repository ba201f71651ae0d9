"""The drive emulator's physics, stepped: :class:`Plant`.

The drive node calls :meth:`Plant.advance` once per SYNC period with the amplifier
input it decoded from the DAC command, then :meth:`Plant.sample` for the ADC and
encoder counts it transmits, and reads the noise-free truth for the truth channel.
Pure numerics: no CAN, no I/O, no wall clock, so a seed gives the same run anywhere.

Signal chain ([Taghirad97] listing A.1: ``write_dac0`` drives the servo amplifier,
``DT1401Read`` samples tacho, current monitor and torque bridge, ``pcsample`` is the
quadrature count)::

    V_dac --amplifier--> i --Kt--> motor torque --harmonic drive--> load <-- tau_l
                                    (two-mass flexible joint, [Vertechy] Eq. 1)
    T_true + mesh ripple + misalignment --gauges, bridge, amplifier--> ADC_torque
    omega_m --tacho--> ADC_tacho ; i --monitor--> ADC_current
    theta_m --quadrature--> ENC_count
"""

from __future__ import annotations

import math

import numpy as np

from hdhil.core.converter import Converter
from hdhil.hostsim.bridge import GaugeHysteresis, StrainGaugeBridge
from hdhil.hostsim.plant.config import TWO_PI, PlantConfig
from hdhil.hostsim.plant.linear import (
    discrete_model,
    has_ideal_amplifier,
    person_model,
    prescribed_model,
    zoh,
)
from hdhil.hostsim.plant.stability import NonFiniteStateError, check_step
from hdhil.hostsim.plant.truth import RippleParts, Truth
from hdhil.hostsim.sensor_faults import SensorHook

__all__ = ["ENCODER_MODULUS", "Plant"]

ENCODER_MODULUS = 1 << 16  # 16-bit wrapping quadrature counter ([Taghirad97]: short pcsample)
_NOISE_BLOCK = 4096  # standard normals drawn from the generator at a time
_new_tuple = tuple.__new__  # a NamedTuple from a complete tuple of its fields
_INF = math.inf


def _encoder_count(counts: float) -> int:
    """The 16-bit count of an unwrapped position in counts; 0 for one that is not a
    finite number (an angle past the float range has no count to read)."""
    return math.floor(counts) % ENCODER_MODULUS if math.isfinite(counts) else 0


class ConfiguredConverters:
    """The converters and torque limit a drive node reads from a plant
    (:class:`hostsim.plant_model.PlantModel`), as its ``cfg`` (a
    :class:`~hdhil.hostsim.plant.config.PlantConfig`) gives them."""

    cfg: PlantConfig

    @property
    def adc(self) -> Converter:
        """The sensors' ADC (``cfg.adc``)."""
        return self.cfg.adc

    @property
    def dac(self) -> Converter:
        """The converter of the drive's command input (``cfg.dac``)."""
        return self.cfg.dac

    @property
    def max_motor_torque_Nm(self) -> float:
        """Motor torque at the current limit, output-referred (``cfg.max_motor_torque_Nm``)."""
        return self.cfg.max_motor_torque_Nm


class Plant(ConfiguredConverters):
    """The drive emulator's physics, advanced in zero-order-hold steps.

    Integration (per sub-step of ``h = dt / substeps``): the linear part (current
    lag, both inertias, flexspline spring/damper, viscous friction) is advanced with
    its exact matrix exponential (:func:`discrete_model`), computed once per distinct
    ``h`` and applied as unrolled float arithmetic; the Coulomb friction (tanh) and
    the external load torque are held constant over each sub-step at their values at
    its start.  With Coulomb friction off the result is exact for any ``substeps``.
    Gravity (:class:`GravityConfig`) is held over each sub-step like the Coulomb
    friction.  With a prescribed link motion (:class:`LinkMotionConfig`) the map is
    :func:`prescribed_model`'s (motor side and the link's exosystem, exact), and the
    link angle and velocity are set from the prescription at the end of each step.

    The torque sensor is evaluated once per :meth:`advance` (and by
    :meth:`hold_locked`): ``T_ripple`` and the gauge hysteresis state are updated
    from the state at the end of the step.  :meth:`truth` reads the state as it stands
    (:class:`~hdhil.hostsim.plant.truth.Truth`).
    """

    def __init__(self, cfg: PlantConfig, seed: int = 0, faults: SensorHook | None = None) -> None:
        self.cfg = cfg
        self.seed = seed
        #: Sensor-fault hook (:meth:`hdhil.rig.faults.FaultInjector.sensors`) applied to every
        #: :meth:`sample`; None = healthy sensors.
        self.faults = faults
        dt_cfg = cfg.drivetrain
        self._n = dt_cfg.gear_ratio
        self._substeps = cfg.substeps
        self._maps: dict[float, tuple[float, ...]] = {}
        # A state whose size times this overflows cannot be read by the sensors (the
        # 4x motor-angle ripple, the spring and damper torques): a failed step.
        self._state_scale = 8.0 * max(self._n, dt_cfg.k_flex, dt_cfg.c_flex, 1.0)
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
        self._i_cmd = 0.0
        self._tau_load = 0.0
        self._profile = None if cfg.load.kind == "none" else cfg.load.value
        self._const_loads = (0.0,) * self._substeps
        # gravity and prescribed link motion ([Vertechy])
        self._mgl = cfg.gravity.mgl_Nm
        self._g_off = math.radians(cfg.gravity.offset_deg)
        if cfg.link.worn or cfg.link.holds_weight:
            raise ValueError(
                "plant.link stiffness_Nm_per_rad, damping_Nms_per_rad and holds_weight are "
                "for a joint of an arm (a [robot] scenario); a single joint's link follows "
                "its motion exactly"
            )
        self._link = cfg.link if cfg.link.active else None
        self._person_maps: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        if self._link is not None:
            # t = 0: a rigid joint moving with the link (no twist, no velocity jump)
            self._ql = self._link.angle(0.0)
            self._wl = self._wm = self._link.velocity(0.0)
        # sensors
        s = cfg.sensors
        self._spring_only = s.torque_measures == "spring"
        self.bridge = StrainGaugeBridge(cfg.bridge)
        self._volt2Nm = cfg.bridge.volt2Nm
        self._hysteresis = GaugeHysteresis(cfg.bridge.hysteresis_Nm, cfg.bridge.hysteresis_span_Nm)
        self._parts = (0.0, 0.0, 0.0, 0.0, 0.0)  # RippleParts, built when asked for
        self._T_true = 0.0
        self._T_ripple = 0.0
        self._update_sensor()
        self._rng = np.random.Generator(np.random.PCG64(seed))
        self._noise: list[float] = []
        self._noise_pos = 0
        self._sig_torque_V = s.torque_noise_Nm / self._volt2Nm
        self._sig_tacho_V = s.tacho_noise_radps / s.volt2radps
        self._sig_current_V = s.current_noise_A / s.current_monitor_A_per_V
        self._cpr_per_rad = s.encoder_counts_per_rev / TWO_PI

    # ------------------------------------------------------------------ dynamics
    def set_load_torque(self, torque_Nm: float) -> None:
        """External torque on the load, ``tau_l`` of [Vertechy] Eq. 1 (Nm, output).

        Positive drives the load forward.  Held until changed; 0 is free motion.  Adds
        to the gravity torque (:class:`GravityConfig`).  With a prescribed link motion
        it has no effect: the environment imposes the link's motion whatever torque
        anyone else applies.
        """
        if not math.isfinite(torque_Nm):
            raise ValueError(f"load torque must be finite, got {torque_Nm!r}")
        self._tau_load = float(torque_Nm)
        self._const_loads = (self._tau_load,) * self._substeps

    def retune(self, cfg: PlantConfig) -> None:
        """Swap in ``cfg``, which may differ from :attr:`cfg` in ripple and sensor noise
        only (the drive's object 0x2300): the ripple is read at every sensor update, the
        noise deviations are refreshed here.  The state, the clock and the noise stream go
        on where they are."""
        self.cfg = cfg
        s = cfg.sensors
        self._sig_torque_V = s.torque_noise_Nm / cfg.bridge.volt2Nm
        self._sig_tacho_V = s.tacho_noise_radps / s.volt2radps

    def hold_locked(self, theta_motor: float, torque_Nm: float) -> None:
        """Static state of the calibration rig ([Taghirad97] §3): wave generator locked.

        The motor shaft (wave generator) is held at ``theta_motor`` (rad, unwrapped)
        and the flexspline carries ``torque_Nm`` (an arm and weight on the output):
        twist ``torque_Nm / k_flex``, output angle ``theta_motor / N - twist``, all
        velocities and the current zero.  The torque sensor is updated as by
        :meth:`advance` (the gauge hysteresis follows the torque monotonically from its
        previous value); :attr:`time` does not move.  The next :meth:`advance` starts
        from this state with the lock released.
        """
        if not (math.isfinite(theta_motor) and math.isfinite(torque_Nm)):
            raise ValueError(
                f"hold_locked needs finite numbers, got {theta_motor!r}, {torque_Nm!r}"
            )
        if not (abs(theta_motor) + abs(torque_Nm)) * self._state_scale < _INF:
            raise ValueError(
                f"hold_locked: {theta_motor!r} rad, {torque_Nm!r} Nm are beyond what the "
                "sensors can read"
            )
        if self._link is not None:
            raise ValueError("hold_locked: the link already follows a prescribed motion")
        self._d = torque_Nm / self.cfg.drivetrain.k_flex
        self._ql = theta_motor / self._n - self._d
        self._wm = self._wl = self._i = 0.0
        self._update_sensor()

    def _map(self, dt: float) -> tuple[float, ...]:
        m = self._maps.get(dt)
        if m is None:
            h = dt / self._substeps
            coeffs: list[float] = []
            if self._link is None:
                ad, bd = discrete_model(self.cfg, h)
                # rows d, w_m, w_l, q_l depend on (d, w_m, w_l, i) and (i_cmd, tau_m,
                # tau_l); row i depends on i and i_cmd only.
                for r in (0, 1, 2, 4):
                    coeffs += [float(ad[r, j]) for j in range(4)]
                    coeffs += [float(bd[r, j]) for j in range(3)]
                coeffs += [float(ad[3, 3]), float(bd[3, 0])]
            else:
                a, b = prescribed_model(self.cfg)
                ad, bd = zoh(a, b, h, current_row=2, ideal_amplifier=has_ideal_amplifier(self.cfg))
                # rows d, w_m depend on (d, w_m, i, s, co) and (i_cmd, tau_m); row i on
                # i and i_cmd; rows s, co are the exosystem's rotation by w h.
                for r in (0, 1):
                    coeffs += [float(ad[r, j]) for j in range(5)]
                    coeffs += [float(bd[r, j]) for j in range(2)]
                coeffs += [float(ad[2, 2]), float(bd[2, 0])]
                coeffs += [float(ad[3, 3]), float(ad[3, 4]), float(ad[4, 3]), float(ad[4, 4])]
            m = tuple(coeffs)
            if len(self._maps) >= 16:  # a caller with ever-changing dt: do not grow
                self._maps.clear()
            self._maps[dt] = m
        return m

    def prepare(self, dt: float) -> None:
        """Compute the step map for steps of ``dt`` now (it is otherwise computed, and
        scipy's expm kernel loaded, at the first :meth:`advance` by ``dt``): a node calls
        it before its loop starts, so no cycle stalls on it.  Raises ``ValueError`` if
        the configuration cannot be integrated at this step
        (:func:`~hdhil.hostsim.plant.stability.check_step`)."""
        if not dt > 0.0:
            raise ValueError(f"prepare needs dt > 0, got {dt!r}")
        check_step(self.cfg, dt)  # the configuration can be integrated at this step
        self._maps.get(dt) or self._map(dt)

    def advance(self, volts: float, dt: float) -> None:
        """Integrate from ``time`` to ``time + dt`` with the amplifier input held at ``volts``.

        ``volts`` is the amplifier input (the DAC output voltage); ``dt`` in seconds.
        """
        if not dt > 0.0 or volts != volts:
            raise ValueError(f"advance needs dt > 0 and a number of volts, got {volts!r}, {dt!r}")
        if self._link is not None:
            if self._link.kind == "person":
                self._advance_person(volts, dt)
            else:
                self._advance_prescribed(volts, dt)
            return
        (
            dd, dm, dl, di, du, dtm, dtl,
            md, mm, ml, mi, mu, mtm, mtl,
            ld, lm, ll, li, lu, ltm, ltl,
            qd, qm, ql, qi, qu, qtm, qtl,
            ii, iu,
        ) = self._maps.get(dt) or self._map(dt)  # fmt: skip
        # coefficient <row><column>: rows d (twist), m (w_m), l (w_l), q (q_l), i (current);
        # columns d, m, l, i (state), u (i_cmd), tm / tl (motor / load non-linear torque)
        i_cmd = self._command_current(volts)
        # constant-over-the-step input terms
        du *= i_cmd
        mu *= i_cmd
        lu *= i_cmd
        qu *= i_cmd
        iu *= i_cmd
        cm, cl, inv_eps = self._cm, self._cl, self._inv_eps
        profile = self._profile
        if profile is None:
            loads = self._const_loads
        else:  # the environment is plant physics: evaluated from the plant's own clock
            h = dt / self._substeps
            t0, tau = self._t, self._tau_load
            loads = tuple(tau + profile(t0 + j * h) for j in range(self._substeps))
        tanh, sin = math.tanh, math.sin
        mgl, g_off = self._mgl, self._g_off
        d, wm, wl, i, q_out = self._d, self._wm, self._wl, self._i, self._ql
        for tau_load in loads:
            tm = -cm * tanh(wm * inv_eps)
            tl = tau_load - cl * tanh(wl * inv_eps)
            if mgl:
                tl += mgl * sin(q_out + g_off)
            # the new state from the old one (no tuple built per substep)
            d_new = dd * d + dm * wm + dl * wl + di * i + du + dtm * tm + dtl * tl
            wm_new = md * d + mm * wm + ml * wl + mi * i + mu + mtm * tm + mtl * tl
            wl_new = ld * d + lm * wm + ll * wl + li * i + lu + ltm * tm + ltl * tl
            q_out = q_out + qd * d + qm * wm + ql * wl + qi * i + qu + qtm * tm + qtl * tl
            i = ii * i + iu
            d, wm, wl = d_new, wm_new, wl_new
        # NaN, an infinity or a state too large for the sensors to read (NaN < inf is
        # False): the step failed (:mod:`.stability`)
        if not (abs(d) + abs(wm) + abs(wl) + abs(i) + abs(q_out)) * self._state_scale < _INF:
            self._non_finite(dt, d=d, wm=wm, wl=wl, i=i, ql=q_out)
        self._d, self._wm, self._wl, self._i, self._ql = d, wm, wl, i, q_out
        self._tick(dt)
        self._update_sensor()

    def _non_finite(self, dt: float, **state: float) -> None:
        """Raise :class:`NonFiniteStateError` for a step of ``dt`` that left ``state``
        (the new values, by attribute name) non-finite; the plant keeps its last finite
        state and its clock."""
        names = {"d": "twist", "wm": "motor velocity", "wl": "load velocity",
                 "i": "current", "ql": "load angle"}  # fmt: skip
        scale = self._state_scale
        bad = tuple(names[k] for k, v in state.items() if not abs(v) * scale < _INF)
        raise NonFiniteStateError(self._t + dt, bad or tuple(names[k] for k in state))

    def _command_current(self, volts: float) -> float:
        """The amplifier's current command for ``volts``, clipped at its current limit."""
        i_cmd = self._gain * volts
        if i_cmd > self._ilim:
            i_cmd = self._ilim
        elif i_cmd < -self._ilim:
            i_cmd = -self._ilim
        self._i_cmd = i_cmd
        return i_cmd

    def _tick(self, dt: float) -> None:
        """Advance the clock by ``dt`` (Kahan-compensated sum)."""
        y = dt - self._t_carry
        t = self._t + y
        self._t_carry = (t - self._t) - y
        self._t = t

    def _advance_person(self, volts: float, dt: float) -> None:
        """:meth:`advance` with the link moved as a sum of sinusoids (:func:`person_model`);
        the exosystem starts each step from the plant's clock, as for the sine."""
        maps = self._person_maps
        m = maps.get(dt)
        if m is None:
            a, b = person_model(self.cfg)
            m = zoh(
                a,
                b,
                dt / self._substeps,
                current_row=2,
                ideal_amplifier=has_ideal_amplifier(self.cfg),
            )
            if len(maps) >= 16:
                maps.clear()
            maps[dt] = m
        ad, bd = m
        i_cmd = self._command_current(volts)
        link = self._link
        assert link is not None
        comps = link.components()
        t0 = self._t
        z = np.empty(ad.shape[0])
        z[0], z[1], z[2] = self._d, self._wm, self._i
        for j, (_a, w, p) in enumerate(comps):
            z[3 + 2 * j] = math.sin(w * t0 + p)
            z[4 + 2 * j] = math.cos(w * t0 + p)
        u = np.array([i_cmd, 0.0])
        cm, inv_eps, tanh = self._cm, self._inv_eps, math.tanh
        for _ in range(self._substeps):
            u[1] = -cm * tanh(z[1] * inv_eps)
            z = ad @ z + bd @ u
        d, wm, i = float(z[0]), float(z[1]), float(z[2])
        if not (abs(d) + abs(wm) + abs(i)) * self._state_scale < _INF:
            self._non_finite(dt, d=d, wm=wm, i=i)
        self._d, self._wm, self._i = d, wm, i
        self._tick(dt)
        self._ql = link.angle(self._t)
        self._wl = link.velocity(self._t)
        self._update_sensor()

    def _advance_prescribed(self, volts: float, dt: float) -> None:
        """:meth:`advance` with the link on its prescribed trajectory (:func:`prescribed_model`).

        The exosystem ``(s, co)`` starts each step from the plant's clock, so the link
        phase never drifts; the link angle and velocity are set from the prescription
        at the end of the step.
        """
        (
            dd, dm, di, ds, dc, du, dtm,
            md, mm, mi, ms, mc, mu, mtm,
            ii, iu,
            ss, sc, cs, cc,
        ) = self._map(dt)  # fmt: skip
        i_cmd = self._command_current(volts)
        du *= i_cmd
        mu *= i_cmd
        iu *= i_cmd
        cm, inv_eps, tanh = self._cm, self._inv_eps, math.tanh
        link = self._link
        assert link is not None
        phase = link.omega_radps * self._t
        sn, co = math.sin(phase), math.cos(phase)
        d, wm, i = self._d, self._wm, self._i
        for _ in range(self._substeps):
            tm = -cm * tanh(wm * inv_eps)
            d, wm, i, sn, co = (
                dd * d + dm * wm + di * i + ds * sn + dc * co + du + dtm * tm,
                md * d + mm * wm + mi * i + ms * sn + mc * co + mu + mtm * tm,
                ii * i + iu,
                ss * sn + sc * co,
                cs * sn + cc * co,
            )
        if not (abs(d) + abs(wm) + abs(i)) * self._state_scale < _INF:
            self._non_finite(dt, d=d, wm=wm, i=i)
        self._d, self._wm, self._i = d, wm, i
        self._tick(dt)
        self._ql = link.angle(self._t)
        self._wl = link.velocity(self._t)
        self._update_sensor()

    def _update_sensor(self) -> None:
        """Everything the gauges add to ``T_true`` at the present state (``T_ripple``).

        Mesh ripple and misalignment (:class:`RippleConfig`) are torques the gauges
        see; the gauge nonlinearity and hysteresis act on their sum with ``T_true``;
        the bridge's wave-generator residual ([Taghirad97] §2 Eqs. 1-4) depends on
        ``beta`` only (:attr:`Truth.beta_rad`).  All as torque-equivalents at the true gain.
        """
        r = self.cfg.ripple
        th_m = self._n * (self._ql + self._d)
        q_l = self._ql
        mesh = r.amp2_Nm * math.sin(2.0 * th_m + r.phase2_rad) + r.amp4_Nm * math.sin(
            4.0 * th_m + r.phase4_rad
        )
        mis = 0.5 * r.misalignment_pp_Nm * math.sin(q_l + r.misalignment_phase_rad)
        T_true = self._T_true = self._torque_true()  # for the next sample(s) at this state
        torsion = T_true + mesh + mis
        hyst = self._hysteresis.update(torsion)
        bridge = self.bridge
        nl = bridge.nonlinearity_Nm(torsion)
        mod = bridge.modulation_V(th_m + q_l) * self._volt2Nm
        self._parts = (mesh, mis, mod, nl, hyst)
        self._T_ripple = mesh + mis + mod + nl + hyst

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

        With :attr:`faults` set, the counts then pass through the sensor faults (stuck,
        saturated, encoder glitches, tacho spikes; :mod:`hdhil.hostsim.sensor_faults`).
        """
        pos = self._noise_pos
        noise = self._noise
        if pos + 3 > len(noise):
            noise = self._noise = self._rng.standard_normal(_NOISE_BLOCK).tolist()
            pos = 0
        n_torque, n_tacho, n_current = noise[pos], noise[pos + 1], noise[pos + 2]
        self._noise_pos = pos + 3
        cfg = self.cfg
        s = cfg.sensors
        adc = cfg.adc
        # T_true as _update_sensor found it: the state has not moved since.
        torque_V = (
            (self._T_true + self._T_ripple) / self._volt2Nm
            + s.torque_offset_V
            + self._sig_torque_V * n_torque
        )
        tacho_V = self._n * self._wm / s.volt2radps + self._sig_tacho_V * n_tacho
        current_V = self._i / s.current_monitor_A_per_V + self._sig_current_V * n_current
        theta_motor_unwrapped = self._n * (self._ql + self._d)
        # Converter.to_counts of the three channels, inline (same arithmetic: NaN -> 0,
        # round to nearest, saturate), as this runs every SYNC.
        lsb, lo, hi = adc.lsb_V, adc.code_min, adc.code_max
        try:
            enc = math.floor(theta_motor_unwrapped * self._cpr_per_rad) % ENCODER_MODULUS
            c_torque = round(torque_V / lsb) if torque_V == torque_V else 0
            c_tacho = round(tacho_V / lsb) if tacho_V == tacho_V else 0
            c_current = round(current_V / lsb) if current_V == current_V else 0
        except (OverflowError, ValueError):  # a reading beyond any float: saturate
            enc = _encoder_count(theta_motor_unwrapped * self._cpr_per_rad)
            c_torque, c_tacho, c_current = (
                adc.to_counts(torque_V),
                adc.to_counts(tacho_V),
                adc.to_counts(current_V),
            )
        counts = (
            hi if c_torque > hi else lo if c_torque < lo else c_torque,
            hi if c_tacho > hi else lo if c_tacho < lo else c_tacho,
            hi if c_current > hi else lo if c_current < lo else c_current,
            enc,
        )
        if self.faults is not None:
            return self.faults.apply(self._t, counts, lo, hi, lsb)
        return counts

    # ------------------------------------------------------------------ clock and truth
    @property
    def time(self) -> float:
        """Simulated time in s (sum of the ``dt`` of all :meth:`advance` calls)."""
        return self._t

    def _torque_true(self) -> float:
        """:attr:`Truth.T_true_Nm` at the present state."""
        dt_cfg = self.cfg.drivetrain
        if self._spring_only:
            return dt_cfg.k_flex * self._d
        return dt_cfg.k_flex * self._d + dt_cfg.c_flex * (self._wm - self._wl)

    def truth(self) -> Truth:
        """The plant's ground truth at :attr:`time` (:class:`Truth`, every field filled).

        The external load torque ``tau_l`` is the value held with
        :meth:`set_load_torque` plus the :class:`LoadTorqueConfig` profile at
        :attr:`time`; with a prescribed link motion, what it takes to impose the motion
        at the handle: ``tau_ext`` less gravity and the output bearings' friction
        (``load_friction_Nm``: the drive train's load friction and the link's
        ``bearing_coulomb_Nm``).
        """
        d = self.cfg.drivetrain
        n, twist, wm, wl, q_l = self._n, self._d, self._wm, self._wl, self._ql
        spring = d.k_flex * twist
        transmitted = spring + d.c_flex * (wm - wl)
        tau_d = -d.b_motor * wm - self._cm * math.tanh(wm * self._inv_eps)
        friction = -d.b_load * wl - self._cl * math.tanh(wl * self._inv_eps)
        mgl = self._mgl  # GravityConfig.torque, inline (the same expression)
        tau_g = mgl * math.sin(q_l + self._g_off) if mgl != 0.0 else 0.0
        link = self._link
        if link is None:
            profile = self._profile
            tau_l = self._tau_load + (0.0 if profile is None else profile(self._t))
            tau_ext = tau_l + tau_g + friction
            accel = (transmitted + tau_l + tau_g + friction) / d.J_load
        else:
            accel = link.acceleration(self._t)
            tau_ext = d.J_load * accel - transmitted
            if link.bearing_coulomb_Nm:  # between the sensor and the handle
                friction += link.bearing_friction(wl)
            tau_l = tau_ext - tau_g - friction
        kt_out = n * self.cfg.amplifier.torque_constant_Nm_per_A
        # Built by tuple.__new__, all fields given in order: the NamedTuple's generated
        # __new__ (keyword handling) costs more than the rest of this method.
        return _new_tuple(
            Truth,
            (
                spring if self._spring_only else transmitted,
                n * (q_l + twist),
                q_l,
                n * wm,
                wl,
                kt_out * self._i,
                kt_out * self._i_cmd,
                self._T_ripple,
                tau_ext,
                tau_d,
                transmitted,
                spring,
                self._i,
                tau_l,
                tau_g,
                friction,
                accel,
                _new_tuple(RippleParts, self._parts),
            ),
        )
