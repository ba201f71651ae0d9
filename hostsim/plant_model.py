"""The seam between the drive node and its physics: what :class:`hostsim.drive.DriveNode`
needs from a plant.

The drive node is the CANopen device (NMT, heartbeat, CiA 402 state machine, PDOs,
EMCY); the plant is the physics behind it. The node holds no physics: on SYNC k it
advances the plant by one period with the amplifier input of the past period, reads the
sensors and sends them (docs/design.md, "Timing semantics"). Any object with the members
below can stand behind the node: the emulator's own :class:`hostsim.plant.Plant`
(harmonic drive, flexible joint, strain-gauge sensor with ripple) or a model of your
own (README, "Plugging in a plant"; a rigid inertia in ``tests/test_plant_model.py``).

Units: volts, seconds, newton-metres, radians and rad/s at the output (load) side except
where a name says motor. Sensor readings are ADC counts of the drive's sensor frame
(DRIVE_TPDO1, ``dbc/control.dbc``), converted with :attr:`PlantModel.adc`; the drive
turns received DAC counts into the amplifier voltage with :attr:`PlantModel.dac`, the
same :class:`hdhil.core.converter.Converter` the firmware uses, so both sides agree on
counts and volts by construction.

The emulator's extras (object 0x2300: ripple, noise and load torque at run time; 0x2310
sub 1-7: sensor faults) act on :class:`hostsim.plant.Plant` only; with another model the
drive refuses those SDO writes (abort 0x08000022). Ground truth (the ``truth`` members)
goes to the truth channel, which the firmware never reads.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from hdhil.core.converter import Converter

#: One sensor reading in DRIVE_TPDO1 order: torque bridge, tachometer and motor-current
#: ADC counts, and the 16-bit encoder count.
SensorCounts = tuple[int, int, int, int]


@runtime_checkable
class PlantModel(Protocol):
    """What the drive node needs from a plant (module docstring)."""

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
        (continuous over-current) while :attr:`motor_torque_command_output` is there."""
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

    # ------------------------------------------------------------ truth (scoring only)
    @property
    def T_true(self) -> float:
        """Joint torque the sensor should read (Nm)."""
        ...

    @property
    def T_ripple(self) -> float:
        """Torque ripple in the sensor reading (Nm; 0 for a sensor without ripple)."""
        ...

    @property
    def theta_motor(self) -> float:
        """Motor angle (rad, wrapped as in TRUTH_MOTION)."""
        ...

    @property
    def theta_output(self) -> float:
        """Output angle (rad, wrapped as in TRUTH_MOTION)."""
        ...

    @property
    def omega_motor(self) -> float:
        """Motor velocity (rad/s)."""
        ...

    @property
    def omega_output(self) -> float:
        """Output velocity (rad/s)."""
        ...

    @property
    def external_torque(self) -> float:
        """Torque of the environment on the load (Nm)."""
        ...

    @property
    def motor_disturbance(self) -> float:
        """Disturbance torque on the motor side, output-referred (Nm; e.g. friction)."""
        ...

    @property
    def motor_torque_output(self) -> float:
        """Motor torque the amplifier produces now, output-referred (Nm)."""
        ...

    @property
    def motor_torque_command_output(self) -> float:
        """Motor torque commanded by the amplifier input, output-referred (Nm)."""
        ...
