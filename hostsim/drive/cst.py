"""The drive's cyclic synchronous torque objects (CiA 402-2, mode CST).

A controller that speaks CiA 402 rather than the DBC's raw DAC counts commands torque
through 0x6071 and reads back 0x6077, 0x6064 and 0x606C; these objects translate between
that and the plant, so a CST mapping (``dbc/drive-cst.dcf``) drives the same amplifier
as the raw DAC command does.
"""

from __future__ import annotations

from collections.abc import Callable

from hdhil.canopen.cia402 import (
    MAX_TORQUE_OBJECT,
    POSITION_ACTUAL_OBJECT,
    RATED_TORQUE_OBJECT,
    TARGET_TORQUE_OBJECT,
    TORQUE_ACTUAL_OBJECT,
    VELOCITY_ACTUAL_OBJECT,
)
from hdhil.canopen.od import index_of
from hdhil.canopen.services import CanopenServices
from hdhil.hostsim.plant_model import PlantModel

__all__ = ["CstObjects"]


class CstObjects:
    """Cyclic synchronous torque objects (CiA 402-2): 0x6071 target torque and 0x6077
    torque actual in per mille of 0x6076 motor rated torque (mNm), limited by 0x6072 max
    torque (per mille); 0x6064 position actual (encoder increments, unwrapped to 32 bits)
    and 0x606C velocity actual (increments per second, from the encoder over the last SYNC
    period).  The rated torque's power-on value is the amplifier's full-scale command,
    ``torque_per_volt`` x the DAC's full scale (60000 mNm for the default plant, the EDS
    default; a plant model without a ``torque_per_volt`` keeps the EDS default and
    commands no torque through 0x6071)."""

    def __init__(self, services: CanopenServices, plant: PlantModel) -> None:
        self.services = services
        self.plant = plant
        self._dac = plant.dac
        od = services.od
        self.od_target_torque = index_of(od, TARGET_TORQUE_OBJECT)
        self._od_max_torque = index_of(od, MAX_TORQUE_OBJECT)
        self._od_rated_torque = index_of(od, RATED_TORQUE_OBJECT)
        self._od_torque_actual = index_of(od, TORQUE_ACTUAL_OBJECT)
        self._od_position = index_of(od, POSITION_ACTUAL_OBJECT)
        self._od_velocity = index_of(od, VELOCITY_ACTUAL_OBJECT)
        per_volt = getattr(getattr(plant, "cfg", None), "torque_per_volt", None)
        self._torque_per_volt: float | None = float(per_volt) if per_volt else None
        if self._torque_per_volt:
            rated_mNm = round(self._torque_per_volt * self._dac.full_scale_V * 1e3)
            services.set_power_on_value(self._od_rated_torque, 0, rated_mNm)
        self.position = 0
        self.velocity = 0
        self._last_encoder: int | None = None

    def live_values(self) -> dict[tuple[int, int], Callable[[], int]]:
        """The objects read from the node's state, not from the object dictionary."""
        return {
            (self._od_torque_actual, 0): self.torque_actual,
            (self._od_position, 0): lambda: self.position,
            (self._od_velocity, 0): lambda: self.velocity,
        }

    def _rated_Nm(self) -> float:
        return self.services.read(self._od_rated_torque) * 1e-3

    def torque_to_counts(self, per_mille: int) -> int:
        """0x6071 (per mille of rated torque, within 0x6072) as the amplifier's DAC
        command: torque / torque_per_volt, quantised as the raw DAC object would be."""
        if not self._torque_per_volt:
            return 0
        rated = self._rated_Nm()
        limit = self.services.read(self._od_max_torque) * 1e-3 * rated
        torque = min(max(per_mille * 1e-3 * rated, -limit), limit)
        return self._dac.to_counts(torque / self._torque_per_volt)

    def torque_actual(self) -> int:
        """0x6077: the motor torque the amplifier produces, per mille of rated torque."""
        rated = self._rated_Nm()
        value = round(self.plant.truth().tau_m_Nm / rated * 1e3) if rated else 0
        return min(max(value, -32768), 32767)

    def update_position(self, encoder: int, dt: float) -> None:
        """0x6064 and 0x606C from the encoder count of a SYNC, ``dt`` after the last."""
        last = self._last_encoder
        self._last_encoder = encoder
        if last is None:
            return
        delta = (encoder - last + 0x8000) % 0x10000 - 0x8000
        self.position = (self.position + delta + 0x80000000) % 0x100000000 - 0x80000000
        self.velocity = round(delta / dt) if dt > 0 else 0
