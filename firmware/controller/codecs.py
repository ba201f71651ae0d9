"""The controller's PDO codecs: which frames it decodes and encodes, and with what layout.

Without a drive DCF the frames are the [Taghirad97] raw ADC/DAC mapping of
``control.dbc``, encoded with its compiled codecs.  With one, the controller gives its own
PDOs the drive's mapping (:mod:`hdhil.firmware.controller.objects`) and the frames are
encoded and decoded from that live mapping, the objects picked by name.  The choice is
made once, at construction, so the per-cycle code only indexes tuples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hdhil.canopen.mapping import layout_codec, od_layouts
from hdhil.canopen.pdo import PdoLayout
from hdhil.dbc import FrameCodec, codec

__all__ = ["LinkCodecs", "default_codecs", "mapped_codecs"]

#: The sensor objects of the raw mapping and of the CiA 402 CST mapping, by name, and the
#: drive's joint-torque sensor (0x2102), which the CST mapping may carry beside them.
RAW_SENSOR = ("ADC_torque", "ADC_tacho", "ADC_current", "ENC_count")
CST_SENSOR = ("torque_actual_value", "position_actual_value")
JOINT_TORQUE_SENSOR = "joint_torque_sensor"


@dataclass
class LinkCodecs:
    """The frames of the link and how the node reads and fills them.

    ``sensor_mapping``: which sensor objects the drive sends, "raw" (the seed's ADC counts and
    encoder), "cst" (CiA 402 torque actual 0x6077 and position actual 0x6064) or
    "cst-sensor" (those and the joint-torque sensor 0x2102, mV of the strain-gauge bridge).
    ``sensor_picks`` / ``command_picks``: the positions of the objects the node uses in the
    sensor and command frames (raw: torque, tacho, current, encoder; CST: torque, position,
    then the joint-torque sensor if mapped; command: DAC code or target torque, controlword,
    then the cycle counter if mapped).  ``dbc_command``: the command frame is
    ``control.dbc``'s, encoded in its signal order.
    """

    sensor: FrameCodec
    command: FrameCodec
    telemetry: FrameCodec
    control_telemetry: FrameCodec
    status: FrameCodec
    sensor_mapping: str = "raw"
    sensor_picks: tuple[int, ...] = (0, 1, 2, 3)
    command_picks: tuple[int, ...] = (0, 1, 2)
    dbc_command: bool = True


def default_codecs() -> LinkCodecs:
    """``control.dbc``'s codecs, each checked against the names this node packs and
    unpacks (a DBC with reordered signals fails here, loudly)."""
    return LinkCodecs(
        sensor=codec("control", "DRIVE_TPDO1").expect(*RAW_SENSOR),
        command=codec("control", "DRIVE_RPDO1").expect("DAC_cmd", "controlword", "cycle"),
        telemetry=codec("control", "CTRL_TPDO1").expect(
            "T_meas", "T_filtered", "velocity", "current"
        ),
        control_telemetry=codec("control", "CTRL_TPDO2").expect(
            "dtau_s_hat", "tau_lgd_hat", "tau_sD", "e_hat"
        ),
        status=codec("control", "DRIVE_TPDO2").expect("statusword"),
    )


def mapped_codecs(od: Any, read: Any, control_active: bool) -> LinkCodecs:
    """Codecs of a mapping taken from the drive's DCF, from this node's live PDOs (RPDO1
    the sensor frame, RPDO2 the statusword, TPDO3 the command), with the objects picked
    by name: the sensor frame must carry the seed's ADC channels and encoder or the CiA
    402 torque and position actual values, the command the controlword and the DAC
    command or the target torque.  The telemetry keeps ``control.dbc``'s layout.  Which
    torque the firmware filters follows from the mapping read here, not from a name:
    when the sensor frame carries the joint-torque sensor 0x2102 beside 0x6077 the
    mapping is "cst-sensor" and the filter runs on the gauge torque.

    Raises ``ValueError`` for a mapping the firmware cannot run, and for a torque-control
    law (``control_active``) in the CST mapping without the joint-torque sensor:
    [Vertechy]'s laws regulate the sensor torque tau_s = k (theta_l - theta_m) (Eq. 2,
    8), and 0x6077 is the amplifier's motor torque, a different quantity.
    """
    layouts = od_layouts(od, read)

    def live(kind: str, number: int, name: str) -> FrameCodec:
        layout: PdoLayout = layouts[(kind, number)]
        if not layout.valid:
            raise ValueError(f"the controller's {kind.upper()}{number} ({name}) is not valid")
        return layout_codec(od, layout, name)

    def picks(frame: FrameCodec, names: tuple[str, ...]) -> tuple[int, ...] | None:
        have = frame.signal_names
        return tuple(have.index(n) for n in names) if set(names) <= set(have) else None

    sensor = live("rpdo", 1, "DRIVE_TPDO1")
    raw = picks(sensor, RAW_SENSOR)
    cst = picks(sensor, CST_SENSOR)
    if raw is None and cst is None:
        raise ValueError(
            f"the drive's sensor PDO maps ({', '.join(sensor.signal_names)}); the firmware "
            "needs ADC_torque, ADC_tacho, ADC_current and ENC_count (raw mapping) or "
            "torque_actual_value and position_actual_value (CiA 402 CST mapping)"
        )
    command = live("tpdo", 3, "DRIVE_RPDO1")
    target = "DAC_cmd" if raw is not None else "target_torque"
    order = picks(command, (target, "controlword"))
    if order is None:
        raise ValueError(
            f"the drive's command PDO maps ({', '.join(command.signal_names)}); with the "
            f"{'raw' if raw is not None else 'CST'} sensor objects it must map {target} "
            "and controlword"
        )
    cycle = picks(command, ("cycle",))
    status = live("rpdo", 2, "DRIVE_TPDO2").expect("statusword")
    gauge = picks(sensor, (JOINT_TORQUE_SENSOR,)) if raw is None else None
    if raw is None and gauge is None and control_active:
        raise ValueError(
            "the torque-control laws ([Vertechy]) regulate the strain-gauge sensor "
            "torque; the CiA 402 CST mapping carries the amplifier's torque 0x6077 "
            "only: run them in the raw mapping or map the joint-torque sensor 0x2102 "
            "(--mapping cst-sensor)"
        )
    default = default_codecs()
    return LinkCodecs(
        sensor=sensor,
        command=command,
        telemetry=default.telemetry,
        control_telemetry=default.control_telemetry,
        status=status,
        sensor_mapping="raw" if raw is not None else "cst" if gauge is None else "cst-sensor",
        sensor_picks=raw if raw is not None else (*cst, *(gauge or ())),  # type: ignore[misc]
        command_picks=(*order, *(cycle or ())),
        dbc_command=False,
    )
