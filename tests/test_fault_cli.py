"""Faults from the command line (``--fault KEY=VALUE``) and through the drive's object
0x2310 "Fault injection" (SDO), and a node faulting its own transmissions.

The SDO tests run in lockstep on ``simbus``: a host bus plays the SDO client (and, without
a controller, the SYNC producer and NMT master), one cycle at a time as ``hdhil run`` does.
"""

from __future__ import annotations

import json
import math
import struct
import time

import can
import pytest
from conftest import BusHarness

from hdhil.can.faults import FaultLog, FaultyTransmitBus
from hdhil.cli import main
from hdhil.commands import run as run_module
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.dbc import codec
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.faults import FaultConfig, FaultInjector, parse_fault_flags, with_fault_flags
from hdhil.rig.scenario import load_scenario

TS = 1e-3
SENSOR = codec("control", "DRIVE_TPDO1")
SDO_RX, SDO_TX = 0x602, 0x582


# ============================================================================ flags


def test_flags_parse_into_the_faults_table_later_flags_winning():
    table = parse_fault_flags(
        [
            "control.loss_rate=0.05",
            "control.jitter_us=200",
            "sensors.tacho_spike_rate=0.001",
            "seed=3",
            "control.silence=[{node=2,start_s=1,duration_s=0.5}]",
            "control.loss_rate=0.02",
            'sensors.saturated=[{channel="torque", start_s=0.5, level="min"}]',
        ]
    )
    assert table == {
        "control": {
            "loss_rate": 0.02,
            "jitter_us": 200,
            "silence": [{"node": 2, "start_s": 1, "duration_s": 0.5}],
        },
        "sensors": {
            "tacho_spike_rate": 0.001,
            "saturated": [{"channel": "torque", "start_s": 0.5, "level": "min"}],
        },
        "seed": 3,
    }
    cfg = with_fault_flags(None, ["control.silence=[{node=2,start_s=1,duration_s=0.5}]"])
    assert cfg is not None and cfg.control.silence[0].cob_ids >= {0x182, 0x702}


def test_flags_merge_over_the_scenario_table_the_flag_wins():
    scenario = from_dict(
        FaultConfig,
        {"seed": 7, "control": {"loss_rate": 0.1, "delay_us": 50.0},
         "sensors": {"stuck": [{"channel": "tacho", "start_s": 0.2}]}},
    )  # fmt: skip
    cfg = with_fault_flags(
        scenario,
        ["control.loss_rate=0.02", "truth.loss_rate=0.5",
         'sensors.stuck=[{channel="encoder", start_s=1}]'],
    )  # fmt: skip
    assert cfg is not None
    assert (cfg.seed, cfg.control.loss_rate, cfg.control.delay_us) == (7, 0.02, 50.0)
    assert cfg.truth.loss_rate == 0.5
    assert [w.channel for w in cfg.sensors.stuck] == ["encoder"]  # a list is replaced
    assert with_fault_flags(scenario, []) is scenario
    # Keys that only make sense together may come one from each side.
    burst = from_dict(FaultConfig, {"control": {"burst_every_s": 0.1, "burst_len_frames": 2}})
    merged = with_fault_flags(burst, ["control.burst_len_frames=5"])
    assert merged is not None and merged.control.burst_len_frames == 5


def _captured_scenario(monkeypatch, args: list[str]):
    """The scenario ``hdhil run ARGS`` would run (run_lockstep replaced by a probe)."""
    seen = []

    class Probe(Exception):
        pass

    def probe(request, *a, **k):
        seen.append(request.scenario)
        raise Probe

    monkeypatch.setattr(run_module, "run_lockstep", probe)
    with pytest.raises(Probe):
        main(["run", *args])
    return seen[0]


def test_run_merges_flags_over_the_scenario_and_override_files(monkeypatch, tmp_path):
    override = tmp_path / "faults.toml"
    override.write_text(
        "[faults]\nseed = 4\n[faults.control]\nloss_rate = 0.1\njitter_us = 100.0\n"
    )
    base = _captured_scenario(monkeypatch, ["--override", str(override)])
    assert (base.faults.seed, base.faults.control.loss_rate) == (4, 0.1)
    scn = _captured_scenario(
        monkeypatch,
        ["--override", str(override), "--fault", "control.loss_rate=0.02",
         "--fault", "sensors.encoder_glitch_rate=0.01",
         "--fault", "sensors.encoder_glitch_counts=8"],
    )  # fmt: skip
    f = scn.faults
    assert (f.seed, f.control.loss_rate, f.control.jitter_us) == (4, 0.02, 100.0)
    assert (f.sensors.encoder_glitch_rate, f.sensors.encoder_glitch_counts) == (0.01, 8)
    assert scn.plant == base.plant and scn.firmware == base.firmware
    # No [faults] anywhere: the flags make the table.
    only = _captured_scenario(monkeypatch, ["--fault", "seed=9"])
    assert only.faults == FaultConfig(seed=9)
    assert _captured_scenario(monkeypatch, []).faults is None


@pytest.mark.parametrize(
    ("command", "flag", "expected"),
    [
        ("run", "control.loss_rat=0.1", "unknown key faults.control.loss_rat"),
        ("run", "control.loss_rate=1.5", "BusFaults.loss_rate must be a probability"),
        ("run", "control.loss_rate=true", "faults.control.loss_rate: expected a number"),
        ("run", "control.burst_len_frames=0.5", "faults.control.burst_len_frames"),
        ("run", "control.jitter_us=-1", "BusFaults.jitter_us must be >= 0"),
        ("run", "control.loss_rate=abc", "control.loss_rate: 'abc' is not a TOML value"),
        ("run", "control.loss_rate", "expected KEY=VALUE"),
        ("run", "sensors.stuck=[{channel='speed', start_s=0}]", "stuck[0].channel: must be one"),
        ("run", "seed=-2", "FaultConfig.seed must be an integer >= 0"),
        ("run", "control.burst_every_s=0.1", "burst_len_frames and burst_every_s go together"),
        ("emulate", "sensors.tacho_spike_rate=2", "SensorFaults.tacho_spike_rate"),
        ("emulate", "truth.loss_rate=0.1", "--fault truth.*: these faults do not act"),
        ("firmware", "sensors.tacho_spike_rate=0.1", "--fault sensors.*: these faults do not"),
        ("firmware", "control.error_frame_rate=0.1", "cannot transmit error frames"),
    ],
)
def test_bad_flags_exit_2_with_one_line_naming_the_key(capsys, command, flag, expected):
    assert main([command, "--fault", flag, "--interface", "virtual"]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert expected in err, err
    assert err.startswith("hdhil: error:") and len(err.splitlines()) == 1
    assert "Traceback" not in err and captured.out == ""


@pytest.mark.slow
def test_the_same_faults_by_flag_as_by_toml_table_give_the_same_fault_log(tmp_path, capsys):
    table = tmp_path / "faults.toml"
    table.write_text(
        "[faults]\nseed = 3\n"
        "[faults.control]\nloss_rate = 0.05\njitter_us = 200.0\n"
        "silence = [{ node = 2, start_s = 0.2, duration_s = 0.004 }]\n"
        "[faults.sensors]\ntacho_spike_rate = 0.02\ntacho_spike_V = 0.5\n"
    )
    flags = ["seed=3", "control.loss_rate=0.05", "control.jitter_us=200",
             "control.silence=[{node=2,start_s=0.2,duration_s=0.004}]",
             "sensors.tacho_spike_rate=0.02", "sensors.tacho_spike_V=0.5"]  # fmt: skip
    args = ["run", "--duration", "0.4", "--trace", "", "--no-evaluate", "--json"]
    by_toml, by_flag = tmp_path / "toml.jsonl", tmp_path / "flag.jsonl"
    assert main([*args, "--override", str(table), "--fault-log", str(by_toml)]) == 0
    toml_result = json.loads(capsys.readouterr().out)
    fault_args = [a for f in flags for a in ("--fault", f)]
    assert main([*args, *fault_args, "--fault-log", str(by_flag)]) == 0
    flag_result = json.loads(capsys.readouterr().out)
    assert by_toml.read_bytes() == by_flag.read_bytes()
    records = [json.loads(line) for line in by_flag.read_text().splitlines()]
    kinds = {r["kind"] for r in records}
    assert {"loss", "delay", "silence", "tacho_spike"} <= kinds
    assert flag_result["faults"] == toml_result["faults"]
    assert sum(flag_result["faults"].values()) == len(records)
    assert flag_result["torque"] == toml_result["torque"]
    # A different seed by flag gives other faults.
    other = tmp_path / "other.jsonl"
    assert main([*args, *fault_args, "--fault", "seed=4", "--fault-log", str(other)]) == 0
    capsys.readouterr()
    assert other.read_bytes() != by_flag.read_bytes()


# ============================================================================ SDO 0x2310


class Bench(BusHarness):
    """The drive (and optionally the controller, which then sends SYNC) in lockstep on
    the shared bus harness, whose host plays the SDO client.

    Without a controller the host starts the drive (NMT) and produces SYNC; the drive then
    samples and sends its sensor frame every cycle, its torque off (SWITCH ON DISABLED).
    """

    def __init__(self, controller: bool = False, log: FaultLog | None = None) -> None:
        super().__init__("t-fault-cli")
        ctrl_bus, drive_bus = self.bus(), self.bus()
        self.injector = FaultInjector(FaultConfig(seed=5), log)
        self.plant = Plant(PlantConfig(), seed=1, faults=self.injector.sensors())
        self.drive = self.add(DriveNode(drive_bus, self.plant, DriveConfig(),
                                        faults=self.injector))  # fmt: skip
        self.controller = (
            self.add(ControllerNode(ctrl_bus, FirmwareConfig()), sync=True) if controller else None
        )
        self.drive.boot(0.0)
        if self.controller is not None:
            self.controller.boot(0.0)
        else:
            self.send(0x000, bytes((0x01, 2)))  # NMT start node 2
        self.pump()

    @property
    def samples(self) -> list[tuple[int, int, int, int]]:
        """The sensor frames the host saw, decoded."""
        return [SENSOR.decode(m.data) for m in self.recorder.with_id(SENSOR.frame_id)]

    def sdo_write(self, sub: int, data: bytes, index: int = 0x2310) -> int | None:
        """Expedited download to the drive; the abort code or None."""
        self.send(SDO_RX, struct.pack("<BHB", 0x23 | (4 - len(data)) << 2, index, sub)
                   + data.ljust(4, b"\0"))  # fmt: skip
        (response,) = [d for i, d in self.pump() if i == SDO_TX]
        if response[0] == 0x80:
            return struct.unpack_from("<I", response, 4)[0]
        assert response[0] == 0x60
        return None

    def sdo_read(self, sub: int, index: int = 0x2310) -> bytes:
        self.send(SDO_RX, struct.pack("<BHB4x", 0x40, index, sub))
        (response,) = [d for i, d in self.pump() if i == SDO_TX]
        assert response[0] & 0xE0 == 0x40, response.hex()
        return response[4 : 8 - ((response[0] >> 2) & 3)]


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def f32(x: float) -> bytes:
    return struct.pack("<f", x)


def test_fault_free_drive_has_no_sensor_hook(bench):
    assert bench.plant.faults is None
    assert bench.sdo_read(1) == f32(0.0) and bench.sdo_read(5) == b"\x00"
    bench.sdo_write(1, f32(0.5))
    bench.cycle()
    assert bench.plant.faults is not None
    bench.sdo_write(1, f32(0.0))
    bench.cycle()
    assert bench.plant.faults is None  # switched off: the plant's fault-free path again


@pytest.mark.slow
def test_tacho_spikes_switched_on_by_sdo_are_injected_logged_and_reproducible():
    def run(write_at: int | None) -> tuple[list, dict, list]:
        b = Bench()
        try:
            for k in range(120):
                if k == write_at:
                    assert b.sdo_write(1, f32(0.25)) is None  # rate
                    assert b.sdo_write(2, f32(1.0)) is None  # 1 V
                b.cycle()
            return b.samples, b.injector.summary(), [r.time for r in b.injector.log.records]
        finally:
            b.close()

    clean, none, _ = run(None)
    faulty, counts, times = run(40)
    assert none == {} and set(counts) == {"tacho_spike"}
    assert 10 <= counts["tacho_spike"] <= 35  # 0.25 x 80 samples
    diffs = [(k, f[1] - c[1]) for k, (c, f) in enumerate(zip(clean, faulty, strict=True))
             if f != c]  # fmt: skip
    assert len(diffs) == counts["tacho_spike"]  # every spike is logged, nothing unlogged
    assert all(abs(d) == 205 for _, d in diffs)  # 1 V / 4.88 mV per count
    assert min(k for k, _ in diffs) >= 40 and min(times) >= 40 * TS
    again, counts_again, times_again = run(40)
    assert (again, counts_again, times_again) == (faulty, counts, times)  # seeded


def test_stuck_and_saturated_channel_masks(bench):
    for _ in range(5):
        bench.cycle()
    assert bench.sdo_write(5, b"\x01") is None  # torque stuck
    for _ in range(30):
        bench.cycle()
    torque = [s[0] for s in bench.samples[-30:]]
    assert len(set(torque)) == 1
    assert bench.injector.summary()["stuck"] == 30
    assert bench.sdo_write(5, b"\x00") is None
    assert bench.sdo_write(7, b"\x02") is None  # tacho at its bottom code
    frames = []
    for _ in range(30):
        frames += bench.cycle()
    assert len({s[0] for s in bench.samples[-30:]}) > 1  # noise again
    assert all(s[1] == -2048 for s in bench.samples[-30:])
    assert bench.injector.summary()["saturated"] == 30
    emcy = [struct.unpack("<HB5s", d) for i, d in frames if i == 0x082]
    assert [e[2][0] for e in emcy if e[0] == 0x7300] == [2]  # EMCY "sensor": the tacho


@pytest.mark.parametrize(
    ("sub", "data", "code"),
    [
        (1, f32(1.5), 0x06090031),  # a rate above 1
        (3, f32(-0.1), 0x06090032),
        (1, f32(math.nan), 0x06090030),
        (2, f32(25.0), 0x06090031),  # more than the ADC's 20 V span
        (5, b"\x10", 0x06090031),  # no fifth channel
        (6, b"\x08", 0x06090031),  # the encoder has no code limit
        (8, b"\x00\x00\x01", 0x06070012),  # UNSIGNED16 written with 3 bytes
        (0, b"\x03", 0x06010002),  # highest sub-index is const
    ],
)
def test_bad_writes_are_refused_and_change_nothing(bench, sub, data, code):
    bench.cycle()
    before = [bench.sdo_read(s) for s in range(1, 9)]
    assert bench.sdo_write(sub, data) == code
    for _ in range(3):
        bench.cycle()
    assert [bench.sdo_read(s) for s in range(1, 9)] == before
    assert bench.plant.faults is None and bench.injector.summary() == {}


def test_a_channel_saturates_at_one_end_only(bench):
    assert bench.sdo_write(6, b"\x05") is None  # torque and current at the top
    assert bench.sdo_write(7, b"\x04") == 0x06090030  # current also at the bottom: refused
    assert bench.sdo_write(7, b"\x02") is None
    assert bench.sdo_read(7) == b"\x02"
    bench.cycle()
    bench.cycle()
    assert bench.samples[-1][:3] == (2047, -2048, 2047)


def test_nmt_reset_node_restores_the_power_on_faults(bench):
    bench.sdo_write(3, f32(0.5))
    bench.sdo_write(4, struct.pack("<H", 16))
    bench.sdo_write(8, struct.pack("<H", 500))
    bench.cycle()
    assert bench.drive.silent and bench.plant.faults is not None
    bench.send(0x000, bytes((0x81, 2)))  # NMT reset node
    assert (0x702, b"\x00") in bench.pump()  # the boot-up is not silenced
    assert not bench.drive.silent
    assert bench.sdo_read(3) == f32(0.0) and bench.sdo_read(8) == b"\x00\x00"
    bench.cycle()
    assert bench.plant.faults is None


def test_power_on_values_come_from_the_scenario_sensor_faults():
    inj = FaultInjector(from_dict(FaultConfig, {"sensors": {"tacho_spike_rate": 0.125,
                                                            "tacho_spike_V": 2.0}}))  # fmt: skip
    with BusHarness("t-fault-cli") as harness:
        plant = Plant(PlantConfig(), 1, faults=inj.sensors())
        drive = DriveNode(harness.bus(), plant, DriveConfig(), faults=inj)
        assert drive.services.read(0x2310, 1) == 0.125
        assert drive.services.read(0x2310, 2) == 2.0
        assert plant.faults is inj.sensors()


@pytest.mark.slow
def test_drive_silence_puts_the_controller_in_its_safe_state_within_the_hold():
    b = Bench(controller=True)
    try:
        ctrl = b.controller
        assert ctrl is not None
        while ctrl.phase != "operational" and b.k < 100:
            b.cycle()
        for _ in range(20):
            b.cycle()
        assert ctrl.phase == "operational"
        hold = ctrl.sensor_hold_cycles
        assert b.sdo_write(8, struct.pack("<H", 200)) is None  # answered before the silence
        start = b.k
        drive_frames = 0
        while ctrl.phase == "operational" and b.k < start + 50:
            drive_frames += sum(i & 0x7F == 2 for i, _ in b.cycle())
        cycles = b.k - start
        assert ctrl.phase == "safe"
        assert hold <= cycles <= hold + 3, cycles
        assert drive_frames == 0  # the drive sent nothing at all
        silenced = [r for r in b.injector.log.records if r.kind == "silence"]
        assert {r.frame_id for r in silenced} >= {0x182}
        assert all(r.channel == "control" and r.time >= start * TS for r in silenced)
        # Every sensor frame the drive sent is on the bus or in the fault log.
        lost = sum(r.frame_id == SENSOR.frame_id for r in silenced)
        assert b.drive.diagnostics.sensor_frames == len(b.samples) + lost
    finally:
        b.close()


def test_silence_ends_after_its_time_and_the_drive_transmits_again(bench):
    for _ in range(3):
        bench.cycle()
    assert bench.sdo_write(8, struct.pack("<H", 5)) is None
    seen = [any(i == SENSOR.frame_id for i, _ in bench.cycle()) for _ in range(10)]
    assert seen == [False] * 5 + [True] * 5
    assert bench.injector.summary() == {"silence": 5}
    assert not bench.drive.silent and "send" not in vars(bench.drive.bus)  # plain send again
    assert bench.sdo_read(8) == struct.pack("<H", 5)  # reads back the written duration


def test_sdo_fault_log_goes_to_the_run_log_file(tmp_path):
    path = tmp_path / "faults.jsonl"
    b = Bench(log=FaultLog(path))
    try:
        b.sdo_write(6, b"\x01")
        for _ in range(4):
            b.cycle()
    finally:
        b.injector.log.close()
        b.close()
    lines = [json.loads(s) for s in path.read_text().splitlines()]
    assert [x["kind"] for x in lines] == ["saturated"] * 4
    assert {x["details"]["sensor"] for x in lines} == {"torque"}


# ============================================================================ processes


@pytest.fixture
def served_drive(serve_drive):
    """A drive served in real time on python-can's virtual bus (as ``hdhil emulate``)."""
    plant = Plant(load_scenario("free-motion").plant, 1)
    return serve_drive(
        lambda bus: DriveNode(bus, plant, DriveConfig(), faults=FaultInjector(FaultConfig()))
    )


@pytest.mark.realtime
def test_hdhil_sdo_writes_the_fault_object(served_drive, capsys):
    node, bus = served_drive
    assert main(["sdo", "write", "2", "0x2310:1", "0.01", *bus]) == 0
    assert main(["sdo", "read", "2", "0x2310:1", *bus]) == 0
    assert float(capsys.readouterr().out.split()[-1]) == pytest.approx(0.01)
    assert main(["sdo", "write", "2", "0x2310:1", "2", *bus]) == 2
    err = capsys.readouterr().err.strip()
    assert "0x06090031" in err and len(err.splitlines()) == 1
    assert main(["sdo", "write", "2", "0x2310:6", "8", *bus]) == 2
    assert "0x06090031" in capsys.readouterr().err
    assert node.services.read(0x2310, 6) == 0


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _transmit_rig(faults: dict, ids=(0x182,), n: int = 400):
    """A node's bus on ``virtual`` through FaultyTransmitBus; n cycles of 1 ms, one frame
    per ID each; returns (received frames with their send cycle, injector)."""
    channel = f"hdhil-tx-{time.monotonic_ns()}"
    raw, peer = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    inj = FaultInjector(from_dict(FaultConfig, {"seed": 2, "control": faults}), stream="drive")
    clock = FakeClock()
    node_bus = FaultyTransmitBus(raw, inj.channel("control"), clock)
    got = []
    try:
        for k in range(n):
            clock.now = k * 1e-3 + 1e-4  # a frame 100 us into its cycle
            for i in ids:
                node_bus.send(can.Message(arbitration_id=i, is_extended_id=False,
                                          data=k.to_bytes(4, "little")))  # fmt: skip
            assert node_bus.recv(0) is None  # nothing else on the channel
            while (msg := peer.recv(0)) is not None:
                got.append((k, msg.arbitration_id, int.from_bytes(msg.data, "little")))
        clock.now = n * 1e-3
        node_bus.flush()
        while (msg := peer.recv(0.01)) is not None:
            got.append((n, msg.arbitration_id, int.from_bytes(msg.data, "little")))
    finally:
        raw.shutdown()
        peer.shutdown()
    return got, inj


def test_a_node_loses_and_delays_its_own_frames():
    got, inj = _transmit_rig({"loss_rate": 0.1})
    lost = inj.summary()["loss"]
    assert 20 <= lost <= 60 and len(got) == 400 - lost
    assert sorted({k for k in range(400)} - {v for _, _, v in got}) == sorted(
        round(r.time * 1e3) for r in inj.log.records
    )
    got, inj = _transmit_rig({"delay_us": 2500.0})
    assert all(k - v == 3 for k, _, v in got if k < 400)  # sent 2.5 ms late: 3 cycles on
    assert [v for _, _, v in got] == list(range(400)) and inj.summary() == {"delay": 400}


def test_a_node_silence_window_and_its_stream_seed():
    got, inj = _transmit_rig(
        {"silence": [{"node": 2, "start_s": 0.1, "duration_s": 0.05}]}, ids=(0x182, 0x201)
    )
    missing = {(i, v) for i in (0x182, 0x201) for v in range(400)} - {(i, v) for _, i, v in got}
    assert missing == {(0x182, v) for v in range(100, 150)}
    assert inj.summary() == {"silence": 50}
    # The node's own stream: other draws than the simulated bus's channel with that seed.
    a, _ = _transmit_rig({"loss_rate": 0.1})
    lockstep = FaultInjector(from_dict(FaultConfig, {"seed": 2, "control": {"loss_rate": 0.1}}))
    hook = lockstep.channel("control")
    assert hook is not None
    drops = [not hook.transmit(can.Message(arbitration_id=0x182, data=b"\0"), k * 1e-3, 0)[0]
             for k in range(400)]  # fmt: skip
    assert {v for _, _, v in a} != {k for k in range(400) if not drops[k]}


@pytest.mark.slow
@pytest.mark.realtime
def test_emulate_with_a_fault_flag_faults_its_own_frames_and_logs_them(tmp_path, capsys):
    channel = f"hdhil-emu-{time.monotonic_ns()}"
    listener = can.Bus(interface="virtual", channel=channel)
    log = tmp_path / "emu.jsonl"
    args = ["emulate", "--interface", "virtual", "--channel", channel, "--duration", "0.35"]
    try:
        assert main([*args, "--fault", "control.loss_rate=1", "--fault-log", str(log)]) == 0
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert listener.recv(0.05) is None  # boot-up and heartbeats all lost
        records = [json.loads(s) for s in log.read_text().splitlines()]
        assert summary["faults"] == {"loss": len(records)} and len(records) >= 4
        assert {r["frame_id"] for r in records} == {0x702}
        assert main(args) == 0
        assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["faults"] == {}
        assert listener.recv(0.05).arbitration_id == 0x702  # without the flag: boot-up
    finally:
        listener.shutdown()


def test_config_error_type():
    with pytest.raises(ConfigError, match="more than one TOML value"):
        parse_fault_flags(["seed=1\nx=2"])
