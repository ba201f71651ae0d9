"""The emulator's own objects of the drive: 0x2300 "Emulator" and 0x2310 "Fault injection".

A real drive has neither: they let a test or a user retune the emulated physics (ripple,
sensor noise, load torque) and break its sensors or its link while a run goes on, over
SDO like any other parameter, reproducibly from the run's fault seed. Writes are applied
at the next SYNC, before the plant's step, so a cycle never sees half a change. They act
on the emulator's own :class:`~hdhil.hostsim.plant.Plant`; a drive around another plant
model refuses them (SDO abort 0x08000022).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import can

from hdhil.can.faults import TransmitSilence
from hdhil.canopen.services import ABORT_DEVICE_STATE, ABORT_INVALID_VALUE, CanopenServices
from hdhil.core.faultbase import FaultLog
from hdhil.hostsim.plant import Plant
from hdhil.hostsim.plant_model import PlantModel
from hdhil.hostsim.sensor_faults import (
    SensorFaultInjector,
    SensorFaults,
    SensorFaultSource,
    SensorHook,
    SensorWindow,
)

__all__ = [
    "EMULATOR_KNOBS",
    "FAULT_FIELDS",
    "FAULT_MASKS",
    "FAULT_SILENCE_MS",
    "MASK_CHANNELS",
    "OD_EMULATOR",
    "OD_FAULTS",
    "EmulatorObjects",
]

OD_EMULATOR = 0x2300
OD_FAULTS = 0x2310

#: 0x2300 sub-index -> (plant sub-configuration, field); "load" is the held load torque.
EMULATOR_KNOBS: dict[int, tuple[str, str]] = {
    1: ("ripple", "amp2_Nm"),
    2: ("ripple", "amp4_Nm"),
    3: ("ripple", "misalignment_pp_Nm"),
    4: ("sensors", "torque_noise_Nm"),
    5: ("sensors", "tacho_noise_radps"),
    6: ("load", "torque_Nm"),
}

#: 0x2310 sub-index -> the :class:`hdhil.hostsim.sensor_faults.SensorFaults` field it sets.
FAULT_FIELDS: dict[int, str] = {
    1: "tacho_spike_rate",
    2: "tacho_spike_V",
    3: "encoder_glitch_rate",
    4: "encoder_glitch_counts",
}
#: 0x2310 channel masks: sub-index -> (fault, saturation level).
FAULT_MASKS: dict[int, tuple[str, str]] = {
    5: ("stuck", "max"),
    6: ("saturated", "max"),
    7: ("saturated", "min"),
}
#: 0x2310 sub-index of the drive's silence (ms).
FAULT_SILENCE_MS = 8
#: Bit n of a 0x2310 channel mask is sensor channel n (DRIVE_TPDO1 order).
MASK_CHANNELS = ("torque", "tacho", "current", "encoder")


class EmulatorObjects:
    """Objects 0x2300 and 0x2310 of the drive, and the drive's silence.

    - 0x2300 "Emulator" (REAL32): 1 ``ripple_amp2_Nm``, 2 ``ripple_amp4_Nm`` (0..10 Nm),
      3 ``misalignment_pp_Nm`` (0..20 Nm), 4 ``torque_noise_Nm`` (0..5 Nm), 5
      ``tacho_noise_radps`` (0..10 rad/s), 6 ``load_torque_Nm`` (-100..100 Nm, the
      external torque the plant holds, :meth:`hdhil.hostsim.plant.Plant.set_load_torque`).
      Their power-on values are the plant's configuration.  A write is applied at the
      next SYNC, before the plant step: the plant's frozen configuration is rebuilt with
      ``dataclasses.replace`` and swapped in (:meth:`Plant.retune`), so the step ending at
      that SYNC and its sample use the new values.
    - 0x2310 "Fault injection" (:mod:`hdhil.hostsim.sensor_faults`), applied at the next
      SYNC like 0x2300: 1 ``tacho_spike_rate`` (REAL32, 0..1 per sample), 2
      ``tacho_spike_V`` (0..20 V), 3 ``encoder_glitch_rate`` (0..1 per sample), 4
      ``encoder_glitch_counts`` (UNSIGNED16); channel masks (UNSIGNED8, bit 0 torque, 1
      tacho, 2 current, 3 encoder) 5 ``stuck_mask`` (the channel holds its count from the
      next sample on), 6 ``saturated_max_mask`` and 7 ``saturated_min_mask`` (an ADC
      channel at its top or bottom code; the encoder has none, and a channel in both
      masks is refused with abort 0x06090030); 8 ``silence_ms`` (UNSIGNED16): from the
      next SYNC the drive transmits nothing for that long (PDOs, heartbeat, EMCY, SDO
      answers; a write during the silence is applied but not answered; 0 ends it), so the
      controller's sensor hold and heartbeat consumer react as to a drive that fell off
      the bus.  Power-on values: the plant's configured sensor faults
      (``[faults.sensors]``), no mask, no silence.  The faults are drawn from the run's
      fault seed and every one is recorded in its fault log (a silenced frame as
      ``silence`` on ``control``).  Nothing is installed while nothing is switched on:
      the plant keeps its fault-free path and the bus its own ``send``.

    ``faults`` is the run's fault injector, the one whose ``sensors()`` hook the plant has
    (if any): its seed and log serve the faults switched on through 0x2310.  Without one
    the drive keeps its own (seed 0; the plant's hook's log).  ``clock()`` is the node's
    time (the silence's).
    """

    def __init__(
        self,
        services: CanopenServices,
        plant: PlantModel,
        bus: can.BusABC,
        clock: Callable[[], float],
        faults: SensorFaultSource | None = None,
    ) -> None:
        self.services = services
        self.plant = plant
        self._clock = clock
        #: The emulator's own plant: 0x2300 and the sensor faults of 0x2310 act on it.
        self.active = isinstance(plant, Plant)
        hook = plant.faults if isinstance(plant, Plant) else None
        if faults is None:
            faults = SensorFaultInjector(
                hook.cfg if hook is not None else SensorFaults(),
                0,
                hook.log if hook is not None else FaultLog(keep=False),
            )
        self.faults = faults
        self._sensor_hook: SensorHook | None = hook
        # The configured sensor faults: the plant's hook's, else the source's (the hook
        # it would install; the same object later, when 0x2310 switches a fault on).
        if hook is None:
            hook = faults.sensors(always=True)
            assert hook is not None
        self._base_sensor_faults = hook.cfg
        self._mask_windows: dict[tuple[int, str], SensorWindow] = {}
        self.silence = TransmitSilence(bus, faults.log, "control", clock)

        # (index, sub) -> power-on value; writes wait for the next SYNC in ``pending``.
        self._power_on = self._knob_values_of(plant) | self._fault_power_on_values()
        self._fault_values = {
            sub: value for (index, sub), value in self._power_on.items() if index == OD_FAULTS
        }
        od = services.od
        for (index, sub), value in self._power_on.items():
            od[index][sub].default = value
        #: Writes of the cycle in progress, applied at the next SYNC (:meth:`apply`).
        self.pending: dict[tuple[int, int], float] = {}
        self._register()

    @property
    def silent(self) -> bool:
        """True while a silence written to 0x2310 sub 8 lasts (the drive sends nothing)."""
        return self.silence.active and self._clock() < self.silence.until

    def reset(self) -> None:
        """NMT reset node: the silence ends, the power-on values are written at the next
        SYNC."""
        self.silence.stop()  # the boot-up message goes out
        self.pending = dict(self._power_on)

    def _register(self) -> None:
        s = self.services
        for sub in EMULATOR_KNOBS:
            s.on_write(OD_EMULATOR, sub, self._writer(OD_EMULATOR, sub))
        for sub in (*FAULT_FIELDS, *FAULT_MASKS, FAULT_SILENCE_MS):
            s.on_write(OD_FAULTS, sub, self._writer(OD_FAULTS, sub))
        if not self.active:  # another plant model: nothing to retune or fault
            extras = (
                (OD_EMULATOR, tuple(EMULATOR_KNOBS)),
                (OD_FAULTS, (*FAULT_FIELDS, *FAULT_MASKS)),
            )
            for index, subs in extras:
                for sub in subs:
                    s.add_validator(index, sub, lambda _value: ABORT_DEVICE_STATE)
        # A channel saturates at one end: refuse a mask overlapping the other end's.
        for sub, other in ((6, 7), (7, 6)):
            s.add_validator(
                OD_FAULTS,
                sub,
                lambda mask, other=other: (
                    ABORT_INVALID_VALUE if mask & s.read(OD_FAULTS, other) else None
                ),
            )

    @staticmethod
    def _knob_values_of(plant: PlantModel) -> dict[tuple[int, int], float]:
        if not isinstance(plant, Plant):
            return dict.fromkeys(((OD_EMULATOR, sub) for sub in EMULATOR_KNOBS), 0.0)
        cfg = plant.cfg
        values = {}
        for sub, (section, name) in EMULATOR_KNOBS.items():
            # The held load torque starts at 0 in a new Plant.
            value = 0.0 if section == "load" else float(getattr(getattr(cfg, section), name))
            values[(OD_EMULATOR, sub)] = value
        return values

    def _fault_power_on_values(self) -> dict[tuple[int, int], float]:
        """0x2310 at power-on: the configured sensor faults' rates and sizes, no channel
        masked, no silence."""
        base = self._base_sensor_faults
        values: dict[tuple[int, int], float] = {
            (OD_FAULTS, sub): getattr(base, name) for sub, name in FAULT_FIELDS.items()
        }
        for sub in (*FAULT_MASKS, FAULT_SILENCE_MS):
            values[(OD_FAULTS, sub)] = 0
        return values

    def _writer(self, index: int, sub: int) -> Callable[[float], None]:
        def write(value: float) -> None:
            self.pending[(index, sub)] = float(value) if index == OD_EMULATOR else value

        return write

    def apply(self) -> None:
        """Apply the 0x2300 and 0x2310 writes of the past cycle (before the plant's next
        step)."""
        pending, self.pending = self.pending, {}
        emulator = {sub: v for (index, sub), v in pending.items() if index == OD_EMULATOR}
        faults = {sub: v for (index, sub), v in pending.items() if index == OD_FAULTS}
        if emulator:
            self._apply_emulator_knobs(emulator)
        if faults:
            self._apply_fault_switches(faults)

    def _apply_emulator_knobs(self, pending: dict[int, float]) -> None:
        """0x2300: the plant's ripple, sensor noise and load torque."""
        plant = self.plant
        assert isinstance(plant, Plant)
        cfg = plant.cfg
        changes: dict[str, dict[str, float]] = {"ripple": {}, "sensors": {}}
        for sub, value in pending.items():
            section, name = EMULATOR_KNOBS[sub]
            if section == "load":
                plant.set_load_torque(value)
            else:
                changes[section][name] = value
        if changes["ripple"] or changes["sensors"]:
            plant.retune(
                dataclasses.replace(
                    cfg,
                    ripple=dataclasses.replace(cfg.ripple, **changes["ripple"]),
                    sensors=dataclasses.replace(cfg.sensors, **changes["sensors"]),
                )
            )

    def _apply_fault_switches(self, changes: dict[int, Any]) -> None:
        """0x2310: start or end a silence; switch the plant's sensor faults.  The faults
        act from the sample that ends the plant step starting now; the sensor hook is
        installed only while some sensor fault is configured (none: the plant's
        fault-free path)."""
        if FAULT_SILENCE_MS in changes:
            self.silence.start(changes.pop(FAULT_SILENCE_MS) * 1e-3)
        if not changes:
            return
        self._fault_values.update(changes)
        cfg = self._switched_sensor_faults()
        hook = self._sensor_hook
        if hook is None:
            if not cfg.enabled:
                return
            hook = self._sensor_hook = self.faults.sensors(always=True)
            assert hook is not None
        hook.reconfigure(cfg)
        self.plant.faults = hook if cfg.enabled else None  # type: ignore[attr-defined]

    def _switched_sensor_faults(self) -> SensorFaults:
        """The configured sensor faults with 0x2310's rates and sizes, plus one window per
        masked channel from now on (a channel that stays masked keeps its window, so a
        stuck channel keeps its count)."""
        values = self._fault_values
        start = self.plant.time
        windows: dict[tuple[int, str], SensorWindow] = {}
        for sub, (_, level) in FAULT_MASKS.items():
            for bit, channel in enumerate(MASK_CHANNELS):
                if int(values[sub]) >> bit & 1:
                    key = (sub, channel)
                    windows[key] = self._mask_windows.get(key) or SensorWindow(
                        channel,  # type: ignore[arg-type]
                        start_s=start,
                        level=level,  # type: ignore[arg-type]
                    )
        self._mask_windows = windows
        base = self._base_sensor_faults
        stuck = tuple(w for (sub, _), w in windows.items() if FAULT_MASKS[sub][0] == "stuck")
        saturated = tuple(w for (sub, _), w in windows.items() if FAULT_MASKS[sub][0] != "stuck")
        return dataclasses.replace(
            base,
            stuck=base.stuck + stuck,
            saturated=base.saturated + saturated,
            **{name: values[sub] for sub, name in FAULT_FIELDS.items()},
        )
