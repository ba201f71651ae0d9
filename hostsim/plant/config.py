"""Configuration of the drive emulator's physics: one frozen dataclass per part.

Amplifier, flexible joint, gear ripple, sensors, load-torque profile, prescribed link
motion and gravity, gathered in :class:`PlantConfig`, the ``[plant]`` table of a
scenario (built with :func:`hdhil.core.dataconf.from_dict`). Each class checks its own
values, so a bad scenario fails when it is loaded, naming the field, not in the middle of
a run. Each class's docstring gives its model, its defaults and their sources.

Units: SI, angles in rad (degrees where a name says ``_deg``), torques in Nm; the
joint's inertias, stiffness, damping and friction are reduced to the output shaft
([Vertechy] Eq. 1).
"""

from __future__ import annotations

import bisect
import itertools
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from hdhil.core.converter import Converter
from hdhil.core.dataconf import check_fields
from hdhil.hostsim.bridge import BridgeConfig

__all__ = [
    "PERSON_BAND_HZ",
    "PERSON_COMPONENTS",
    "TWO_PI",
    "AmplifierConfig",
    "BridgeConfig",
    "DriveTrainConfig",
    "GravityConfig",
    "LinkMotionConfig",
    "LoadTorqueConfig",
    "PlantConfig",
    "RippleConfig",
    "SensorConfig",
]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class AmplifierConfig:
    """Servo amplifier in current mode ([Taghirad97] listing A.1: "floatV for MAX-100 servo").

    ``i_cmd = clip(gain_A_per_V * V_dac, -current_limit_A, +current_limit_A)``; the
    current follows ``i_cmd`` through a first-order lag of time constant
    ``current_lag_s`` (the closed current loop; 0 = ideal, i = i_cmd at once).  The
    motor torque at the motor shaft is ``torque_constant_Nm_per_A * i``.

    The papers give no amplifier or motor data; all defaults are representative of a
    brushed servo motor on an RHS-20-class harmonic drive, not from the papers
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
    """Two-mass flexible joint, everything reduced to the OUTPUT shaft ([Vertechy] Eq. 1).

    ``J_m ddq_m = tau_m + tau_d + k (q_l - q_m) + c (dq_l - dq_m)``
    ``J_l ddq_l = tau_l + tau_g - k (q_l - q_m) - c (dq_l - dq_m)``

    with ``q_m = theta_motor / gear_ratio``, ``tau_m = gear_ratio * Kt * i``, the motor
    disturbance ``tau_d = -b_motor dq_m - coulomb_motor tanh(dq_m / friction_smoothing)``
    (motor bearings + wave generator, [Vertechy]: "friction and ripple effects of both
    motor and harmonic drive", here friction only, see :class:`RippleConfig`) and the
    load-side friction ``-b_load dq_l - coulomb_load tanh(dq_l / friction_smoothing)``
    added to the external ``tau_l + tau_g`` (:meth:`Plant.set_load_torque`).

    Defaults and their sources:

    * ``gear_ratio`` 100: [Taghirad97] §2 (RHS series, 100:1) and listing (``Gain = 100``).
    * ``J_motor`` 0.3 kg m²: a 3e-5 kg m² rotor (+ wave generator) times 100²;
      representative of an RHS-20-class harmonic drive, not from the papers.
    * ``b_motor`` 1.7 Nm s/rad and ``coulomb_motor`` 1.2 Nm (output-referred, i.e.
      0.017 Nm s/rad and 0.012 Nm at the motor): representative of an RHS-20-class
      harmonic drive, not from the papers; tuned together with ``J_motor`` so that the
      free-motion step of [Taghirad97] Fig. 8 settles to ~156 rad/s with a ~0.19 s
      mechanical time constant (flat from 0.8 s to 1.1 s).
    * ``friction_smoothing`` 0.01 rad/s at the output (1 rad/s at the motor): the
      width of the tanh Coulomb model; a numerical choice, not from the papers.
    * ``k_flex`` 1.0e4 Nm/rad and ``c_flex`` 5 Nm s/rad: flexspline torsional stiffness
      and structural damping, representative of an RHS-20-class harmonic drive, not
      from the papers ([Vertechy]'s 6.3 kNm/rad and 11.8 Nm s/rad belong to a different
      joint that includes a sensor hub).  With the default inertias the locked-free
      natural frequency ``sqrt(k (1/J_m + 1/J_l))`` is 783 rad/s (125 Hz).
    * ``J_load`` 1.725e-2 kg m²: [Taghirad97] listing A.1 (``J_load``).
    * ``b_load`` 0.01 Nm s/rad and ``coulomb_load`` 0.05 Nm: output bearings of the
      free-motion test stand; representative, not from the papers.

    The [Vertechy] joint (§I: "motor shaft inertia reduced to the joint output shaft
    J_m = 2.5 Kgm²", "overall joint torsional stiffness ... k = 6.3 kNm/rad", rigid
    link J_l = 0.7 Kgm²; §II: c = 11.8 Nms/rad) is ``J_motor = 2.5``, ``J_load =
    0.7``, ``k_flex = 6300``, ``c_flex = 11.8``, ``gear_ratio = 100`` (§I).  Its motor
    disturbance friction (§VI, the "experimentally determined motor friction torque
    model") is printed garbled, ``tau_d = [-13.7 sign(w)(1 + tanh(|w|/2) - 4)]/2``;
    read literally it is 20.6 Nm at rest falling to 13.7 Nm, *aiding* the motion.
    What it must be, from the seed's own numbers (``max(tau_s^D + tau_d) ≈ 33.7 Nm``
    with ``tau_s^D`` ≤ 20 Nm), is a friction opposing the motion whose magnitude tops
    out at 13.7 Nm, smooth through zero velocity, with a velocity scale of 2 rad/s
    (the ``|w|/2``).  (Moving the bracket, ``-13.7 sign(w) (1 + tanh(|w|/2 - 4)) / 2``,
    also tops out at 13.7 Nm, but as a smooth step centred at |w| = 8 rad/s that
    vanishes near rest, which no friction does: a reading for the firmware's
    compensation, ``firmware.config.FrictionModelConfig.model = "fade-in"``, not for the
    plant.)  The tanh Coulomb model here is the reading we take:
    ``tau_d = -13.7 tanh(dq_m / eps)``, i.e. ``coulomb_motor = 13.7``, ``b_motor =
    0``, with ``eps = friction_smoothing``.  The seed's w is the motor velocity
    reduced to the output (§II: all quantities reduced to the output link), so the
    literal scale is ``eps = 2`` rad/s; read at the motor shaft (a saturation at
    2 rad/s of the motor, 0.02 rad/s at the output, the usual width of a Coulomb
    friction) it is ``eps = 0.02``.  Scenarios state which one they use.  Note that
    ``friction_smoothing`` also sets the width of the load-side Coulomb term.
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
        """Undamped flexspline mode ``sqrt(k (1/J_m + 1/J_l))`` in rad/s ([Vertechy] Eq. 2)."""
        return math.sqrt(self.k_flex * (1.0 / self.J_motor + 1.0 / self.J_load))

    @property
    def natural_frequency_Hz(self) -> float:
        """``sqrt(k/J) / 2 pi`` in Hz: [Vertechy] §II "≈ 17 Hz" (17.08 Hz for AG1)."""
        return self.natural_frequency_radps / TWO_PI

    @property
    def reduced_inertia(self) -> float:
        """``J = J_m J_l / (J_m + J_l)`` in kg m² ([Vertechy], below Eq. 2)."""
        return self.J_motor * self.J_load / (self.J_motor + self.J_load)

    @property
    def damping_ratio(self) -> float:
        """Damping ratio of the joint mode of [Vertechy] Eq. 2, ``c / (2 sqrt(k J))``
        (spring/damper only; motor and load friction not included)."""
        return self.c_flex / (2.0 * math.sqrt(self.k_flex * self.reduced_inertia))


@dataclass(frozen=True)
class RippleConfig:
    """Gear-meshing ripple and misalignment torque picked up by the flexspline gauges.

    ``mesh = amp2 sin(2 theta_motor + phase2) + amp4 sin(4 theta_motor + phase4)``
    ``misalignment = (misalignment_pp / 2) sin(theta_output + misalignment_phase)``

    * 2x and 4x MOTOR angle: gear meshing in two zones ([Taghirad97] §4: "a real torque
      oscillation ... twice the motor velocity, for the gear teeth in harmonic drives
      are meshing in two zones"; Fig. 8: peaks at 312 and 624 rad/s at 156 rad/s).
      The sensor's own 2x modulation (§2 Eq. 2) is NOT here: it comes out of the
      gauge model (:class:`hostsim.bridge.StrainGaugeBridge`, ``PlantConfig.bridge``).
    * OUTPUT angle: misalignment of drive shaft and load ([Taghirad97] §5: frequency
      equals the output shaft velocity; 10 Nm p-p before re-assembly, < 2 Nm after).
      A side load that the sensor picks up ("many torque sensors exhibit the limitation
      of being sensitive to the torques applied on the direction perpendicular to their
      axis of measurement", §5): measurement path, like the meshing ripple.

    Modelling choice: both are added to the torque the gauges see (the measurement
    path) and do not drive the mechanics.  [Taghirad97] §4 says the meshing ripple is a
    real torque oscillation; leaving it out of the dynamics keeps the ground truth
    exactly separable, ``T_meas_clean = T_true + T_ripple`` (see the module
    docstring), which is what the Kalman filter is scored against.  Being locked to
    angle, both are also present (as static, position-dependent offsets) at standstill.

    Default amplitudes (0.6 Nm and 0.25 Nm, about 19 and 8 LSB of the 12-bit torque
    channel at 6.6 Nm/V) and phases are chosen to look like [Taghirad97] Fig. 8/9; the
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


LoadKind = Literal["none", "constant", "square", "sine", "steps"]


@dataclass(frozen=True)
class LoadTorqueConfig:
    """External torque on the output, ``tau_l + tau_g`` of [Vertechy] Eq. 1, as a profile.

    Positive drives the load forward (a negative torque brakes a forward-running
    load).  The plant evaluates it from its own clock at the start of every
    sub-step and holds it over the sub-step; it adds to the value held with
    :meth:`Plant.set_load_torque`.  With ``f = frequency_Hz``, ``t' = t − start_s``
    and ``p = frac(f t')``:

    - ``none``: 0 (the default; free motion).
    - ``constant``: ``bias_Nm`` from ``start_s`` on.
    - ``square``: ``bias_Nm + amplitude_Nm`` while ``p < duty``, else
      ``bias_Nm − amplitude_Nm``, from ``start_s`` on.
    - ``sine``: ``bias_Nm + amplitude_Nm sin(2 pi f t')`` from ``start_s`` on.
    - ``steps``: ``step_values_Nm[i]`` from ``step_times_s[i]`` (absolute times,
      strictly increasing) until the next step; 0 before the first.  Ignores
      ``bias_Nm``, ``amplitude_Nm``, ``frequency_Hz``, ``duty`` and ``start_s``.

    All kinds are 0 before ``start_s``.
    """

    kind: LoadKind = "none"
    bias_Nm: float = 0.0
    amplitude_Nm: float = 0.0
    frequency_Hz: float = 1.0
    duty: float = 0.5
    start_s: float = 0.0
    step_times_s: tuple[float, ...] = ()
    step_values_Nm: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("none", "constant", "square", "sine", "steps"):
            raise ValueError(
                "LoadTorqueConfig.kind must be one of none, constant, square, sine, steps, "
                f"got {self.kind!r}"
            )
        check_fields(
            self,
            {"bias_Nm": "finite", "amplitude_Nm": "finite", "frequency_Hz": ">0",
             "duty": ">=0", "start_s": ">=0"},
        )  # fmt: skip
        if self.duty > 1.0:
            raise ValueError(f"LoadTorqueConfig.duty must be within [0, 1], got {self.duty!r}")
        times, values = self.step_times_s, self.step_values_Nm
        for name, seq in (("step_times_s", times), ("step_values_Nm", values)):
            if not isinstance(seq, tuple) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in seq
            ):
                raise ValueError(f"LoadTorqueConfig.{name} must be a list of numbers, got {seq!r}")
        if self.kind == "steps":
            if not times or len(times) != len(values):
                raise ValueError(
                    "LoadTorqueConfig: kind 'steps' needs step_times_s and step_values_Nm of "
                    f"the same non-zero length, got {len(times)} and {len(values)}"
                )
            if times[0] < 0 or any(b <= a for a, b in itertools.pairwise(times)):
                raise ValueError(
                    "LoadTorqueConfig.step_times_s must be >= 0 and strictly increasing, "
                    f"got {list(times)}"
                )
        elif times or values:
            raise ValueError(
                f"LoadTorqueConfig: step_times_s / step_values_Nm are for kind 'steps', "
                f"not {self.kind!r}"
            )

    def value(self, t: float) -> float:
        """The load torque at time ``t`` (s), in Nm."""
        kind = self.kind
        if kind == "none":
            return 0.0
        if kind == "steps":
            k = bisect.bisect_right(self.step_times_s, t)
            return self.step_values_Nm[k - 1] if k else 0.0
        if t < self.start_s:
            return 0.0
        if kind == "constant":
            return self.bias_Nm
        tp = t - self.start_s
        if kind == "sine":
            return self.bias_Nm + self.amplitude_Nm * math.sin(TWO_PI * self.frequency_Hz * tp)
        cycles = self.frequency_Hz * tp
        p = cycles - math.floor(cycles)
        return self.bias_Nm + (self.amplitude_Nm if p < self.duty else -self.amplitude_Nm)


LinkMotionKind = Literal["none", "hold", "sine", "person"]

#: ``person`` link motion: how many sinusoids make up the motion.
PERSON_COMPONENTS = 5
#: ``person`` link motion: the band its frequencies are drawn from (Hz).  A person moving
#: a handle over ±60° by hand does so in slow, uneven strokes of one to several seconds;
#: the upper end also keeps the link within [Vertechy]'s "motor rotor maximum velocity
#: equal to 1000rpm" (§I), 1.05 rad/s at the output (see :meth:`LinkMotionConfig.components`).
PERSON_BAND_HZ = (0.05, 0.25)


@dataclass(frozen=True)
class LinkMotionConfig:
    """A prescribed trajectory of the output link ([Vertechy] §VI simulation conditions).

    [Vertechy] §VI: "the controller attempts to track tau_s^D while the output link is
    moved according to a given trajectory", ``theta_l = 20 sin(2 pi t)`` deg.  The
    environment has infinite impedance: with a kind other than ``none`` the load angle
    and velocity follow the prescription exactly, whatever the joint does, and the
    motor side integrates against the spring/damper ([Vertechy] Eq. 1, first line, with
    ``theta_l(t)`` an input).  With ``A = amplitude_deg``, ``f = frequency_Hz``,
    ``theta_0 = offset_deg`` (all converted to rad), at the plant's time t:

    - ``none``: the link is free (the default): it obeys Eq. 1, second line.
    - ``hold``: ``theta_l = theta_0`` (link clamped, e.g. a user gripping the handle).
    - ``sine``: ``theta_l = theta_0 + A sin(2 pi f t)`` ([Vertechy] §VI: A = 20°, f = 1 Hz).
    - ``person``: a person-like motion of the handle ([Vertechy] §VI experiment: "the end
      link is moved in the range theta_l in [-60, 60] deg by a human user who acts on the
      sensorized handle").  The seed gives no trajectory; our model is a sum of
      :data:`PERSON_COMPONENTS` sinusoids ``theta_l = theta_0 + sum_i a_i sin(2 pi f_i t
      + phi_i)`` whose frequencies are drawn uniformly from :data:`PERSON_BAND_HZ`,
      phases uniformly, amplitudes ``∝ 1 / f_i`` (equal velocity per component, a
      smooth, irregular stroke), from ``numpy.random.default_rng(motion_seed)``: the
      same ``motion_seed`` gives the same motion on any machine.  The amplitudes are
      scaled so that the largest ``|theta_l - theta_0|`` over the first
      ``horizon_s`` seconds is ``A`` (60° for the seed's range) unless that would make
      the link faster than ``max_velocity_radps`` ([Vertechy] §I: 1000 rpm at the motor,
      1.047 rad/s at the output through the 100:1 reduction), in which case the
      velocity bound sets the scale.  Smooth to every derivative, so the environment
      torque it takes (the handle torque) is smooth too.

    The torque it takes is truth: ``Truth.tau_ext_Nm = J_l ddtheta_l - T_transmitted``
    on the link, and ``Truth.tau_l_Nm``, that less gravity and the output bearings'
    friction, at the handle.  At t = 0 the motor starts
    where a rigid joint would be: no twist, and moving with the link's initial velocity
    (so a sine does not begin with a velocity jump across the damper).

    The discretisation is exact: the sine comes from a harmonic exosystem integrated
    with the joint in the same matrix exponential (:func:`prescribed_model`), so the
    only sub-step-dependent part is the motor's Coulomb friction, as in free motion.

    ``bearing_coulomb_Nm``: a Coulomb friction in the output-shaft bearings between the
    joint's torque sensor and the handle where the person's torque is measured
    (``τl^m`` of [Vertechy] §VI), ``-bearing_coulomb_Nm tanh(dtheta_l /
    bearing_smoothing_radps)`` on the link, the same smoothed form as the motor's
    Coulomb friction (:class:`DriveTrainConfig`).  The environment imposes the motion,
    so it does not change the joint's dynamics: the person supplies it, and it is the
    difference between what the handle's sensor measures (``Truth.tau_l_Nm``) and the
    torque acting on the link besides the joint's (``Truth.tau_ext_Nm``, the truth
    channel's ``TRUTH_JOINT.tau_ext``), which is what the joint's observer estimates.
    :meth:`handle_torque` takes one to the other; the scorer compares the observer's
    external-torque estimate with the handle torque.  Not in [Vertechy]'s model (Eq. 1);
    0 (the default) makes the two the same.  Only with a prescribed motion: on a free
    link the output bearings' friction is the drive train's ``b_load`` and
    ``coulomb_load``, which move the link.

    In an arm (:class:`~hdhil.hostsim.plant.arm.ArmPlant`, a ``[robot]`` scenario) the
    motion is a person's intent, not imposed: the person wears the arm and pulls each
    joint towards it through a joint impedance, ``tau_p = stiffness_Nm_per_rad
    (theta_p - theta_l) + damping_Nms_per_rad (dtheta_p - dtheta_l)``, plus, with
    ``holds_weight``, the gravity torque that holds the arm's links still (a person
    carries the weight of their own arm).  ``tau_p`` is the environment's torque on the
    link (``Truth.tau_l_Nm``).  A single joint's link follows the motion exactly, so
    these three are for arms only (:class:`~hdhil.hostsim.plant.model.Plant` refuses
    them).
    """

    kind: LinkMotionKind = "none"
    amplitude_deg: float = 0.0
    frequency_Hz: float = 1.0
    offset_deg: float = 0.0
    motion_seed: int = 0
    horizon_s: float = 60.0
    max_velocity_radps: float = 1000.0 * TWO_PI / 60.0 / 100.0
    #: Nm: Coulomb friction of the output-shaft bearings between the torque sensor and
    #: the handle (not seen by the handle's sensor); only with a prescribed motion.
    bearing_coulomb_Nm: float = 0.0
    #: rad/s of the link: the width of ``tanh`` in the bearing friction.
    bearing_smoothing_radps: float = 0.01
    #: Nm/rad: in an arm, the stiffness of the person who moves the link (docs/multibody.md).
    stiffness_Nm_per_rad: float = 0.0
    #: Nm s/rad: in an arm, the person's damping about the motion's velocity.
    damping_Nms_per_rad: float = 0.0
    #: In an arm: the person also carries the links' weight (their own arm's).
    holds_weight: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("none", "hold", "sine", "person"):
            raise ValueError(
                f"LinkMotionConfig.kind must be one of none, hold, sine, person, got {self.kind!r}"
            )
        check_fields(
            self,
            {
                "amplitude_deg": "finite",
                "frequency_Hz": ">0",
                "offset_deg": "finite",
                "horizon_s": ">0",
                "max_velocity_radps": ">0",
                "bearing_coulomb_Nm": ">=0",
                "bearing_smoothing_radps": ">0",
                "stiffness_Nm_per_rad": ">=0",
                "damping_Nms_per_rad": ">=0",
            },
        )
        if not isinstance(self.holds_weight, bool):
            raise ValueError(
                f"LinkMotionConfig.holds_weight must be true or false, got {self.holds_weight!r}"
            )
        if self.kind == "none" and (self.worn or self.holds_weight):
            raise ValueError(
                "LinkMotionConfig: stiffness_Nm_per_rad, damping_Nms_per_rad and holds_weight "
                "are a person's, who moves the link: kind hold, sine or person"
            )
        if self.bearing_coulomb_Nm and self.kind == "none":
            raise ValueError(
                "LinkMotionConfig.bearing_coulomb_Nm is for a prescribed motion (kind hold, "
                "sine or person); a free link's bearing friction is "
                "plant.drivetrain.coulomb_load"
            )
        ms = self.motion_seed
        if isinstance(ms, bool) or not isinstance(ms, int) or ms < 0:
            raise ValueError(f"LinkMotionConfig.motion_seed must be an integer >= 0, got {ms!r}")
        object.__setattr__(self, "_components", self._make_components())

    def _make_components(self) -> tuple[tuple[float, float, float], ...]:
        if self.kind == "sine":
            return ((math.radians(self.amplitude_deg), TWO_PI * self.frequency_Hz, 0.0),)
        if self.kind != "person" or self.amplitude_deg == 0.0:
            return ()
        rng = np.random.default_rng(self.motion_seed)
        lo, hi = PERSON_BAND_HZ
        f = rng.uniform(lo, hi, PERSON_COMPONENTS)
        phase = rng.uniform(0.0, TWO_PI, PERSON_COMPONENTS)
        w = TWO_PI * f
        a = 1.0 / f
        t = np.arange(0.0, self.horizon_s, 0.01)
        shape = (a[:, None] * np.sin(w[:, None] * t + phase[:, None])).sum(axis=0)
        speed = (a[:, None] * w[:, None] * np.cos(w[:, None] * t + phase[:, None])).sum(axis=0)
        scale = math.radians(abs(self.amplitude_deg)) / float(np.max(np.abs(shape)))
        scale = min(scale, self.max_velocity_radps / float(np.max(np.abs(speed))))
        sign = 1.0 if self.amplitude_deg > 0 else -1.0
        return tuple(
            (sign * scale * float(ai), float(wi), float(pi))
            for ai, wi, pi in zip(a, w, phase, strict=True)
        )

    def components(self) -> tuple[tuple[float, float, float], ...]:
        """The motion as ``(amplitude_rad, omega_radps, phase_rad)`` sinusoids around
        ``offset_deg``: one for ``sine``, :data:`PERSON_COMPONENTS` for ``person``, none
        for ``hold`` and ``none``."""
        return self._components  # type: ignore[attr-defined, no-any-return]

    @property
    def active(self) -> bool:
        """True when the link follows the prescription (kind other than ``none``)."""
        return self.kind != "none"

    @property
    def worn(self) -> bool:
        """True when a person pulls the link through an impedance (in an arm) rather
        than imposing the motion exactly."""
        return self.stiffness_Nm_per_rad > 0.0 or self.damping_Nms_per_rad > 0.0

    @property
    def amplitude_rad(self) -> float:
        """Amplitude in rad (0 for ``hold`` and ``none``)."""
        return math.radians(self.amplitude_deg) if self.kind == "sine" else 0.0

    @property
    def omega_radps(self) -> float:
        """Angular frequency ``2 pi f`` in rad/s."""
        return TWO_PI * self.frequency_Hz

    def angle(self, t: float) -> float:
        """Prescribed link angle (rad) at time ``t`` (s)."""
        if self.kind == "person":
            return math.radians(self.offset_deg) + sum(
                a * math.sin(w * t + p) for a, w, p in self.components()
            )
        return math.radians(self.offset_deg) + self.amplitude_rad * math.sin(self.omega_radps * t)

    def velocity(self, t: float) -> float:
        """Prescribed link velocity (rad/s) at time ``t``."""
        if self.kind == "person":
            return sum(a * w * math.cos(w * t + p) for a, w, p in self.components())
        w = self.omega_radps
        return self.amplitude_rad * w * math.cos(w * t)

    def bearing_friction(self, velocity: float) -> float:
        """The output-shaft bearings' friction on the link (Nm) at the link velocity
        ``velocity`` (rad/s): ``-bearing_coulomb_Nm tanh(velocity /
        bearing_smoothing_radps)``."""
        c = self.bearing_coulomb_Nm
        return -c * math.tanh(velocity / self.bearing_smoothing_radps) if c else 0.0

    def handle_torque(self, tau_ext: float, velocity: float) -> float:
        """What the handle's sensor measures, ``τl^m`` (plus gravity, ``τl + τg``), from
        the torque on the link besides the joint's ``tau_ext`` (``Truth.tau_ext_Nm``,
        ``TRUTH_JOINT.tau_ext``) at the link velocity ``velocity``: ``tau_ext`` without
        the bearing friction (:meth:`bearing_friction`)."""
        return tau_ext - self.bearing_friction(velocity)

    def acceleration(self, t: float) -> float:
        """Prescribed link acceleration (rad/s²) at time ``t``."""
        if self.kind == "person":
            return -sum(a * w * w * math.sin(w * t + p) for a, w, p in self.components())
        w = self.omega_radps
        return -self.amplitude_rad * w * w * math.sin(w * t)


@dataclass(frozen=True)
class GravityConfig:
    """Gravity on the output link, ``tau_g`` of [Vertechy] Eq. 1.

    ``tau_g = mgl_Nm * sin(theta_l + offset_deg)`` (Nm at the output, positive forward),
    with ``mgl_Nm`` the link's mass x g x distance of its centre of mass from the axis.
    ``offset_deg`` is the link's angle from the upright position at ``theta_l = 0``: 0
    puts the unstable equilibrium at ``theta_l = 0`` (gravity pushes away from it),
    180 makes ``theta_l = 0`` the hanging position (``tau_g = -mgl sin theta_l``,
    restoring).  Default 0 Nm: [Vertechy] §VI, "the joint axis is vertical so that tau_g
    = 0".  In free motion it is held over each sub-step (like the Coulomb friction);
    with a prescribed link motion it changes only ``Truth.tau_l_Nm``.
    """

    mgl_Nm: float = 0.0
    offset_deg: float = 0.0

    def __post_init__(self) -> None:
        check_fields(self, {"mgl_Nm": "finite", "offset_deg": "finite"})

    def torque(self, theta_l: float) -> float:
        """``tau_g`` (Nm) at link angle ``theta_l`` (rad)."""
        if self.mgl_Nm == 0.0:
            return 0.0
        return self.mgl_Nm * math.sin(theta_l + math.radians(self.offset_deg))


TorqueMeasurand = Literal["transmitted", "spring"]


@dataclass(frozen=True)
class SensorConfig:
    """Analog sensors ahead of the 12-bit ADC, and the motor encoder.

    * Torque: the strain-gauge bridge through its amplifier (``PlantConfig.bridge``,
      [Taghirad97] §2), ``V = (T_true + T_ripple) / volt2Nm_true + torque_offset_V +
      noise`` (see :class:`~hdhil.hostsim.plant.truth.Truth`); ``torque_offset_V`` is the bridge
      amplifier's electrical zero offset.
    * Tachometer on the motor: ``V = omega_motor / volt2radps + noise``; 56.2565 rad/s
      per V is [Taghirad97] listing A.1 (``volt2radps``).
    * Amplifier current monitor: ``V = i / current_monitor_A_per_V + noise``
      (representative, not from the papers).
    * Quadrature encoder on the motor, ``encoder_counts_per_rev`` counts per motor
      revolution (8000 = 2000 lines x 4; representative, not from the papers), read as
      a 16-bit wrapping count ([Taghirad97] listing: ``short pcsample``).

    Noise standard deviations are in physical units (Nm, rad/s at the motor, A),
    white and Gaussian, one independent draw per sample; representative values, not
    from the papers, except for [Vertechy]'s torque sensor: "torque sensor variance W =
    0.12 Nm (measured with the motor driver turned on)" (§I) is read by its unit, Nm: a
    standard deviation, ``torque_noise_Nm = 0.12`` Nm per sample.  The seed measured it
    on the sampled signal, so it is per sample here, at the 1 kHz sample rate: the one
    reading of W the whole project uses (the LQG design's too, see
    ``hdhil.firmware.lqg_design``, "One reading of W").

    ``torque_measures``: what the ideal torque sensor reads, ``Truth.T_true_Nm``.
    ``"transmitted"`` (default): the flexspline torque ``k (q_m - q_l) + c (dq_m -
    dq_l)``, spring and damper (the flexspline gauges of [Taghirad97]).  ``"spring"``: the
    spring torque ``k (q_m - q_l) = -tau_s`` only, the sensor torque of [Vertechy]
    (§II: ``tau_s = k (theta_l - theta_m)``; the variable of Eq. 2, so the joint
    response is exactly the second-order system the seed identifies in Fig. 5).
    """

    torque_offset_V: float = 0.0
    torque_noise_Nm: float = 0.02
    volt2radps: float = 56.2565
    tacho_noise_radps: float = 0.05
    current_monitor_A_per_V: float = 1.0
    current_noise_A: float = 0.0
    encoder_counts_per_rev: int = 8000
    torque_measures: TorqueMeasurand = "transmitted"

    def __post_init__(self) -> None:
        if self.torque_measures not in ("transmitted", "spring"):
            raise ValueError(
                "SensorConfig.torque_measures must be 'transmitted' or 'spring', "
                f"got {self.torque_measures!r}"
            )
        check_fields(
            self,
            {
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

    ``bridge`` is the strain-gauge torque sensor (:mod:`hostsim.bridge`), ``load`` the
    external load-torque profile, ``link`` a prescribed link trajectory (exclusive with
    a ``load`` profile: an infinitely stiff environment absorbs any load torque),
    ``gravity`` the gravity torque on the link.  ``adc`` converts the three analog sensor voltages
    to counts, ``dac`` is the converter the drive node uses to turn received DAC
    counts into the amplifier voltage (``dac.to_volts``) before calling
    :meth:`Plant.advance`.  ``substeps`` is the number of internal integration steps
    per :meth:`Plant.advance` call.
    """

    amplifier: AmplifierConfig = field(default_factory=AmplifierConfig)
    drivetrain: DriveTrainConfig = field(default_factory=DriveTrainConfig)
    ripple: RippleConfig = field(default_factory=RippleConfig)
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    load: LoadTorqueConfig = field(default_factory=LoadTorqueConfig)
    adc: Converter = field(default_factory=Converter)
    dac: Converter = field(default_factory=Converter)
    substeps: int = 4
    link: LinkMotionConfig = field(default_factory=LinkMotionConfig)
    gravity: GravityConfig = field(default_factory=GravityConfig)

    def __post_init__(self) -> None:
        for name, cls in (
            ("amplifier", AmplifierConfig),
            ("drivetrain", DriveTrainConfig),
            ("ripple", RippleConfig),
            ("bridge", BridgeConfig),
            ("sensors", SensorConfig),
            ("load", LoadTorqueConfig),
            ("adc", Converter),
            ("dac", Converter),
            ("link", LinkMotionConfig),
            ("gravity", GravityConfig),
        ):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"PlantConfig.{name} must be a {cls.__name__}")
        s = self.substeps
        if isinstance(s, bool) or not isinstance(s, int) or not 1 <= s <= 10_000:
            raise ValueError(f"PlantConfig.substeps must be an integer 1..10000, got {s!r}")
        if self.link.active and self.load.kind != "none":
            raise ValueError(
                f"PlantConfig: a prescribed link motion (link.kind = {self.link.kind!r}) "
                f"leaves no room for a load-torque profile (load.kind = {self.load.kind!r})"
            )

    @property
    def torque_per_volt(self) -> float:
        """Motor torque at the output per amplifier input volt (Nm/V): ``N Kt g``.

        ``gear_ratio * torque_constant_Nm_per_A * gain_A_per_V``: the steady-state
        output-referred motor torque (``tau_m`` of [Vertechy] Eq. 1) per DAC volt, below
        the current limit.  A firmware that commands torque through the DAC needs the
        same constant as its actuator calibration.
        """
        a = self.amplifier
        return self.drivetrain.gear_ratio * a.torque_constant_Nm_per_A * a.gain_A_per_V

    @property
    def max_motor_torque_Nm(self) -> float:
        """Motor torque saturation at the output (Nm): ``N Kt current_limit_A``."""
        a = self.amplifier
        return self.drivetrain.gear_ratio * a.torque_constant_Nm_per_A * a.current_limit_A
