"""Fault injection: bus faults at the simbus channel, sensor faults at Plant.sample()."""

from __future__ import annotations

import itertools
import json
import math

import can
import pytest
from runs import lockstep

from hdhil.can.faults import FaultLog, node_ids
from hdhil.can.simbus import SimClock
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.faults import FaultConfig, FaultInjector
from hdhil.rig.scenario import scenario_from_dict

_names = itertools.count()


def _injector(seed: int = 0, log: FaultLog | None = None, **control: object) -> FaultInjector:
    return FaultInjector(from_dict(FaultConfig, {"seed": seed, "control": control}), log)


def _link(injector: FaultInjector, receivers: int = 1):
    clock = SimClock()
    name = f"t-faults-{next(_names)}"
    hook = injector.channel("control")
    tx = can.Bus(interface="simbus", channel=name, clock=clock, faults=hook)
    rx = [can.Bus(interface="simbus", channel=name) for _ in range(receivers)]
    return clock, tx, rx


def _drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(0)) is not None:
        out.append(m)
    return out


def _run(injector: FaultInjector, n: int = 4000, ids=(0x182,), receivers: int = 1):
    """Send ``n`` cycles of frames (one per ID each 1 ms, payload = cycle count)."""
    clock, tx, rx = _link(injector, receivers)
    got: list[list[can.Message]] = [[] for _ in rx]
    try:
        for k in range(n):
            clock.now = k * 1e-3
            for i in ids:
                tx.send(can.Message(arbitration_id=i, is_extended_id=False,
                                    data=k.to_bytes(4, "little")))  # fmt: skip
            for r, g in zip(rx, got, strict=True):
                g += _drain(r)
    finally:
        for b in (tx, *rx):
            b.shutdown()
    return got[0] if receivers == 1 else got


@pytest.mark.parametrize(
    ("key", "kind"),
    [
        ("loss_rate", "loss"),
        ("duplicate_rate", "duplicate"),
        ("reorder_rate", "reorder"),
        ("corrupt_rate", "corrupt"),
        ("dlc_rate", "wrong_dlc"),
        ("error_frame_rate", "error_frame"),
    ],
)
def test_each_rate_fault_happens_at_its_rate_and_is_logged(key, kind):
    inj = _injector(seed=5, **{key: 0.05})
    got = _run(inj, n=4000)
    count = inj.summary()[kind]
    assert 0.05 * 4000 * 0.8 < count < 0.05 * 4000 * 1.2
    assert len(inj.log.records) == count and set(inj.summary()) == {kind}
    assert all(r.kind == kind and r.channel == "control" and r.frame_id == 0x182
               for r in inj.log.records)  # fmt: skip
    frames = [m for m in got if not m.is_error_frame]
    if kind == "loss":
        assert len(frames) == 4000 - count
    elif kind == "duplicate":
        assert len(frames) == 4000 + count
        seqs = [bytes(m.data) for m in frames]
        assert sum(a == b for a, b in itertools.pairwise(seqs)) == count
    elif kind == "reorder":
        seqs = [int.from_bytes(m.data, "little") for m in frames]
        swaps = sum(b < a for a, b in itertools.pairwise(seqs))
        assert count - 1 <= swaps <= count  # the last held frame may still be waiting
        stamps = [m.timestamp for m in frames]
        assert stamps == sorted(stamps)
    elif kind == "corrupt":
        bad = [m for k, m in enumerate(frames) if bytes(m.data) != k.to_bytes(4, "little")]
        assert len(bad) == count
        for m in bad:
            k = round(m.timestamp * 1e3 - 0.5)
            diff = int.from_bytes(m.data, "little") ^ k
            assert bin(diff).count("1") == 1
    elif kind == "wrong_dlc":
        assert sum(len(m.data) != 4 for m in frames) == count
        assert all(m.dlc == len(m.data) for m in frames)
    elif kind == "error_frame":
        assert sum(m.is_error_frame for m in got) == count and len(frames) == 4000


def test_burst_loss_drops_bursts_of_the_configured_length():
    inj = _injector(burst_every_s=0.1, burst_len_frames=3)
    got = _run(inj, n=1000)
    assert inj.summary() == {"burst_loss": 27}  # bursts at 0.1 .. 0.9 s, 3 frames each
    seqs = {int.from_bytes(m.data, "little") for m in got}
    missing = sorted(set(range(1000)) - seqs)
    assert missing[:3] == [100, 101, 102] and len(missing) == 27


def test_delay_and_jitter_shift_the_delivery_time():
    clean = _run(_injector(), n=200)  # no faults configured: a clean link
    inj = _injector(delay_us=100.0, jitter_us=200.0)
    late = _run(inj, n=200)
    shifts = [b.timestamp - a.timestamp for a, b in zip(clean, late, strict=True)]
    assert all(100e-6 <= s <= 300e-6 for s in shifts)
    assert max(shifts) - min(shifts) > 150e-6
    assert inj.summary() == {"delay": 200}
    logged = [r.details["delay_us"] for r in inj.log.records]
    assert logged == pytest.approx([s * 1e6 for s in shifts])


def test_jitter_reorders_frames_of_one_cycle_by_timestamp():
    inj = _injector(seed=1, jitter_us=500.0)
    got = _run(inj, n=200, ids=(0x181, 0x182, 0x183))
    stamps = [m.timestamp for m in got]
    assert stamps == sorted(stamps)
    order = [m.arbitration_id for m in got]
    assert order != [0x181, 0x182, 0x183] * 200  # overtaking happened


def test_duplicates_reach_every_receiver():
    inj = _injector(duplicate_rate=0.1)
    a, b = _run(inj, n=500, receivers=2)
    assert [bytes(m.data) for m in a] == [bytes(m.data) for m in b]
    assert len(a) == 500 + inj.summary()["duplicate"]


def test_silence_drops_exactly_the_senders_frames_in_the_window():
    node2 = sorted(node_ids(2))
    # The per-node identifiers come from control.dbc: EMCY, TPDO1, TPDO2, SDO response and
    # heartbeat, the function codes both nodes of the DBC transmit.
    assert node2 == [0x082, 0x182, 0x282, 0x582, 0x702]
    inj = _injector(silence=[{"node": 2, "start_s": 0.1, "duration_s": 0.05},
                             {"ids": [0x80], "start_s": 0.3, "duration_s": 0.01}])  # fmt: skip
    got = _run(inj, n=400, ids=(0x080, 0x182, 0x282, 0x202))
    seen = {(m.arbitration_id, int.from_bytes(m.data, "little")) for m in got}
    expected = {
        (i, k)
        for k in range(400)
        for i in (0x080, 0x182, 0x282, 0x202)
        if not ((i in (0x182, 0x282) and 100 <= k < 150) or (i == 0x080 and 300 <= k < 310))
    }
    assert seen == expected
    assert inj.summary() == {"silence": 2 * 50 + 10}


def test_bus_off_drops_frames_until_recovery_and_frees_the_wire():
    inj = _injector(bus_off=[{"ids": [0x182], "start_s": 0.05, "duration_s": 0.02}])
    got = _run(inj, n=100, ids=(0x182, 0x183))
    ks = [int.from_bytes(m.data, "little") for m in got if m.arbitration_id == 0x182]
    assert ks == [k for k in range(100) if not 50 <= k < 70]
    assert inj.summary() == {"bus_off": 20}
    # A bus-off node's frames take no wire time: 0x183 goes first in the window.
    k60 = next(m for m in got if m.arbitration_id == 0x183 and m.data[0] == 60)
    k40 = next(m for m in got if m.arbitration_id == 0x183 and m.data[0] == 40)
    assert k60.timestamp - 0.060 < k40.timestamp - 0.040


def test_no_faults_means_no_hook_and_the_clean_path():
    inj = FaultInjector(FaultConfig())
    assert inj.channel("control") is None and inj.sensors() is None
    assert _run(inj, n=10) and inj.summary() == {}


def test_same_seed_same_faults_different_seed_different_faults():
    cfg = {"loss_rate": 0.05, "jitter_us": 200.0, "duplicate_rate": 0.02, "reorder_rate": 0.02,
           "corrupt_rate": 0.02, "dlc_rate": 0.02, "error_frame_rate": 0.02}  # fmt: skip

    def frames(seed: int):
        inj = _injector(seed=seed, **cfg)
        got = _run(inj, n=1000, ids=(0x181, 0x182))
        recs = [r.as_dict() for r in inj.log.records]
        return [(m.arbitration_id, bytes(m.data), m.timestamp, m.is_error_frame) for m in got], recs

    assert frames(3) == frames(3)
    assert frames(3) != frames(4)


def test_fault_log_writes_json_lines(tmp_path):
    path = tmp_path / "faults.jsonl"
    log = FaultLog(path)
    inj = _injector(log=log, loss_rate=0.1)
    _run(inj, n=200)
    log.close()
    lines = [json.loads(s) for s in path.read_text().splitlines()]
    assert len(lines) == inj.summary()["loss"] > 0
    assert set(lines[0]) == {"time", "channel", "kind", "frame_id", "details"}
    assert lines[0]["kind"] == "loss" and lines[0]["frame_id"] == 0x182


# ----------------------------------------------------------------------------- sensors
def _samples(sensors: dict | None, n: int = 300, seed: int = 0):
    inj = FaultInjector(from_dict(FaultConfig, {"seed": seed, "sensors": sensors or {}}))
    plant = Plant(PlantConfig(), seed=1, faults=inj.sensors())
    out = []
    for _ in range(n):
        plant.advance(1.0, 1e-3)
        out.append(plant.sample())
    return out, inj


def test_stuck_channel_holds_its_count_for_the_window():
    clean, _ = _samples(None)
    faulty, inj = _samples({"stuck": [{"channel": "encoder", "start_s": 0.1, "duration_s": 0.05}]})
    stuck = [k for k, (c, f) in enumerate(zip(clean, faulty, strict=True)) if f != c]
    times = [r.time for r in inj.log.records]
    n = len(times)  # 50 samples, 51 when float rounding puts the 150th on the edge
    assert all(0.1 <= t <= 0.15 + 1e-9 for t in times) and n in (50, 51)
    first = round(times[0] * 1e3) - 1  # sample k is taken at t = (k + 1) ms
    assert stuck and all(first <= k < first + n for k in stuck)
    assert all(faulty[k][3] == clean[first][3] and faulty[k][:3] == clean[k][:3]
               for k in range(first, first + n))  # fmt: skip
    assert inj.summary() == {"stuck": n}


def test_saturated_channel_reads_the_code_limit():
    clean, _ = _samples(None)
    faulty, inj = _samples({"saturated": [{"channel": "torque", "start_s": 0.2, "level": "min"}]})
    assert all(f[0] == -2048 for f in faulty[200:])
    assert faulty[:199] == clean[:199]
    assert inj.summary() == {"saturated": 101}


def test_encoder_glitches_and_tacho_spikes():
    clean, _ = _samples(None, n=2000)
    faulty, inj = _samples({"encoder_glitch_rate": 0.01, "encoder_glitch_counts": 40,
                            "tacho_spike_rate": 0.02, "tacho_spike_V": 1.0}, n=2000)  # fmt: skip
    s = inj.summary()
    assert 10 <= s["encoder_glitch"] <= 30 and 25 <= s["tacho_spike"] <= 55
    offsets = {(f[3] - c[3]) % 65536 for c, f in zip(clean, faulty, strict=True)}
    assert all(o % 40 == 0 or (65536 - o) % 40 == 0 for o in offsets) and len(offsets) > 1
    spikes = [abs(f[1] - c[1]) for c, f in zip(clean, faulty, strict=True) if f[1] != c[1]]
    assert len(spikes) == s["tacho_spike"] and all(d == 205 for d in spikes)  # 1 V / 4.88 mV
    assert (
        faulty
        == _samples(
            {
                "encoder_glitch_rate": 0.01,
                "encoder_glitch_counts": 40,
                "tacho_spike_rate": 0.02,
                "tacho_spike_V": 1.0,
            },
            n=2000,
        )[0]
    )


def test_the_sensor_faults_and_the_plant_import_nothing_of_can():
    """The plant and its sensor faults are physics: importing them loads neither python-can
    nor the project's CAN layers (also an import contract in pyproject.toml)."""
    import subprocess
    import sys

    code = (
        "import sys, hdhil.hostsim.sensor_faults, hdhil.hostsim.plant\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'can'"
        " or m.startswith(('hdhil.can', 'hdhil.canopen'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120).stdout  # fmt: skip
    assert out.strip() == "[]"


# ----------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"control": {"loss_rat": 0.1}}, "faults.control.loss_rat"),
        ({"control": {"loss_rate": 1.5}}, "loss_rate"),
        ({"control": {"loss_rate": "x"}}, "faults.control.loss_rate"),
        ({"control": {"jitter_us": -1.0}}, "jitter_us"),
        ({"control": {"burst_every_s": 0.1}}, "burst_len_frames"),
        ({"control": {"silence": [{"start_s": 0.1}]}}, "NodeWindow"),
        ({"sensors": {"stuck": [{"channel": "speed", "start_s": 0}]}}, "channel"),
        ({"sensors": {"saturated": [{"channel": "encoder", "start_s": 0}]}}, "saturated"),
        ({"seed": -1}, "seed"),
        ({"bus": {}}, "faults.bus"),
    ],
)
def test_config_errors_name_the_key(data, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        from_dict(FaultConfig, data, "faults")


def test_scenario_faults_table():
    base = {"scenario": {"name": "x", "duration_s": 1.0}}
    assert scenario_from_dict(base).faults is None
    scn = scenario_from_dict({**base, "faults": {"seed": 2, "control": {"loss_rate": 0.05}}})
    assert scn.faults is not None and scn.faults.control.loss_rate == 0.05
    assert scn.faults.seed == 2 and scn.faults.enabled
    with pytest.raises(ConfigError, match=r"faults\.control\.los"):
        scenario_from_dict({**base, "faults": {"control": {"los": 1}}})


def test_inf_duration_window_is_allowed():
    cfg = from_dict(FaultConfig, {"control": {"bus_off": [{"node": 1, "start_s": 1.0}]}})
    assert cfg.control.bus_off[0].duration_s == math.inf


# ----------------------------------------------------------------------------- lockstep
def _lockstep(monkeypatch, faults: dict | None, seed: int = 0):
    """``hdhil.rig.runner.run_lockstep`` on free-motion with ``faults`` on the control channel
    (attached by wrapping ``can.Bus`` until run_lockstep takes a faults argument)."""
    from hdhil.rig.scenario import load_scenario

    inj = FaultInjector(from_dict(FaultConfig, {"seed": seed, "control": faults or {}}))
    real_bus = can.Bus

    def bus(*args, **kwargs):
        if kwargs.get("interface") == "simbus" and str(kwargs.get("channel")).endswith("-control"):
            kwargs["faults"] = inj.channel("control")
        return real_bus(*args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(can, "Bus", bus)
        result = lockstep(load_scenario("free-motion"), evaluate=False)
    return result, inj


@pytest.mark.slow
def test_free_motion_with_5_percent_loss_and_200us_jitter(monkeypatch):
    clean, none = _lockstep(monkeypatch, None)
    assert none.summary() == {}
    lossy = {"loss_rate": 0.05, "jitter_us": 200.0}
    r, inj = _lockstep(monkeypatch, lossy, seed=0)
    s = inj.summary()
    assert s["loss"] > 300 and s["delay"] > 7000
    assert r.cycles == clean.cycles == 2000 and not r.interrupted
    ratio = r.torque["rms_error_filtered"] / clean.torque["rms_error_filtered"]
    assert ratio <= 1.5  # the issue's goal (1.02 with this seed)
    again, inj2 = _lockstep(monkeypatch, lossy, seed=0)
    assert again.torque == r.torque and inj2.summary() == s  # bit-identical
    assert [x.as_dict() for x in inj2.log.records] == [x.as_dict() for x in inj.log.records]


@pytest.mark.slow
def test_run_cli_injects_faults_from_an_override_and_logs_them(tmp_path, capsys):
    """hdhil run --override FILE with a [faults] table: faults act, are logged and counted."""
    import json

    from hdhil.cli import main

    faults = tmp_path / "lossy.toml"
    faults.write_text("[faults]\nseed = 3\n[faults.control]\nloss_rate = 0.05\njitter_us = 200.0\n")
    log = tmp_path / "faults.jsonl"
    args = ["run", "--duration", "0.5", "--trace", "", "--no-evaluate", "--json"]
    assert main([*args, "--override", str(faults), "--fault-log", str(log)]) == 0
    lossy = json.loads(capsys.readouterr().out)
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert lossy["faults"]["loss"] > 0 and lossy["faults"]["delay"] > 0
    assert len(records) == sum(lossy["faults"].values())
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["faults"] is None
