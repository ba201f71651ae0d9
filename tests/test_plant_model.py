"""A plant of one's own behind the drive node (:class:`hdhil.hostsim.plant_model.PlantModel`),
in the lockstep runner and in the one-node-per-process mode.

The example is the smallest plant that makes sense: a rigid inertia ``J`` driven by an
ideal amplifier (``k`` Nm per volt, no current lag, no friction), with a linear torque
sensor between motor and inertia, a tachometer and an encoder. Its physics: the torque
is ``k V`` and the velocity a ramp of slope ``k V / J`` while ``V`` is held. The tests
check that the run follows it: the truth channel's velocity grows with that slope in
simulated time, and the firmware's own readings (torque sensor, tachometer) agree.
"""

from __future__ import annotations

import itertools
import json
import math

import can
import pytest
from conftest import FrameRecorder
from runs import lockstep

from hdhil.cli import main
from hdhil.core.converter import Converter
from hdhil.dbc import CHANNEL_NUMBER, codec
from hdhil.firmware.config import FirmwareConfig
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant_model import PlantModel, SensorCounts, Truth
from hdhil.rig.factories import NodeSite
from hdhil.rig.scenario import load_scenario

FW = FirmwareConfig()
#: Sensor gains equal to what the firmware assumes (its calibration), so it reads truth.
VOLT2NM = FW.calibration.volt2Nm
VOLT2RADPS = FW.calibration.volt2radps
CPR = FW.calibration.encoder_counts_per_rev
#: The free-motion scenario's reference step (DAC volts; an exact 12-bit code).
STEP_V = 0.654296875


class RigidInertia:
    """A rigid inertia ``J_kgm2`` driven with ``k_Nm_per_V`` Nm per amplifier volt."""

    def __init__(self, J_kgm2: float = 0.005, k_Nm_per_V: float = 1.0) -> None:
        self.J = J_kgm2
        self.k = k_Nm_per_V
        self.adc = Converter()
        self.dac = Converter()
        self.max_motor_torque_Nm = 10.0 * k_Nm_per_V
        self.time = 0.0
        self.angle = 0.0
        self.omega = 0.0
        self.torque = 0.0
        self.volts_seen: set[float] = set()
        self.on_s = 0.0  # time with a non-zero amplifier input

    def advance(self, volts: float, dt: float) -> None:
        if volts:
            self.volts_seen.add(volts)
            self.on_s += dt
        self.torque = self.k * volts
        alpha = self.torque / self.J
        self.angle += self.omega * dt + 0.5 * alpha * dt * dt
        self.omega += alpha * dt
        self.time += dt

    def sample(self) -> tuple[int, int, int, int]:
        counts = self.adc.to_counts
        encoder = math.floor(self.angle / (2 * math.pi) * CPR) % 65536
        return counts(self.torque / VOLT2NM), counts(self.omega / VOLT2RADPS), 0, encoder

    def truth(self) -> Truth:
        """Motor and output are one rigid body; no ripple, no external torque."""
        return Truth(
            T_true_Nm=self.torque,
            theta_motor_rad=self.angle,
            theta_output_rad=self.angle,
            omega_motor_radps=self.omega,
            omega_output_radps=self.omega,
            tau_m_Nm=self.torque,
            tau_m_cmd_Nm=self.torque,
        )


def rigid_drive(site: NodeSite) -> DriveNode:
    """The drive factory of the example in docs/extending.md."""
    return DriveNode(site.bus, RigidInertia(), site.drive_config(), truth_bus=site.truth_bus)


def test_the_example_plant_is_a_plant_model():
    assert isinstance(RigidInertia(), PlantModel)


def test_a_rigid_inertia_runs_in_the_lockstep_runner_as_its_physics_says():
    frames = FrameRecorder()
    r = lockstep(
        load_scenario("free-motion"),
        duration_s=0.5,
        seed=1,
        evaluate=False,
        extra_listeners=[frames],
        drive_factories=[rigid_drive],
    )
    assert r.cycles == 500 and not r.interrupted
    slope = 1.0 * STEP_V / 0.005  # k V / J, rad/s^2
    # The ramp: truth velocity against simulated time, after the step was applied.
    truth = [(t, v[2]) for t, v in frames.decoded("truth", "TRUTH_MOTION")]  # omega_motor
    ramp = [b for a, b in itertools.pairwise(truth) if b[1] > a[1] > 1.0]
    assert len(ramp) > 300
    (t0, w0), (t1, w1) = ramp[0], ramp[-1]
    assert (w1 - w0) / (t1 - t0) == pytest.approx(slope, rel=2e-3)
    assert w1 > 50  # it moved: about 58 rad/s after 0.45 s
    # The firmware reads it through its own sensors: torque k V, the velocity on the ramp.
    _, (T_meas, _filtered, velocity, _current) = frames.decoded("control", "CTRL_TPDO1")[-1]
    assert T_meas == pytest.approx(STEP_V, abs=VOLT2NM * 10 / 2048)  # one ADC step
    assert velocity == pytest.approx(w1, abs=VOLT2RADPS * 10 / 2048 + slope * 2e-3)
    assert r.velocity_final == pytest.approx(velocity, abs=0.01)


def _protocol_example() -> type:
    """The plant of :class:`PlantModel`'s docstring, built from the docstring as it stands."""
    import textwrap

    doc = PlantModel.__doc__ or ""
    code = textwrap.dedent(doc[doc.index("class RigidInertia:") - 8 :])
    namespace = {"math": math, "Converter": Converter, "SensorCounts": SensorCounts,
                 "Truth": Truth}  # fmt: skip
    exec(code, namespace)
    return namespace["RigidInertia"]


class _TruthFrames(can.Listener):
    """The truth channel, decoded: (time, T_true, omega_motor, tau_m) per SYNC."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float, float]] = []
        self._torque = codec("truth", "TRUTH_TORQUE")
        self._motion = codec("truth", "TRUTH_MOTION")
        self._joint = codec("truth", "TRUTH_JOINT")
        self._row: dict[str, float] = {}

    def on_message_received(self, msg: can.Message) -> None:
        if msg.channel != CHANNEL_NUMBER["truth"]:
            return
        if msg.arbitration_id == self._torque.frame_id:
            self._row = {"T": self._torque.decode(msg.data)[0]}
        elif msg.arbitration_id == self._motion.frame_id:
            self._row["w"] = self._motion.decode(msg.data)[2]
        elif msg.arbitration_id == self._joint.frame_id:
            tau_ext, tau_d, tau_m, _cmd = self._joint.decode(msg.data)
            assert tau_ext == tau_d == 0.0  # the defaults of a plant without them
            row = self._row
            self.rows.append((msg.timestamp, row["T"], row["w"], tau_m))


def test_the_protocols_own_example_is_a_short_plant_the_drive_runs():
    """The user plant in :class:`PlantModel`'s docstring is about 15 lines, is a
    ``PlantModel``, and behind a drive in the lockstep runner it follows its physics:
    the truth channel carries its torque ``k V`` and its velocity ramp ``k V / J``."""
    plant_cls = _protocol_example()
    doc = PlantModel.__doc__ or ""
    body = doc[doc.index("class RigidInertia:") :].splitlines()
    assert len([line for line in body if line.strip()]) <= 18
    plant = plant_cls()
    assert isinstance(plant, PlantModel)
    frames = _TruthFrames()
    r = lockstep(
        load_scenario("free-motion"),
        duration_s=0.5,
        seed=1,
        evaluate=False,
        extra_listeners=[frames],
        drive_factories=[
            lambda site: DriveNode(site.bus, plant, site.drive_config(), truth_bus=site.truth_bus)
        ],
    )
    assert r.cycles == 500 and not r.interrupted
    on = [row for row in frames.rows if row[1] > 0.0]
    assert len(on) > 400
    torque = plant.k * STEP_V
    # each at the truth channel's resolution (truth.dbc: 1 uNm and 5 mNm)
    assert all(abs(T - torque) <= 1e-6 and abs(tau_m - torque) <= 2.5e-3 for _, T, _, tau_m in on)
    (t0, _, w0, _), (t1, _, w1, _) = on[1], on[-1]
    assert (w1 - w0) / (t1 - t0) == pytest.approx(torque / plant.J, rel=2e-3)
    assert plant.omega == pytest.approx(w1, rel=1e-3)


def test_other_plants_refuse_the_emulators_own_knobs():
    """0x2300 (ripple, noise, load) acts on the emulator's own plant only: an SDO write
    to a drive around another plant is refused, not silently ignored."""
    bus = can.Bus(interface="virtual", channel="hdhil-plant-model-knobs")
    try:
        drive = DriveNode(bus, RigidInertia(), DriveConfig())
        with pytest.raises(Exception, match=r"0x08000022|device state"):
            drive.services.write(0x2300, 6, 1.0)
    finally:
        bus.shutdown()


@pytest.mark.realtime
def test_a_rigid_inertia_served_alone_follows_the_firmware_in_its_own_loop(serve_drive, capsys):
    """One node per process: the drive with the example plant served in the node loop of
    ``hdhil emulate``, the firmware command in this process over a virtual bus."""
    plants: list[RigidInertia] = []

    def make(bus: can.BusABC) -> DriveNode:
        plants.append(RigidInertia())
        return DriveNode(bus, plants[0], DriveConfig())

    drive, bus_args = serve_drive(make)
    code = main(
        ["firmware", *bus_args, "--lockstep", "--scenario", "free-motion", "--duration", "0.3"]
    )
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and out["operational_cycles"] == 300
    plant = plants[0]
    # The firmware's step (from sample 50 of 300) reached the plant as the one voltage it
    # commands, for every cycle from then to the stop: no cycle lost or doubled.
    assert plant.volts_seen == {STEP_V}
    assert plant.on_s == pytest.approx(0.25, abs=2.5e-3)
    assert plant.omega == pytest.approx(plant.k * STEP_V / plant.J * plant.on_s, rel=1e-9)
    assert drive.diagnostics.syncs > 300


@pytest.mark.slow
def test_the_emulators_plant_computes_its_step_map_when_the_drive_is_built():
    """The emulator's step map (and the scipy.linalg import it needs) is ready before the
    node loop starts: a cycle in a real-time or network run must not stall on it."""
    from hdhil.hostsim.plant import Plant

    bus = can.Bus(interface="virtual", channel="hdhil-plant-prepare")
    try:
        plant = Plant(load_scenario("free-motion").plant)
        assert 1e-3 not in plant._maps
        DriveNode(bus, plant, DriveConfig(sample_period_s=1e-3))
        assert 1e-3 in plant._maps
    finally:
        bus.shutdown()


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_readme_example_runs_and_prints_what_the_readme_says():
    """The plug-in example of docs/extending.md (section "Example: a rigid inertia", which
    the README's "Your own plant or controller" points to), run as it stands in a fresh
    interpreter."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    page = (Path(__file__).parent.parent / "docs" / "extending.md").read_text(encoding="utf-8")
    section = page[page.index("## Example: a rigid inertia") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    claimed = re.search(r"It prints `([^`]*)`", section).group(1)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True).stdout  # fmt: skip
    assert out.strip() == claimed


@pytest.mark.slow
@pytest.mark.realtime
def test_firmware_realtime_paces_with_the_run_pacer_and_reports_its_statistics(serve_drive, capsys):
    """``hdhil firmware`` (real time by default) against a served drive: SYNC paced by the
    pacer of ``hdhil run --realtime``, its statistics in the summary line, covering the
    cycles in operation, each cycle no shorter than the period."""
    import time

    drive, bus_args = serve_drive(lambda bus: DriveNode(bus, RigidInertia(), DriveConfig()))
    t0 = time.monotonic()
    code = main(["firmware", *bus_args, "--scenario", "free-motion", "--duration", "0.2"])
    wall = time.monotonic() - t0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and out["operational_cycles"] == 200 and out["phase"] == "stopped"
    rt = out["realtime"]
    assert 199 <= rt["cycles"] <= 201 and rt["sample_period_s"] == pytest.approx(1e-3)
    # a sensor frame that comes after the next deadline is a miss, handled a cycle late
    assert 0 < rt["interrupts"] <= rt["cycles"]
    assert 0 <= rt["deadline_misses"] <= rt["cycles"]
    assert rt["applied"] or rt["refused"]  # the process settings were tried
    assert wall >= 0.2  # paced: 200 cycles of 1 ms take at least 0.2 s
    assert drive.diagnostics.syncs >= 200
