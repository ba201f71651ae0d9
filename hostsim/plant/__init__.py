"""The drive emulator's physics: servo amplifier, flexible harmonic-drive joint, sensors.

One job per module: :mod:`.config` (the ``[plant]`` table as frozen dataclasses),
:mod:`.linear` (state-space models, their exact discretisation, the steady state),
:mod:`.model` (:class:`Plant`, the stepper and the sensor read-out), :mod:`.stability`
(which configurations the stepper integrates at a given step) and :mod:`.truth` (the
ground-truth record). Every public name is importable from here, as
``hdhil.hostsim.plant.PlantConfig``, except :mod:`.multibody`'s (the rigid-body link
dynamics of a robot from its URDF, the ``arm`` extra) and :mod:`.arm`'s (an actuator on
every joint of those links), imported from there when needed.

The plant is what stands behind :class:`hdhil.hostsim.drive.DriveNode`; any object
with the members of :class:`hdhil.hostsim.plant_model.PlantModel` can take its place.
"""

from hdhil.hostsim.plant.config import (
    PERSON_BAND_HZ,
    PERSON_COMPONENTS,
    AmplifierConfig,
    BridgeConfig,
    DriveTrainConfig,
    GravityConfig,
    LinkMotionConfig,
    LoadTorqueConfig,
    PlantConfig,
    RippleConfig,
    SensorConfig,
)
from hdhil.hostsim.plant.linear import (
    continuous_model,
    discrete_model,
    person_model,
    prescribed_model,
    steady_state_motor_velocity,
    steady_state_volts,
)
from hdhil.hostsim.plant.model import ENCODER_MODULUS, Plant
from hdhil.hostsim.plant.stability import NonFiniteStateError, check_step, step_problems
from hdhil.hostsim.plant.truth import RippleParts, Truth

__all__ = [
    "ENCODER_MODULUS",
    "PERSON_BAND_HZ",
    "PERSON_COMPONENTS",
    "AmplifierConfig",
    "BridgeConfig",
    "DriveTrainConfig",
    "GravityConfig",
    "LinkMotionConfig",
    "LoadTorqueConfig",
    "NonFiniteStateError",
    "Plant",
    "PlantConfig",
    "RippleConfig",
    "RippleParts",
    "SensorConfig",
    "Truth",
    "check_step",
    "continuous_model",
    "discrete_model",
    "person_model",
    "prescribed_model",
    "steady_state_motor_velocity",
    "steady_state_volts",
    "step_problems",
]
