"""The torque-sensor calibration rig of [Taghirad97] §3, emulated: arm and weight on a
locked wave generator, least-squares gains, their mean and consistency (Table 1).

Why emulated: ``hdhil calibrate`` finds the sensor gain the firmware needs the way the
paper's rig does, with every error of the real chain, so the gain error of an
uncalibrated firmware and what calibration removes can be measured.

1. The plant is held locked (:meth:`Plant.hold_locked`): wave generator fixed, the
   flexspline carrying the arm's torque, read through the whole sensor chain (gauges,
   bridge, amplifier, noise, 12-bit ADC) and averaged over ``samples`` readings.
2. ``positions`` flexspline positions around the circumference, each set so that the
   wave generator's angle relative to the gauges (``Truth.beta_rad``) steps evenly
   through one period of the bridge's 2β modulation, from a random start.
3. At each position one experiment per range of ``ranges_Nm`` (weights 0 → +max → 0 →
   −max → 0 in ``steps`` increments), each fitted with a least-squares line; the gain
   is the mean over the experiments, the consistency their std / mean.

The lever arm's effective length differs from the nominal one by a random relative error
of standard deviation ``lever_error`` per mounting, unknown to the experimenter; it
dominates the consistency, as on the real rig.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from hdhil.core.dataconf import check_fields
from hdhil.hostsim.plant import Plant, PlantConfig

__all__ = ["CalibrationResult", "CalibrationRig", "Experiment", "calibrate", "load_sequence"]

TWO_PI = 2.0 * math.pi
G_N_PER_KG = 9.80665  # standard gravity


@dataclass(frozen=True)
class CalibrationRig:
    """The arm-and-weight experiment ([Taghirad97] §3).

    - ``positions`` 4 flexspline positions x ``ranges_Nm`` (5 Nm low range, 40 Nm full
      range = the rated torque, [Taghirad97] §2) = the seed's eight experiments (Table 1).
    - ``steps`` 5 weights per direction; ``samples`` 200 ADC readings averaged per load
      step (0.2 s at 1 kHz).
    - ``arm_length_m`` 0.5 m: only turns torques into the masses the report lists.
    - ``lever_error`` 0.5 %: relative standard deviation of the arm's effective length
      per mounting (see the module docstring).  Not from the seed.
    """

    positions: int = 4
    ranges_Nm: tuple[float, ...] = (5.0, 40.0)
    steps: int = 5
    samples: int = 200
    arm_length_m: float = 0.5
    lever_error: float = 5e-3

    def __post_init__(self) -> None:
        for name, lo, hi in (("positions", 1, 360), ("steps", 1, 1000), ("samples", 1, 10**6)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"CalibrationRig.{name} must be an integer {lo}..{hi}, got {v!r}")
        if not self.ranges_Nm or not all(
            isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and r > 0
            for r in self.ranges_Nm
        ):
            raise ValueError(
                f"CalibrationRig.ranges_Nm must list torques > 0, got {self.ranges_Nm!r}"
            )
        check_fields(self, {"arm_length_m": ">0", "lever_error": ">=0"})
        if self.positions * len(self.ranges_Nm) < 2:
            raise ValueError("the consistency measure needs at least two experiments")


@dataclass(frozen=True)
class Experiment:
    """One loading/unloading experiment at one flexspline position (one row of the report)."""

    index: int
    position: int
    range_Nm: float
    flexspline_deg: float  #: output (flexspline) angle, degrees in [0, 360)
    beta_deg: float  #: wave generator relative to the gauges, degrees in [0, 180)
    mass_per_step_kg: float
    points: int
    gain_Nm_per_V: float
    offset_V: float  #: the fitted line's zero-torque voltage
    residual_rms_Nm: float
    torques_Nm: tuple[float, ...] = field(repr=False)
    volts: tuple[float, ...] = field(repr=False)


@dataclass(frozen=True)
class CalibrationResult:
    """Table 1 of [Taghirad97] for the emulated sensor, plus the emulator's truth."""

    seed: int
    rig: CalibrationRig
    experiments: tuple[Experiment, ...]
    gain_Nm_per_V: float  #: mean of the experiments' gains ([Taghirad97] §3)
    consistency: float  #: sample std / mean of the gains (a fraction; Table 1: 0.02)
    true_gain_Nm_per_V: float  #: the emulated chain's small-signal gain (BridgeConfig)

    @property
    def error(self) -> float:
        """Relative error of the calibrated gain against the emulator's true gain."""
        return self.gain_Nm_per_V / self.true_gain_Nm_per_V - 1.0

    def as_dict(self, points: bool = False) -> dict:
        """Plain data (JSON); ``points`` adds each experiment's (torque, volts) lists."""
        rows = []
        for e in self.experiments:
            row = asdict(e)
            if not points:
                del row["torques_Nm"], row["volts"]
            else:
                row["torques_Nm"], row["volts"] = list(e.torques_Nm), list(e.volts)
            rows.append(row)
        rig = asdict(self.rig)
        rig["ranges_Nm"] = list(self.rig.ranges_Nm)
        return {
            "seed": self.seed,
            "rig": rig,
            "gain_Nm_per_V": self.gain_Nm_per_V,
            "consistency": self.consistency,
            "true_gain_Nm_per_V": self.true_gain_Nm_per_V,
            "error": self.error,
            "experiments": rows,
        }


def load_sequence(max_Nm: float, steps: int) -> list[float]:
    """Nominal torques of one experiment: 0 → +max → 0 → −max → 0 in ``steps`` increments."""
    up = [max_Nm * k / steps for k in range(steps + 1)]
    down = up[-2::-1]
    return up + down[:-1] + [-v for v in up] + [-v for v in down]


def _locked_motor_angle(p: int, positions: int, beta0: float, gear_ratio: float) -> float:
    """Wave-generator angle of position p: output near 2 pi p / P, beta = beta0 + pi p / P.

    With the lock unloaded, ``beta = theta_m (N + 1) / N`` (``Truth.beta_rad``); the
    output is turned from ``2 pi p / P`` by less than pi / (N + 1) to hit the target.
    """
    n = gear_ratio
    nominal = n * TWO_PI * p / positions
    target = beta0 + math.pi * p / positions
    delta = (target - nominal * (n + 1.0) / n) % math.pi
    return nominal + delta * n / (n + 1.0)


def calibrate(
    plant_cfg: PlantConfig | None = None,
    rig: CalibrationRig | None = None,
    seed: int = 0,
    on_experiment: Callable[[int, int], object] | None = None,
) -> CalibrationResult:
    """Run the emulated calibration of [Taghirad97] §3 and return its Table 1.

    Deterministic for a given ``seed``: it seeds the plant's sensor noise and the
    rig's own draws (the first position's modulation phase, the lever-arm errors).
    ``on_experiment(done, total)`` is called after each experiment (progress).
    """
    plant_cfg = plant_cfg or PlantConfig()
    rig = rig or CalibrationRig()
    plant = Plant(plant_cfg, seed=seed)
    rng = np.random.Generator(np.random.PCG64([seed, 0x5EED]))
    beta0 = float(rng.uniform(0.0, math.pi))
    n_exp = rig.positions * len(rig.ranges_Nm)
    lever = 1.0 + rig.lever_error * rng.standard_normal(n_exp)
    adc = plant_cfg.adc
    gear = plant_cfg.drivetrain.gear_ratio
    experiments: list[Experiment] = []
    for p in range(rig.positions):
        theta_m = _locked_motor_angle(p, rig.positions, beta0, gear)
        for max_Nm in rig.ranges_Nm:
            idx = len(experiments)
            if on_experiment is not None and idx:
                on_experiment(idx, n_exp)
            torques = load_sequence(max_Nm, rig.steps)
            volts = []
            for nominal in torques:
                plant.hold_locked(theta_m, nominal * float(lever[idx]))
                total = 0.0
                for _ in range(rig.samples):
                    total += adc.to_volts(plant.sample()[0])
                volts.append(total / rig.samples)
            slope, intercept = np.polyfit(volts, torques, 1)
            fit = slope * np.asarray(volts) + intercept
            plant.hold_locked(theta_m, 0.0)
            truth = plant.truth()
            experiments.append(
                Experiment(
                    index=idx + 1,
                    position=p + 1,
                    range_Nm=max_Nm,
                    flexspline_deg=math.degrees(truth.theta_output_rad % TWO_PI),
                    beta_deg=math.degrees(truth.beta_rad % math.pi),
                    mass_per_step_kg=max_Nm / rig.steps / (G_N_PER_KG * rig.arm_length_m),
                    points=len(torques),
                    gain_Nm_per_V=float(slope),
                    offset_V=float(-intercept / slope),
                    residual_rms_Nm=float(np.sqrt(np.mean((fit - np.asarray(torques)) ** 2))),
                    torques_Nm=tuple(torques),
                    volts=tuple(volts),
                )
            )
    gains = np.array([e.gain_Nm_per_V for e in experiments])
    mean = float(gains.mean())
    return CalibrationResult(
        seed=seed,
        rig=rig,
        experiments=tuple(experiments),
        gain_Nm_per_V=mean,
        consistency=float(gains.std(ddof=1) / mean),
        true_gain_Nm_per_V=plant.bridge.volt2Nm,
    )
