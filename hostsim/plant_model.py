"""The seam between the drive node and its physics: what the drive needs from a plant.

The drive node (:class:`hdhil.hostsim.drive.DriveNode`) is the CANopen device and holds
no physics: on SYNC k it advances the plant by one period with the amplifier input of
the past period, reads the sensors, sends them, and publishes the plant's
:class:`~hdhil.hostsim.plant.truth.Truth` on the truth channel (which the firmware never
reads). Any object with the members of :class:`PlantModel` can stand behind it: the
emulator's own :class:`hdhil.hostsim.plant.Plant` or a model of your own.

Units: volts, seconds, newton-metres, radians and rad/s at the output except where a
name says motor. Sensor readings are the ADC counts of DRIVE_TPDO1 (``dbc/control.dbc``)
in the converter :attr:`PlantModel.adc`; the drive turns DAC counts into amplifier volts
with :attr:`PlantModel.dac`, the converter the firmware uses too. The emulator's extras
(object 0x2300, the sensor faults of 0x2310) act on its own plant only; another plant
refuses those SDO writes (abort 0x08000022).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from hdhil.core.converter import Converter
from hdhil.hostsim.plant.truth import Truth

__all__ = ["PlantModel", "SensorCounts", "Truth"]

#: One sensor reading in DRIVE_TPDO1 order: torque bridge, tachometer and motor-current
#: ADC counts, and the 16-bit encoder count.
SensorCounts = tuple[int, int, int, int]


@runtime_checkable
class PlantModel(Protocol):
    """What the drive node needs from a plant. A rigid inertia ``J`` driven with ``k`` Nm
    per amplifier volt, with a linear torque sensor, a tachometer and an encoder read
    with the firmware's gains (``tests/test_plant_model.py`` runs it)::

        class RigidInertia:
            adc = dac = Converter()  # the firmware's 12-bit, +/-10 V converters
            max_motor_torque_Nm = 10.0
            J, k = 0.005, 1.0  # kg m², Nm per volt
            time = angle = omega = torque = 0.0

            def advance(self, volts: float, dt: float) -> None:
                self.torque = self.k * volts
                self.angle += (self.omega + 0.5 * self.torque / self.J * dt) * dt
                self.omega += self.torque / self.J * dt
                self.time += dt

            def sample(self) -> SensorCounts:
                counts = self.adc.to_counts
                enc = math.floor(self.angle / (2 * math.pi) * 8000) % 65536
                return counts(self.torque / 6.6), counts(self.omega / 56.2565), 0, enc

            def truth(self) -> Truth:
                a, w, T = self.angle, self.omega, self.torque
                return Truth(T, a, a, w, w, tau_m_Nm=T, tau_m_cmd_Nm=T)
    """

    @property
    def adc(self) -> Converter:
        """Converter of the three analog sensor voltages to counts."""
        ...

    @property
    def dac(self) -> Converter:
        """Converter the drive uses to turn received DAC counts into amplifier volts."""
        ...

    @property
    def max_motor_torque_Nm(self) -> float:
        """Motor torque at the current limit (Nm, output): the drive signals EMCY 0x2310
        (continuous over-current) while :attr:`Truth.tau_m_cmd_Nm` is there."""
        ...

    @property
    def time(self) -> float:
        """Plant time (s): the sum of every :meth:`advance` ``dt``."""
        ...

    def advance(self, volts: float, dt: float) -> None:
        """Integrate over ``dt`` seconds with the amplifier input held at ``volts``."""
        ...

    def sample(self) -> SensorCounts:
        """The sensors at :attr:`time`, as ADC counts and the encoder count."""
        ...

    def truth(self) -> Truth:
        """The ground truth at :attr:`time` (scoring only; the firmware never sees it)."""
        ...
