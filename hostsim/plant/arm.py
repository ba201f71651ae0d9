"""An arm's plant: N emulated harmonic-drive actuators on the multibody links, :class:`ArmPlant`.

Each actuated joint of a URDF (:class:`~hdhil.hostsim.plant.multibody.LinkDynamics`)
carries :class:`~hdhil.hostsim.plant.model.Plant`'s actuator: amplifier with current lag
and limit, reflected motor inertia with viscous and Coulomb friction, the flexspline's
spring and damper ([Vertechy] Eq. 1, first line), ripple, misalignment, strain-gauge
bridge, encoder, tacho and converters ([Taghirad97] §2).  The second line of Eq. 1
becomes the links' ``M(q) qdd + b(q, qd) = T + tau_f + J(q)^T w``, ``T`` the N flexspline
torques, ``tau_f`` the output bearings' friction, ``w`` external wrenches.

Coupling.  The flexspline is stiff: ``k`` 6.3e3-1e4 Nm/rad against link inertias down to
the 4e-3 kg m² of a Panda wrist (the smallest eigenvalue of ``M``) puts the joint mode
near ``sqrt(k / lambda_min(M))`` = 1.2e3-1.6e3 rad/s and the damper's rate ``c /
lambda_min(M)`` past 2e3 /s, so an explicit step of 1 ms (``omega h < 2``, ``c h /
lambda_min < 2``) fails.  Each step of ``dt`` is split into ``plant.substeps`` sub-steps
``h``.  ``M(q)`` is evaluated once per step and held over it; gravity, Coriolis and
external wrenches (``LinkDynamics.free_torques``) once per sub-step at its predicted
midpoint ``q + h qd / 2`` (which keeps an unforced arm's energy bounded where the value
at the start lets it drift), the Coulomb frictions at its start, as :class:`Plant`
does; the linear rest (spring, damper, viscous friction, both inertias) is integrated
by the trapezoidal rule, solved exactly: the motor sides eliminated, one N x N
symmetric positive-definite system per step gives the sub-step as one affine map
(:class:`_StepConstants`).  The current follows its first-order lag exactly.
Stability condition: the trapezoidal rule is A-stable, so with ``M`` held the linear
part (passive: every eigenvalue has ``Re <= 0``) is stable for any ``k``, ``c`` and
``h``; what stays explicit has :mod:`.stability`'s bound for held Coulomb friction,
``h C_m / (eps J_m) <= 2`` and ``h C_l / (eps lambda_min(M)) <= 2``
(:meth:`ArmPlant.step_problems`), and ``h`` far below the links' own time scales
(gravity and Coriolis: tens of rad/s).  The rule warps the joint mode's frequency by
``(omega h)^2 / 12`` (0.3 % at 783 rad/s and 0.25 ms) and does not damp it.

One step of the arm serves N drives (:meth:`ArmPlant.joint`): ``docs/multibody.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from scipy.linalg.lapack import dposv

from hdhil.hostsim.plant.config import LinkMotionConfig, PlantConfig
from hdhil.hostsim.plant.model import ConfiguredConverters, Plant
from hdhil.hostsim.plant.multibody import LinkDynamics, Wrench
from hdhil.hostsim.plant.stability import MAX_HELD_SLOPE_STEP, NonFiniteStateError
from hdhil.hostsim.plant.truth import Truth

__all__ = ["ArmJoint", "ArmPlant"]

#: Two clocks that differ by less than this (s) are the same instant.
_CLOCK_TOLERANCE_S = 1e-9


class _JointSensors(Plant):
    """One joint's sensors: :class:`Plant`'s read-out (ripple, bridge, hysteresis, noise
    stream, converters, faults) and truth of the motor side, on a state set by the arm."""

    def hold(self, d: float, wm: float, wl: float, i: float, ql: float, i_cmd: float) -> None:
        self._d, self._wm, self._wl, self._i, self._ql = d, wm, wl, i, ql
        self._i_cmd = i_cmd
        self._update_sensor()


class ArmPlant:
    """N harmonic-drive joints on a robot's links (module docstring), in URDF order.

    ``joints``: one :class:`PlantConfig` per actuated joint of ``link``; everything of
    :class:`Plant` applies except the link side: ``drivetrain.J_load`` is not used
    (the links' inertia is the URDF's ``M(q)``), gravity comes from the URDF (the
    ``gravity`` table must be off) and the link is free (no ``link`` motion).
    ``drivetrain.b_load`` and ``coulomb_load`` are the output bearings' friction on
    each joint; a ``load`` profile and :meth:`set_load_torque` add a torque at the
    joint's output.  ``seeds``: one noise stream per joint, as :class:`Plant`'s.
    ``q0``: the link angles at time 0 (rad), at rest, no twist; by default zeros, or
    where the person's motion is at time 0 and moving with it when a person wears the
    arm (``link`` of kind hold, sine or person with an impedance: :class:`_Person`).
    :meth:`rest_under_load` puts a free arm at rest under its weight instead, and
    :meth:`apply_brakes` holds it there until :meth:`release_brakes`.
    """

    def __init__(
        self,
        link: LinkDynamics,
        joints: Sequence[PlantConfig],
        seeds: Sequence[int],
        q0: Sequence[float] | None = None,
    ) -> None:
        n = link.size
        if len(joints) != n or len(seeds) != n:
            raise ValueError(
                f"the arm has {n} actuated joints ({', '.join(link.names)}); got "
                f"{len(joints)} plant configurations and {len(seeds)} seeds"
            )
        for name, cfg in zip(link.names, joints, strict=True):
            if cfg.link.active and not cfg.link.worn:
                raise ValueError(
                    f"joint {name}: an arm's link moves with the arm; a person moves it "
                    "through an impedance (plant.link stiffness_Nm_per_rad or "
                    "damping_Nms_per_rad > 0)"
                )
            if cfg.link.bearing_coulomb_Nm:
                raise ValueError(
                    f"joint {name}: an arm's output bearings are plant.drivetrain b_load and "
                    "coulomb_load, not plant.link.bearing_coulomb_Nm"
                )
            if cfg.gravity.mgl_Nm != 0.0:
                raise ValueError(f"joint {name}: gravity comes from the URDF; plant.gravity is off")
        if len({cfg.substeps for cfg in joints}) != 1:
            raise ValueError("the joints of an arm share plant.substeps")
        self.link = link
        self.cfgs = tuple(joints)
        self.names = link.names
        self.size = n
        self._substeps = joints[0].substeps
        self._sensors = [
            _JointSensors(replace(cfg, link=LinkMotionConfig()), seed)
            for cfg, seed in zip(joints, seeds, strict=True)
        ]

        def col(values: Sequence[float]) -> np.ndarray:
            return np.array(values, dtype=np.float64)

        dts = [c.drivetrain for c in joints]
        amps = [c.amplifier for c in joints]
        self._gain = col([a.gain_A_per_V for a in amps])
        self._ilim = col([a.current_limit_A for a in amps])
        self._lag = col([a.current_lag_s for a in amps])
        # N Kt: motor torque at the output per A
        self._kt = col(
            [d.gear_ratio * a.torque_constant_Nm_per_A for d, a in zip(dts, amps, strict=True)]
        )
        self._jm = col([d.J_motor for d in dts])
        self._bm = col([d.b_motor for d in dts])
        self._cm = col([d.coulomb_motor for d in dts])
        self._bl = col([d.b_load for d in dts])
        self._cl = col([d.coulomb_load for d in dts])
        self._k = col([d.k_flex for d in dts])
        self._c = col([d.c_flex for d in dts])
        self._inv_eps = col([1.0 / d.friction_smoothing for d in dts])
        self._coulomb = bool(np.any(self._cm) or np.any(self._cl))
        self._inv_eps2 = np.concatenate([self._inv_eps, self._inv_eps])
        self._coulomb2 = np.concatenate([self._cm, self._cl])
        self._profiles = [None if c.load.kind == "none" else c.load.value for c in joints]
        self._tau_load = np.zeros(n)
        self._wrenches: tuple[Wrench, ...] | None = None
        self._person = _Person([c.link for c in joints]) if any(
            c.link.active for c in joints) else None  # fmt: skip
        # the links' viscous terms to ground: the bearings' and the person's damping (the
        # latter's pull, D dtheta_p, is a held torque: _Person.pull)
        self._viscous = self._bl if self._person is None else self._bl + self._person.damping
        self._consts: dict[float, _StepConstants] = {}
        # state: twist (output-referred), motor velocity (output-referred), link
        # velocity, current, link angle; the current command; the amplifier input
        self._d, self._wm, self._wl, self._i, self._q = (np.zeros(n) for _ in range(5))
        if q0 is not None:
            self._q = np.array(q0, dtype=np.float64).reshape(n)
        elif self._person is not None:  # where the person holds it, moving with them
            self._q, self._wl = self._person.intent(0.0)
            self._wm = self._wl.copy()
        self._i_cmd = np.zeros(n)
        self._volts = np.zeros(n)
        self._t = 0.0
        self._t_carry = 0.0
        #: The motors' holding brakes are applied: :meth:`advance` moves the clock and
        #: the currents, not the mechanics (:meth:`release_brakes`).
        self.braked = False
        self._link_truth: tuple[np.ndarray, ...] | None = None
        #: Where :meth:`ArmJoint.advance` takes the N amplifier inputs when the arm has
        #: not been advanced for the cycle yet (``docs/multibody.md``); None: the rig
        #: calls :meth:`advance` itself before the drives' SYNC.
        self.input_source: Callable[[], Sequence[float]] | None = None
        self._views = tuple(ArmJoint(self, k) for k in range(n))
        self._sync_sensors()

    # ------------------------------------------------------------------ set-up
    def set_state(
        self,
        q: Sequence[float],
        *,
        qd: Sequence[float] | None = None,
        twist: Sequence[float] | None = None,
        current: Sequence[float] | None = None,
    ) -> None:
        """Put the arm at link angles ``q`` (rad) and velocities ``qd`` (rad/s, zero by
        default), the motors moving with the links; ``twist`` the flexspline twists (rad,
        output-referred) and ``current`` the motor currents (A), zero by default.  The
        clock does not move."""
        n = self.size

        def arr(x: Sequence[float] | None) -> np.ndarray:
            return np.zeros(n) if x is None else np.array(x, dtype=np.float64).reshape(n)

        self._q, self._wl, self._d, self._i = arr(q), arr(qd), arr(twist), arr(current)
        self._wm = self._wl.copy()
        self._i_cmd = self._i.copy()
        self._sync_sensors()

    def rest_under_load(self) -> None:
        """Put the arm at rest at its present angles as it rests under its own weight:
        each flexspline twisted by the static torque its link needs, ``twist = -f / k``
        with ``f`` the link torques at rest (gravity, wrenches, load torques), so the links
        start in equilibrium instead of dropping onto untwisted flexsplines and ringing
        at the joint mode.  Motors and links still, the currents unchanged; the clock
        does not move."""
        n = self.size
        f = self.link.free_torques(self._q, np.zeros(n), self._wrenches)
        f += self._tau_load
        f += [0.0 if p is None else p(self._t) for p in self._profiles]
        self._d = -f / self._k
        self._wm = np.zeros(n)
        self._wl = np.zeros(n)
        self._sync_sensors()

    def apply_brakes(self) -> None:
        """Hold every motor with its brake (a robot's holding brakes while its drives
        are not yet in operation): :meth:`advance` keeps the arm where it is, the
        currents following their commands, until :meth:`release_brakes`."""
        self.braked = True
        self._wm = np.zeros(self.size)
        self._wl = np.zeros(self.size)
        self._sync_sensors()

    def release_brakes(self) -> None:
        """Release the brakes: from the next :meth:`advance` on the arm moves."""
        self.braked = False

    @property
    def worn(self) -> bool:
        """Whether a person wears the arm (a joint's ``link`` is a person's motion): it
        starts where they hold it, moving with them, rather than at rest."""
        return self._person is not None

    def set_load_torque(self, joint: int, torque_Nm: float) -> None:
        """A torque on joint ``joint``'s output (Nm, positive forward), held until
        changed: :meth:`Plant.set_load_torque` for one joint of the arm."""
        if not math.isfinite(torque_Nm):
            raise ValueError(f"load torque must be finite, got {torque_Nm!r}")
        self._tau_load[joint] = float(torque_Nm)
        self._link_truth = None

    def set_wrenches(self, wrenches: Wrench | Sequence[Wrench] | None) -> None:
        """External wrenches on links (:class:`Wrench`: a person at the handle, a payload),
        held until changed; None or ``()`` removes them."""
        if isinstance(wrenches, Wrench):
            wrenches = (wrenches,)
        self._wrenches = tuple(wrenches) if wrenches else None
        if self._wrenches:
            self.link.external_torques(self._q, self._wrenches)  # an unknown link: now
        self._link_truth = None

    def _constants(self, dt: float) -> _StepConstants:
        """What the sub-steps of a step of ``dt`` share whatever the pose
        (:class:`_StepConstants`)."""
        c = self._consts.get(dt)
        if c is None:
            c = _StepConstants(self, dt)
            if len(self._consts) >= 16:
                self._consts.clear()
            self._consts[dt] = c
        return c

    def step_problems(self, dt: float) -> list[str]:
        """Why the arm cannot be stepped by ``dt`` at its present pose (the held Coulomb
        frictions' bound, module docstring); empty when it can."""
        h = dt / self._substeps
        lam = float(np.linalg.eigvalsh(self.link.mass_matrix(self._q))[0])
        out = []
        eps = 1.0 / self._inv_eps
        for k, name in enumerate(self.names):
            for side, coulomb, inertia in (("motor", self._cm[k], self._jm[k]),
                                           ("load", self._cl[k], lam)):  # fmt: skip
                if h * coulomb / (eps[k] * inertia) > MAX_HELD_SLOPE_STEP:
                    out.append(
                        f"joint {name}: coulomb_{side} {coulomb:.3g} Nm on {inertia:.3g} kg m² "
                        f"chatters at a sub-step of {h:.3g} s: friction_smoothing must be >= "
                        f"{h * coulomb / (MAX_HELD_SLOPE_STEP * inertia):.3g}"
                    )
        return out

    def prepare(self, dt: float) -> None:
        """Check the step (:meth:`step_problems`; ``ValueError`` with the first) and
        compute its coefficients now rather than in the first cycle."""
        if not dt > 0.0:
            raise ValueError(f"prepare needs dt > 0, got {dt!r}")
        problems = self.step_problems(dt)
        if problems:
            raise ValueError(problems[0])
        self._constants(dt)

    # ------------------------------------------------------------------ dynamics
    def advance(self, volts: Sequence[float] | np.ndarray, dt: float) -> None:
        """Integrate every joint from :attr:`time` to ``time + dt`` with amplifier input
        ``volts[k]`` held on joint ``k`` (URDF order).  Raises
        :class:`NonFiniteStateError` (the state kept) when the state does not stay finite."""
        u = np.array(volts, dtype=np.float64).reshape(-1)
        if not dt > 0.0 or u.shape != (self.size,) or np.isnan(u).any():
            raise ValueError(
                f"advance needs dt > 0 and {self.size} numbers of volts, got {volts!r}"
            )
        c = self._constants(dt)
        n, a, h = self.size, c.a, c.h
        link, wrenches = self.link, self._wrenches
        i_cmd = np.clip(self._gain * u, -self._ilim, self._ilim)
        if self.braked:  # the brakes hold the motors: nothing moves, the currents follow
            self._i = i_cmd + (self._i - i_cmd) * c.current_decay
            self._finish_step(i_cmd, u, dt)
            return
        # the sub-step map with M(q) held: x+ = phi @ [x, tau_m, f], x = [d, w_m, w_l, q]
        mass = link.mass_matrix(self._q)
        rhs = c.rhs0.copy()
        rhs[:, 2 * n : 3 * n] = 2.0 * mass
        _, sig_l, info = dposv(mass + c.diag, rhs)  # symmetric positive definite
        if info:
            sig_l = np.linalg.solve(mass + c.diag, rhs)
        phi = c.phi0 + c.rows * sig_l[c.tiled]
        # the motor torque of each sub-step: the exact mean of the lagging current
        i_gap = self._i - i_cmd
        torques = self._kt * (i_cmd + i_gap * c.current_means)
        z = np.concatenate([self._d, self._wm, self._wl, self._q, self._kt, self._kt])
        wl, q = z[2 * n : 3 * n], z[3 * n : 4 * n]
        loads = self._tau_load if self._tau_load.any() else None
        person = self._person
        if person is not None:  # the intent at the step's midpoint, the weight at its start
            pull = person.pull(self._t + 0.5 * dt)
            if person.weight.any():
                pull = pull + person.weight * link.gravity(self._q)
            loads = pull if loads is None else loads + pull
        profiles = self._profiles if any(p is not None for p in self._profiles) else None
        coulomb, slopes, friction = self._coulomb, self._inv_eps2, self._coulomb2
        velocities, held = z[n : 3 * n], z[4 * n :]  # (w_m, w_l) and (tau_m, f) as views
        t0 = self._t
        for j in range(self._substeps):
            # gravity, Coriolis and wrenches at the sub-step's predicted midpoint
            f = link.free_torques(q + a * wl, wl, wrenches)
            if loads is not None:
                f += loads
            if person is not None:  # the person's spring at the predicted midpoint
                f -= person.stiffness * (q + a * wl)
            if profiles is not None:
                f += [0.0 if p is None else p(t0 + j * h) for p in profiles]
            z[4 * n : 5 * n] = torques[j]
            z[5 * n :] = f
            if coulomb:  # both Coulomb frictions at once, from the sub-step's start
                held -= friction * np.tanh(velocities * slopes)
            z[: 4 * n] = phi @ z
        x = z[: 4 * n].copy()
        i = i_cmd + i_gap * c.current_decay
        if not (np.isfinite(x).all() and np.isfinite(i).all()):
            names = ("twist", "motor velocity", "link velocity", "link angle", "current")
            parts = (*(x[r * n : (r + 1) * n] for r in range(4)), i)
            bad = tuple(nm for nm, v in zip(names, parts, strict=True) if not np.isfinite(v).all())
            raise NonFiniteStateError(self._t + dt, bad)
        self._d, self._wm, self._wl, self._q = x[:n], x[n : 2 * n], x[2 * n : 3 * n], x[3 * n :]
        self._i = i
        self._finish_step(i_cmd, u, dt)

    def _finish_step(self, i_cmd: np.ndarray, u: np.ndarray, dt: float) -> None:
        """The end of every step: the held command and input, the clock, the sensors."""
        self._i_cmd = i_cmd
        self._volts = u
        y = dt - self._t_carry
        t = self._t + y
        self._t_carry = (t - self._t) - y
        self._t = t
        self._sync_sensors()

    def _sync_sensors(self) -> None:
        """Hand each joint's sensors its new state (ripple, bridge, hysteresis updated)."""
        self._link_truth = None
        columns = (self._d, self._wm, self._wl, self._i, self._q, self._i_cmd)
        rows = zip(*(x.tolist() for x in columns), strict=True)
        for sensors, (d, wm, wl, i, q, ic) in zip(self._sensors, rows, strict=True):
            sensors.hold(d, wm, wl, i, q, ic)
            sensors._t = self._t

    # ------------------------------------------------------------------ read-out
    def sample(self, joint: int) -> tuple[int, int, int, int]:
        """Joint ``joint``'s sensors now: :meth:`Plant.sample`'s (ADC_torque, ADC_tacho,
        ADC_current, ENC_count), from its own noise stream (``seeds[joint]``)."""
        return self._sensors[joint].sample()

    def _link_side(self) -> tuple[np.ndarray, ...]:
        """Per joint, at the present state: gravity on the link ([Vertechy]'s ``tau_g``),
        the environment's torque ``tau_l``, the bearings' friction, the link
        acceleration and ``M_kk qdd_k - T_k`` (``tau_ext``); once per step."""
        lt = self._link_truth
        if lt is None:
            link, q, wl = self.link, self._q, self._wl
            transmitted = self._k * self._d + self._c * (self._wm - wl)
            friction = -self._bl * wl - self._cl * np.tanh(wl * self._inv_eps)
            tau_l = self._tau_load.copy()
            tau_l += [0.0 if p is None else p(self._t) for p in self._profiles]
            if self._wrenches:
                tau_l += link.external_torques(q, self._wrenches)
            holding = link.gravity(q)
            if self._person is not None:
                tau_l += self._person.torque(self._t, q, wl, holding)
            qdd = link.forward_dynamics(q, wl, transmitted + friction + tau_l, self._wrenches)
            tau_ext = np.diag(link.mass_matrix(q)) * qdd - transmitted
            lt = self._link_truth = (-holding, tau_l, friction, qdd, tau_ext)
        return lt

    def truth(self, joint: int) -> Truth:
        """Joint ``joint``'s ground truth now (:class:`Truth`, every field).

        The motor side and the sensor as :meth:`Plant.truth`; the link side from the
        arm: ``tau_g`` gravity's torque on the links at the joint ([Vertechy]'s sign,
        ``-LinkDynamics.gravity``), ``tau_l`` the environment's (external wrenches
        through ``J^T``, and the load torque), ``load_friction`` the output bearings',
        the link acceleration of the arm's dynamics, and ``tau_ext = M_kk(q) qdd_k -
        T_transmitted``: all torque on the joint's link except its own flexspline's,
        its own inertia ``M_kk`` taken as the link's, so the other links' inertial,
        Coriolis and centrifugal pull counts in with gravity, bearings and environment.
        """
        tau_g, tau_l, friction, qdd, tau_ext = self._link_side()
        return (
            self._sensors[joint]
            .truth()
            ._replace(
                tau_ext_Nm=float(tau_ext[joint]),
                tau_l_Nm=float(tau_l[joint]),
                tau_g_Nm=float(tau_g[joint]),
                load_friction_Nm=float(friction[joint]),
                link_acceleration_radps2=float(qdd[joint]),
            )
        )

    def joint(self, k: int) -> ArmJoint:
        """Joint ``k`` as the plant of one drive (:class:`ArmJoint`)."""
        return self._views[k]

    @property
    def time(self) -> float:
        """Simulated time in s (the Kahan-compensated sum of the steps)."""
        return self._t

    @property
    def q(self) -> np.ndarray:
        """The link angles (rad), a copy."""
        return self._q.copy()

    @property
    def qd(self) -> np.ndarray:
        """The link velocities (rad/s), a copy."""
        return self._wl.copy()

    @property
    def state(self) -> np.ndarray:
        """A copy of the (N, 5) state: twist, reduced motor velocity, link velocity,
        current, link angle (:attr:`PlantBank.state`'s columns)."""
        return np.stack([self._d, self._wm, self._wl, self._i, self._q], axis=1)


class _Person:
    """The person who wears the arm (:class:`LinkMotionConfig`'s docstring): per joint,
    the intended motion ``theta_p(t)``, a stiffness and a damping about it, and whether
    they carry the links' weight.  Joints of kind ``none`` have zero impedance and
    intent."""

    def __init__(self, motions: Sequence[LinkMotionConfig]) -> None:
        self.stiffness = np.array([m.stiffness_Nm_per_rad for m in motions])
        self.damping = np.array([m.damping_Nms_per_rad for m in motions])
        self.weight = np.array([1.0 if m.holds_weight else 0.0 for m in motions])
        # every joint's sinusoids (LinkMotionConfig.components) as rows, zero-padded
        comps = [m.components() if m.active else () for m in motions]
        width = max(1, *(len(c) for c in comps))
        self._amp, self._omega, self._phase = (np.zeros((len(comps), width)) for _ in range(3))
        for k, c in enumerate(comps):
            for i, (a, w, p) in enumerate(c):
                self._amp[k, i], self._omega[k, i], self._phase[k, i] = a, w, p
        self._rate = self._amp * self._omega
        self._offset = np.array([math.radians(m.offset_deg) if m.active else 0.0 for m in motions])

    def intent(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The intended link angles and velocities (rad, rad/s) at time ``t``
        (:meth:`LinkMotionConfig.angle` and ``velocity`` of every joint at once)."""
        x = self._omega * t + self._phase
        return self._offset + (self._amp * np.sin(x)).sum(axis=1), (self._rate * np.cos(x)).sum(
            axis=1
        )

    def pull(self, t: float) -> np.ndarray:
        """The part of the impedance that does not depend on the arm's state:
        ``K theta_p(t) + D dtheta_p(t)``, Nm."""
        q, qd = self.intent(t)
        return self.stiffness * q + self.damping * qd

    def torque(self, t: float, q: np.ndarray, qd: np.ndarray, holding: np.ndarray) -> np.ndarray:
        """The person's torque on the links at time ``t`` and state ``(q, qd)``, Nm;
        ``holding`` the torques that hold the links still at ``q``
        (:meth:`LinkDynamics.gravity`)."""
        return self.pull(t) - self.stiffness * q - self.damping * qd + self.weight * holding


class _StepConstants:
    """The parts of :class:`ArmPlant`'s sub-step that depend on the step, not the pose.

    Per joint, with ``a = h / 2`` and ``g = a (k a + c)``, the trapezoidal rule over a
    sub-step ``h`` eliminates the motor side: ``sigma_m = alpha + beta sigma_l`` with
    ``alpha = (2 J_m w_m - 2 a k d + h tau_m) / D``, ``D = J_m + a (k a + c + b_m)``,
    ``beta = g / D``, and ``(M + diag(a b_l + g (1 - beta))) sigma_l = 2 M w_l + (h k -
    2 a g k / D) d + (2 g J_m / D) w_m + (g h / D) tau_m + h f``, where ``sigma = w +
    w+`` (a velocity before plus after the sub-step), ``tau_m`` the motor's torque
    (current and Coulomb friction) and ``f`` the held link torques; then ``d+ = d + a
    (sigma_m - sigma_l)``, ``w+ = sigma - w``, ``q+ = q + a sigma_l``.  All linear in
    ``z = [d, w_m, w_l, q, tau_m, f]``: ``x+ = phi z`` with ``phi = phi0 + rows *
    [sigma_l; sigma_l; sigma_l; sigma_l]``, ``sigma_l = (M + diag)^-1 rhs``, where only
    ``rhs``'s ``w_l`` columns (``2 M``) depend on the pose.
    ``b_l`` is every viscous term of the link to ground: the bearings' ``b_load`` and a
    wearing person's damping (:class:`_Person`).
    """

    def __init__(self, arm: ArmPlant, dt: float) -> None:
        n, s = arm.size, arm._substeps
        self.h = h = dt / s
        self.a = a = 0.5 * h
        k, jm = arm._k, arm._jm
        g = a * (k * a + arm._c)
        dm = jm + a * (k * a + arm._c + arm._bm)
        beta = g / dm
        self.diag = np.diag(a * arm._viscous + g * (1.0 - beta))
        eye, zeros = np.eye(n), np.zeros((n, n))
        # columns: d, w_m, w_l, q, tau_m, f (w_l's 2 M is set per step)
        self.rhs0 = np.hstack(
            [eye * (h * k - 2.0 * a * g * k / dm), eye * (2.0 * g * jm / dm), zeros, zeros,
             eye * (g * h / dm), eye * h]
        )  # fmt: skip
        alpha = np.hstack(
            [eye * (-2.0 * a * k / dm), eye * (2.0 * jm / dm), zeros, zeros, eye * (h / dm),
             zeros]
        )  # fmt: skip
        own = np.eye(4 * n, 6 * n)  # x's own columns, by block of rows
        block = [own[r * n : (r + 1) * n] for r in range(4)]
        self.phi0 = np.vstack([block[0] + a * alpha, alpha - block[1], -block[2], block[3]])
        self.rows = np.concatenate([a * (beta - 1.0), beta, np.ones(n), np.full(n, a)])[:, None]
        self.tiled = np.tile(np.arange(n), 4)  # sigma_l's rows for the four blocks of x
        # the current, i(t) = i_cmd + (i0 - i_cmd) exp(-t / lag): its mean over sub-step j
        # and its value after the step; an ideal amplifier (lag 0) has i = i_cmd
        lag = arm._lag
        lagging = lag > 0.0
        safe = np.where(lagging, lag, 1.0)
        decay = np.where(lagging, np.exp(-h / safe), 0.0)
        mean = np.where(lagging, safe / h * (1.0 - decay), 0.0)
        self.current_means = mean[None, :] * decay[None, :] ** np.arange(s)[:, None]
        self.current_decay = decay**s


class ArmJoint(ConfiguredConverters):
    """One joint of an :class:`ArmPlant` behind
    :class:`~hdhil.hostsim.plant_model.PlantModel`, the plant of one ``DriveNode``.

    The arm moves once per cycle for all joints, so :meth:`advance` does not
    integrate: it finds the arm already advanced to this joint's clock plus ``dt``
    (the rig called :meth:`ArmPlant.advance` before the SYNC) or, if not, advances it
    with :attr:`ArmPlant.input_source` (the first drive's SYNC moves all joints); then
    it checks that the arm held ``volts`` on this joint.  Either mismatch is a
    ``ValueError``: a wiring error, not physics.
    """

    def __init__(self, arm: ArmPlant, k: int) -> None:
        self.arm = arm
        self.index = k
        self.name = arm.names[k]
        self.cfg = arm.cfgs[k]
        self._t = 0.0

    @property
    def time(self) -> float:
        """The joint's clock: the arm's at the joint's latest :meth:`advance`."""
        return self._t

    def advance(self, volts: float, dt: float) -> None:
        """This joint's part of one cycle of ``dt`` with ``volts`` on its amplifier."""
        arm = self.arm
        target = self._t + dt
        if arm.time < target - _CLOCK_TOLERANCE_S and arm.input_source is not None:
            arm.advance(arm.input_source(), dt)
        if abs(arm.time - target) > _CLOCK_TOLERANCE_S:
            raise ValueError(
                f"joint {self.name}: its drive steps to t = {target:.9g} s but the arm is at "
                f"{arm.time:.9g} s (advance the arm once per cycle before the drives' SYNC, "
                "or give it an input_source)"
            )
        held = float(arm._volts[self.index])
        if held != volts:
            raise ValueError(
                f"joint {self.name}: its drive held {volts!r} V over the step, the arm {held!r} V"
            )
        self._t = arm.time

    def sample(self) -> tuple[int, int, int, int]:
        """:meth:`ArmPlant.sample` of this joint."""
        return self.arm.sample(self.index)

    def truth(self) -> Truth:
        """:meth:`ArmPlant.truth` of this joint."""
        return self.arm.truth(self.index)
