"""An interrupt handler of one's own behind the controller node
(:class:`hdhil.firmware.interrupt.InterruptHandlerModel`), through a controller factory.

The example handler is a velocity P-controller: it reads the tachometer counts, commands
``Kp (w_ref - w)`` volts, and reports the measured torque and velocity as telemetry.
Against the rigid inertia of ``test_plant_model`` (torque ``k V``, ``J dw/dt = k V``) the
loop is first order with time constant ``J / (k Kp)`` (plus one sample of actuation
delay), so the velocity settles at ``w_ref``; the test checks that it does, through the
firmware's telemetry and the truth channel both.
"""

from __future__ import annotations

import can
import pytest
from conftest import FrameRecorder
from runs import lockstep
from test_plant_model import VOLT2NM, VOLT2RADPS, rigid_drive

from hdhil.core.converter import Converter
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode
from hdhil.firmware.interrupt import AdcSample, InterruptHandlerModel, IsrOutput
from hdhil.rig.factories import NodeSite
from hdhil.rig.scenario import load_scenario

W_REF = 40.0  # rad/s
KP = 0.05  # V per rad/s: time constant J / (k Kp) = 0.005 / 0.05 = 0.1 s


class VelocityP:
    """A proportional velocity controller as the controller node's interrupt handler."""

    def __init__(self) -> None:
        self.adc = Converter()
        self.dac = Converter()
        self.samplecount = 0
        self.missed = 0
        self.done = False
        self.shutdown_dac_counts = 0
        self._out = IsrOutput()

    def __call__(self, sample: AdcSample) -> IsrOutput:
        w = self.adc.to_volts(sample.tacho) * VOLT2RADPS
        T = self.adc.to_volts(sample.torque) * VOLT2NM
        volts = KP * (W_REF - w)
        out = self._out
        out.samplecount = self.samplecount
        out.dac_counts = self.dac.to_counts(volts)
        out.reference_V = volts
        out.T_meas = out.T_filtered = T
        out.velocity = w
        self.samplecount += 1
        return out

    def sample_missed(self) -> None:
        self.missed += 1


def velocity_p_controller(site: NodeSite, config: FirmwareConfig) -> ControllerNode:
    return ControllerNode(site.bus, config, node_id=site.node_id, isr=VelocityP())


def test_the_example_handler_is_an_interrupt_handler_model():
    assert isinstance(VelocityP(), InterruptHandlerModel)


def test_a_handler_of_ones_own_closes_the_loop_in_the_lockstep_runner():
    seen = FrameRecorder()
    r = lockstep(
        load_scenario("free-motion"),
        duration_s=1.0,
        evaluate=False,
        extra_listeners=[seen],
        controller_factory=velocity_p_controller,
        drive_factories=[rigid_drive],
    )
    assert r.cycles == 1000 and not r.interrupted
    telemetry = [v[2] for _, v in seen.decoded("control", "CTRL_TPDO1")]  # velocity
    truth = [v[2] for _, v in seen.decoded("truth", "TRUTH_MOTION")]  # omega_motor
    # 10 time constants: settled at the reference within the tachometer's resolution
    # (one ADC step is 10 V / 2048 * 56.3 rad/s per V = 0.27 rad/s; P control leaves no
    # error beyond the quantisation of the command and the reading)
    assert telemetry[-1] == pytest.approx(W_REF, abs=0.5)
    assert truth[-1] == pytest.approx(W_REF, abs=0.5)
    # after one time constant (0.1 s) it is near 1 - 1/e of the way
    assert telemetry[100] == pytest.approx(W_REF * (1 - 0.3679), rel=0.1)
    # the firmware-only parts are left out, the counters are there
    assert r.controller["sensor_frames"] >= 1000 and "filter_mode" not in r.controller


@pytest.mark.slow
@pytest.mark.realtime
def test_a_handler_of_ones_own_is_timed_as_a_whole_in_real_time_mode():
    r = lockstep(
        load_scenario("free-motion"),
        duration_s=0.05,
        evaluate=False,
        realtime=True,
        controller_factory=velocity_p_controller,
        drive_factories=[rigid_drive],
    )
    rt = r.realtime
    assert rt["interrupts"] >= 50 and rt["isr_us"]["p50"] > 0
    assert all(s["p50"] != s["p50"] for s in rt["stages_us"].values())  # NaN: no stages


def test_the_firmware_stage_parameters_refuse_writes_with_a_handler_of_ones_own():
    """The SDO objects that retune the firmware's stages have nothing to act on: refused
    (0x08000022), where the firmware's own handler accepts the same write."""
    from hdhil.firmware.parameters import PARAMETERS

    p = next(p for p in PARAMETERS if p.put is not None)
    value = p.get(FirmwareConfig())
    for isr, refused in ((VelocityP(), True), (None, False)):
        bus = can.Bus(interface="virtual", channel=f"hdhil-isr-params-{refused}")
        try:
            node = ControllerNode(bus, FirmwareConfig(), isr=isr)
            if refused:
                with pytest.raises(Exception, match=r"0x08000022|device state"):
                    node.services.write(p.index, p.sub, value)
            else:
                node.services.write(p.index, p.sub, value)
        finally:
            bus.shutdown()
