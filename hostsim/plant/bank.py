"""Several free-link joints stepped as arrays: :class:`PlantBank`.

A process that emulates an arm runs N joints per 1 kHz cycle.  :class:`Plant` steps one
joint in unrolled scalar Python; a :class:`PlantBank` holds the state of N joints as
arrays and advances all of them with one call per numpy operation, so its cost hardly
grows with N while N :class:`Plant` calls grow linearly.  The crossover is measured by
:func:`hdhil.analysis.joint_scaling.joint_scaling` (``docs/design.md``, "Stepping
several joints"); :func:`plant_bank` picks the faster path for a given N
(:class:`ScalarPlants`, N :class:`Plant` objects behind the same interface, below it).

The equations are :class:`Plant`'s ([Vertechy] Eq. 1 with the amplifier and the gauges
of [Taghirad97] §2): the same exact zero-order-hold map per sub-step, with its
coefficients laid out as one (5, 8) matrix per joint (rows d, w_m, w_l, i, q_l; columns
the state, i_cmd and the motor / load non-linear torques) applied by a batched matrix
product; Coulomb friction, gravity and the held load torque enter as in :class:`Plant`.
The sensor read-out (ripple, gauge nonlinearity and hysteresis, bridge residual, noise,
ADC, encoder) is :meth:`Plant.sample`'s, each joint with its own PCG64 stream drawn in
the same blocks, so joint k of a bank and ``Plant(cfgs[k], seeds[k])`` see the same
noise.  Results equal the scalar plant's to round-off, not bitwise (the matrix product
sums in another order; numpy's tanh and sin are not math's): a single joint keeps
:class:`Plant`, whose traces the golden test pins.

Scope: free links only (no prescribed link motion, no load-torque profile, no sensor
faults); those stay with :class:`Plant`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from hdhil.hostsim.bridge import StrainGaugeBridge
from hdhil.hostsim.plant.config import TWO_PI, PlantConfig
from hdhil.hostsim.plant.linear import discrete_model
from hdhil.hostsim.plant.model import _NOISE_BLOCK, ENCODER_MODULUS, Plant

__all__ = ["VECTOR_CROSSOVER", "PlantBank", "ScalarPlants", "plant_bank"]

#: The number of joints from which one :meth:`PlantBank.step` beats N scalar
#: :meth:`Plant.advance` + :meth:`Plant.sample` calls (measured, ``docs/design.md``).
VECTOR_CROSSOVER = 10

# columns of the state buffers: the state (d, w_m, w_l, i, q_l), tanh of the motor and
# load velocities over the friction smoothing, then the inputs held over the step
_D, _WM, _WL, _I, _Q, _FM, _FL, _U, _TAU = range(9)


class PlantBank:
    """N free-link joints (:class:`PlantConfig` each, possibly all different) as arrays.

    :meth:`advance` takes the N amplifier inputs, :meth:`sample` returns the N sensor
    read-outs as :meth:`Plant.sample` does, joint by joint; :meth:`step` does both.
    """

    def __init__(self, cfgs: Sequence[PlantConfig], seeds: Sequence[int]) -> None:
        if len(cfgs) != len(seeds) or not cfgs:
            raise ValueError(f"one seed per joint, got {len(cfgs)} configs, {len(seeds)} seeds")
        for k, cfg in enumerate(cfgs):
            if cfg.link.active or cfg.load.kind != "none":
                raise ValueError(
                    f"PlantBank steps free links without a load profile; joint {k} has "
                    f"link {cfg.link.kind!r}, load {cfg.load.kind!r} (use Plant)"
                )
        if len({cfg.substeps for cfg in cfgs}) != 1:
            raise ValueError("the joints of a bank share the number of sub-steps")
        self.cfgs = tuple(cfgs)
        self.size = n = len(cfgs)
        self._substeps = cfgs[0].substeps
        self._maps: dict[float, np.ndarray] = {}

        def col(values: Sequence[float]) -> np.ndarray:
            return np.array(values, dtype=np.float64)

        dts = [c.drivetrain for c in cfgs]
        self._gear = col([d.gear_ratio for d in dts])
        self._gain = col([c.amplifier.gain_A_per_V for c in cfgs])
        self._ilim = col([c.amplifier.current_limit_A for c in cfgs])
        self._mgl = col([c.gravity.mgl_Nm for c in cfgs])
        self._g_off = col([math.radians(c.gravity.offset_deg) for c in cfgs])
        self._gravity = bool(np.any(self._mgl != 0.0))
        self._tau_load = np.zeros(n)
        # two state buffers (columns above), each sub-step maps one into the other
        self._s = np.zeros((n, 9, 1))
        self._other = np.zeros((n, 9, 1))
        # sensors: per-joint constants of Plant._update_sensor and Plant.sample
        # the sensor's five waves: sin(a θ_m + b q_l + φ) times an amplitude (N, 5);
        # cos 2β as sin(2β + π/2)
        rip = [c.ripple for c in cfgs]
        bridges = [StrainGaugeBridge(c.bridge) for c in cfgs]
        self._arg_th = np.array([2.0, 4.0, 0.0, 2.0, 2.0])
        self._arg_q = np.array([0.0, 0.0, 1.0, 2.0, 2.0])
        self._arg_ph = np.array(
            [[r.phase2_rad, r.phase4_rad, r.misalignment_phase_rad, 0.5 * math.pi, 0.0]
             for r in rip]
        )  # fmt: skip
        self._wave_amp = np.array(
            [
                [r.amp2_Nm, r.amp4_Nm, 0.5 * r.misalignment_pp_Nm,
                 b.modulation_coefficients_V[0] * c.bridge.volt2Nm,
                 b.modulation_coefficients_V[1] * c.bridge.volt2Nm]
                for r, b, c in zip(rip, bridges, cfgs, strict=True)
            ]
        )  # fmt: skip
        self._k = col([d.k_flex for d in dts])
        self._c = col([0.0 if c.sensors.torque_measures == "spring" else c.drivetrain.c_flex
                       for c in cfgs])  # fmt: skip
        self._nl = col([c.bridge.nonlinearity / c.bridge.rated_torque_Nm**2 for c in cfgs])
        self._volt2Nm = col([c.bridge.volt2Nm for c in cfgs])
        self._h_height = col([c.bridge.hysteresis_Nm for c in cfgs])
        self._h_neg_inv_span = col([-1.0 / c.bridge.hysteresis_span_Nm for c in cfgs])
        self._h_z = np.zeros(n)
        self._h_last = np.zeros(n)
        sens = [c.sensors for c in cfgs]
        # the three analog channels as (N, 3): torque, tacho, current
        self._offset_V = np.array([[s.torque_offset_V, 0.0, 0.0] for s in sens])
        self._sigma_V = np.array(
            [
                [s.torque_noise_Nm / c.bridge.volt2Nm, s.tacho_noise_radps / s.volt2radps,
                 s.current_noise_A / s.current_monitor_A_per_V]
                for s, c in zip(sens, cfgs, strict=True)
            ]
        )  # fmt: skip
        self._volt2radps = col([s.volt2radps for s in sens])
        self._current_A_per_V = col([s.current_monitor_A_per_V for s in sens])
        self._cpr_per_rad = col([s.encoder_counts_per_rev / TWO_PI for s in sens])
        adcs = [c.adc for c in cfgs]
        self._lsb = col([a.lsb_V for a in adcs])[:, None]  # fmt: skip
        self._code_min = col([a.code_min for a in adcs])[:, None]
        self._code_max = col([a.code_max for a in adcs])[:, None]
        self._rngs = [np.random.Generator(np.random.PCG64(seed)) for seed in seeds]
        self._noise = np.empty((n, 0, 3))  # scaled by the deviations
        self._clean_V = np.zeros((n, 3))
        self._enc = np.zeros(n)
        self._out = np.empty((n, 4))
        self._noise_pos = 0
        self._T_true = np.zeros(n)
        self._T_ripple = np.zeros(n)
        self._t = 0.0
        self._t_carry = 0.0
        self._update_sensor()

    # ------------------------------------------------------------------ dynamics
    def set_load_torque(self, torques_Nm: Sequence[float] | np.ndarray) -> None:
        """External torque on each joint's load (Nm, output), as
        :meth:`Plant.set_load_torque`: held until changed."""
        tau = np.array(torques_Nm, dtype=np.float64).reshape(self.size)
        if not np.all(np.isfinite(tau)):
            raise ValueError(f"load torques must be finite, got {tau!r}")
        self._tau_load = tau
        self._s[:, _TAU, 0] = self._other[:, _TAU, 0] = tau

    def _map(self, dt: float) -> np.ndarray:
        """The (N, 7, 9) sub-step maps for steps of ``dt``: :meth:`Plant._map`'s
        coefficients (the current row on i and i_cmd only, q_l carried with 1), the
        friction columns times -Coulomb (they multiply the tanh columns), and two more
        rows giving the new velocities over the friction smoothing (for the next tanh)."""
        m = self._maps.get(dt)
        if m is None:
            h = dt / self._substeps
            m = np.zeros((self.size, 7, 9))
            for k, cfg in enumerate(self.cfgs):
                ad, bd = discrete_model(cfg, h)
                for r in (_D, _WM, _WL, _Q):
                    m[k, r, :4] = ad[r, :4]
                    m[k, r, _FM] = -cfg.drivetrain.coulomb_motor * bd[r, 1]
                    m[k, r, _FL] = -cfg.drivetrain.coulomb_load * bd[r, 2]
                    m[k, r, _U] = bd[r, 0]
                    m[k, r, _TAU] = bd[r, 2]
                m[k, _Q, _Q] = 1.0
                m[k, _I, _I] = ad[_I, _I]
                m[k, _I, _U] = bd[_I, 0]
                inv_eps = 1.0 / cfg.drivetrain.friction_smoothing
                m[k, _FM] = inv_eps * m[k, _WM]
                m[k, _FL] = inv_eps * m[k, _WL]
            if len(self._maps) >= 16:
                self._maps.clear()
            self._maps[dt] = m
        return m

    def prepare(self, dt: float) -> None:
        """Compute the step maps for steps of ``dt`` now (:meth:`Plant.prepare`)."""
        if not dt > 0.0:
            raise ValueError(f"prepare needs dt > 0, got {dt!r}")
        self._map(dt)

    def advance(self, volts: Sequence[float] | np.ndarray, dt: float) -> None:
        """Integrate every joint by ``dt`` with its amplifier input held at ``volts[k]``."""
        u = np.asarray(volts, dtype=np.float64)
        if not dt > 0.0 or u.shape != (self.size,) or np.isnan(u).any():
            raise ValueError(
                f"advance needs dt > 0 and {self.size} numbers of volts, got {volts!r}"
            )
        m = self._maps.get(dt)
        if m is None:
            m = self._map(dt)
        a, b = self._s, self._other
        np.clip(self._gain * u, -self._ilim, self._ilim, out=a[:, _U, 0])
        b[:, _U] = a[:, _U]
        if self._gravity:
            mgl, g_off, tau = self._mgl, self._g_off, self._tau_load
            for _ in range(self._substeps):
                a[:, _TAU, 0] = tau + mgl * np.sin(a[:, _Q, 0] + g_off)
                np.matmul(m, a, out=b[:, :7])
                np.tanh(b[:, _FM:_U], out=b[:, _FM:_U])
                a, b = b, a
        else:
            for _ in range(self._substeps):
                np.matmul(m, a, out=b[:, :7])
                np.tanh(b[:, _FM:_U], out=b[:, _FM:_U])
                a, b = b, a
        self._s, self._other = a, b
        y = dt - self._t_carry
        t = self._t + y
        self._t_carry = (t - self._t) - y
        self._t = t
        self._update_sensor()

    def _update_sensor(self) -> None:
        """:meth:`Plant._update_sensor` for all joints, then the noise-free ADC volts and
        the encoder count of the present state (for :meth:`sample_array`)."""
        st = self._s[:, :5, 0]
        d, q_l = st[:, _D], st[:, _Q]
        th_m = self._gear * (q_l + d)
        # one sin over (N, 5): mesh 2x and 4x, misalignment, bridge residual cos / sin 2β
        waves = np.sin(th_m[:, None] * self._arg_th + q_l[:, None] * self._arg_q + self._arg_ph)
        waves *= self._wave_amp
        mesh_mis = waves[:, 0] + waves[:, 1] + waves[:, 2]
        T_true = self._k * d + self._c * (st[:, _WM] - st[:, _WL])
        torsion = T_true + mesh_mis
        # Dahl hysteresis (GaugeHysteresis.update); delta = 0 leaves z as it is
        delta = torsion - self._h_last
        self._h_last = torsion
        sgn = np.sign(delta)
        self._h_z = z = sgn + (self._h_z - sgn) * np.exp(np.abs(delta) * self._h_neg_inv_span)
        T_ripple = mesh_mis + waves[:, 3] + waves[:, 4] + self._nl * torsion**3 - self._h_height * z
        clean = self._clean_V
        clean[:, 0] = (T_true + T_ripple) / self._volt2Nm
        clean[:, 1] = self._gear * st[:, _WM] / self._volt2radps
        clean[:, 2] = st[:, _I] / self._current_A_per_V
        clean += self._offset_V
        self._enc = np.floor(th_m * self._cpr_per_rad) % ENCODER_MODULUS

    # ------------------------------------------------------------------ sensors
    def sample_array(self) -> np.ndarray:
        """The N read-outs as an (N, 4) float array of whole numbers: ADC torque, tacho,
        current, encoder (:meth:`Plant.sample`, the same noise streams)."""
        pos = self._noise_pos
        if pos >= self._noise.shape[1]:
            per_sample = _NOISE_BLOCK // 3
            self._noise = (
                np.stack(
                    [rng.standard_normal(_NOISE_BLOCK)[: 3 * per_sample] for rng in self._rngs]
                ).reshape(self.size, per_sample, 3)
                * self._sigma_V[:, None, :]
            )
            pos = 0
        self._noise_pos = pos + 1
        out = self._out
        codes = out[:, :3]
        np.divide(self._clean_V + self._noise[:, pos], self._lsb, out=codes)
        np.rint(codes, out=codes)
        np.clip(codes, self._code_min, self._code_max, out=codes)
        if np.isnan(codes).any():  # NaN never reaches the hardware as a number
            codes[np.isnan(codes)] = 0.0
        out[:, 3] = self._enc
        return out.copy()

    def sample(self) -> list[tuple[int, int, int, int]]:
        """The N read-outs as :meth:`Plant.sample`'s tuples of ints, joint by joint."""
        return [(int(a), int(b), int(c), int(e)) for a, b, c, e in self.sample_array().tolist()]

    def step(self, volts: Sequence[float] | np.ndarray, dt: float) -> list[tuple[int, ...]]:
        """:meth:`advance` then :meth:`sample`: one cycle of every joint."""
        self.advance(volts, dt)
        return self.sample()  # type: ignore[return-value]

    # ------------------------------------------------------------------ state
    @property
    def time(self) -> float:
        """Simulated time in s (the Kahan-compensated sum of the ``dt`` stepped)."""
        return self._t

    @property
    def state(self) -> np.ndarray:
        """A copy of the (N, 5) state: twist, reduced motor velocity, load velocity,
        current, load angle (the order of :func:`discrete_model`)."""
        return self._s[:, :5, 0].copy()


class ScalarPlants:
    """N :class:`Plant` objects behind :class:`PlantBank`'s interface, stepped one by one:
    the faster path for few joints (and bitwise :class:`Plant`'s results)."""

    def __init__(self, cfgs: Sequence[PlantConfig], seeds: Sequence[int]) -> None:
        if len(cfgs) != len(seeds) or not cfgs:
            raise ValueError(f"one seed per joint, got {len(cfgs)} configs, {len(seeds)} seeds")
        self.plants = [Plant(cfg, seed) for cfg, seed in zip(cfgs, seeds, strict=True)]
        self.size = len(self.plants)

    def set_load_torque(self, torques_Nm: Sequence[float] | np.ndarray) -> None:
        """:meth:`Plant.set_load_torque` of each joint."""
        for plant, tau in zip(self.plants, np.asarray(torques_Nm).tolist(), strict=True):
            plant.set_load_torque(tau)

    def prepare(self, dt: float) -> None:
        """:meth:`Plant.prepare` of each joint."""
        for plant in self.plants:
            plant.prepare(dt)

    def advance(self, volts: Sequence[float] | np.ndarray, dt: float) -> None:
        """:meth:`Plant.advance` of each joint."""
        for plant, v in zip(self.plants, np.asarray(volts).tolist(), strict=True):
            plant.advance(v, dt)

    def sample(self) -> list[tuple[int, int, int, int]]:
        """:meth:`Plant.sample` of each joint."""
        return [plant.sample() for plant in self.plants]

    def step(self, volts: Sequence[float] | np.ndarray, dt: float) -> list[tuple[int, ...]]:
        """:meth:`advance` then :meth:`sample`."""
        self.advance(volts, dt)
        return self.sample()  # type: ignore[return-value]

    @property
    def time(self) -> float:
        """Simulated time in s (joint 0's; all joints step together)."""
        return self.plants[0].time

    @property
    def state(self) -> np.ndarray:
        """The (N, 5) state in :attr:`PlantBank.state`'s order."""
        return np.array([[p._d, p._wm, p._wl, p._i, p._ql] for p in self.plants])


def plant_bank(
    cfgs: Sequence[PlantConfig], seeds: Sequence[int], vector_from: int = VECTOR_CROSSOVER
) -> PlantBank | ScalarPlants:
    """N joints behind one interface: a :class:`PlantBank` from ``vector_from`` joints
    (the measured crossover, :data:`VECTOR_CROSSOVER`), else :class:`ScalarPlants`.
    Joints the bank cannot step (prescribed link, load profile) always get the scalar path."""
    if (
        len(cfgs) >= vector_from
        and all(not c.link.active and c.load.kind == "none" for c in cfgs)
        and len({c.substeps for c in cfgs}) == 1
    ):
        return PlantBank(cfgs, seeds)
    return ScalarPlants(cfgs, seeds)
