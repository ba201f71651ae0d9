"""The plant's ground truth: what the sensors would read without noise, and its parts.

The drive publishes the truth on the truth channel (``truth.dbc``), which the firmware
never reads; the scorer compares the firmware's estimates with it. It is kept apart
from the sensor readings so that the split the scorer relies on stays exact: the torque
sensor reads ``T_true + T_ripple`` (noise and offset aside) at its true gain.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["RippleParts"]


class RippleParts(NamedTuple):
    """The parts of the torque sensor's ripple ``T_ripple`` (Nm)."""

    mesh: float  #: gear meshing, 2x and 4x motor angle (RippleConfig)
    misalignment: float  #: side load at the output angle (RippleConfig)
    modulation: float  #: wave-generator residual of the bridge at 2 beta (BridgeConfig)
    nonlinearity: float  #: cubic gauge nonlinearity (BridgeConfig)
    hysteresis: float  #: gauge hysteresis (BridgeConfig)
