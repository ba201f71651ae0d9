"""A drive and the controller at any CANopen node-ID: PDO COB-IDs from the node-ID (the
EDS's ``$NODEID+0x180``, CiA 301 pre-defined connection set), the run at the layout's
node-IDs, its trace decoded by name, a stock canopen master finding a served drive at
node-ID 5, and the command-line options' refusals."""

from __future__ import annotations

import math
import time

import can
import canopen
import cantools
import pytest

from hdhil.canopen.cia402 import State, state_from_statusword
from hdhil.dbc import eds_path
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.factories import DriveSlot, RigLayout


def _run(tmp_path, node_id: int, mapping: str | None = None):
    from hdhil.rig.request import resolve
    from hdhil.rig.runner import run_lockstep

    request = resolve("free-motion", duration_s=0.5, seed=1, mapping=mapping,
                      layout=RigLayout(1, (DriveSlot(node_id),)))  # fmt: skip
    trace = tmp_path / f"node{node_id}-{mapping or 'raw'}.blf"
    return run_lockstep(request, trace=trace), trace


def _close(a, b, path=""):
    """Every number of two results within round-off (identifiers and times aside)."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for key in a:
            _close(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, float) and not math.isnan(a):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12), path
    else:
        assert a == b or (a != a and b != b), path


@pytest.mark.slow
def test_a_drive_at_node_id_5_scores_as_at_node_id_2_and_its_trace_decodes_by_name(tmp_path):
    from hdhil.can.traces.sidecar import read_metadata
    from hdhil.canopen.mapping import trace_decoder
    from hdhil.commands.dbc import export
    from hdhil.rig.evaluate import recording_from_trace

    at2, trace2 = _run(tmp_path, 2)
    at5, trace5 = _run(tmp_path, 5)
    a, b = at2.as_dict(), at5.as_dict()
    for key in ("torque", "evaluation", "controller", "drive", "headline", "velocity_peak"):
        _close(a[key], b[key], key)
    # the frame table names the drive's frames at its identifiers
    assert b["frames"]["control 0x185 DRIVE_TPDO1"] == a["frames"]["control 0x182 DRIVE_TPDO1"]
    assert b["frames"]["control 0x205 DRIVE_RPDO1"] == a["frames"]["control 0x202 DRIVE_RPDO1"]
    assert b["drive"]["unknown_frames"] == b["controller"]["unknown_frames"] == 0
    assert read_metadata(trace5)["layout"] == {
        "controller_node_id": 1, "drives": [{"node_id": 5, "bus": "control"}]}  # fmt: skip

    # `hdhil dbc export --drive-node-id 5` decodes every frame of the trace by name
    dbc = tmp_path / "node5.dbc"
    export(dbc, "raw", 5)
    db = cantools.database.load_file(str(dbc))
    names: dict[str, int] = {}
    with can.BLFReader(str(trace5)) as reader:
        for msg in reader:
            message = db.get_message_by_frame_id(msg.arbitration_id)
            message.decode(msg.data)
            names[message.name] = msg.arbitration_id
    assert names["DRIVE_TPDO1"] == 0x185 and names["DRIVE_TPDO2"] == 0x285
    assert names["CTRL_TPDO1"] == 0x181  # the controller's telemetry stays at node-ID 1
    # hdhil's own decoder and replay read the trace at the sidecar's layout
    decoder = trace_decoder(trace5)
    assert decoder.by_name["DRIVE_RPDO1"][1].frame_id == 0x205
    rec2, _ = recording_from_trace(trace2)
    rec5, _ = recording_from_trace(trace5)
    assert len(rec5) == len(rec2) > 400
    assert rec5.column("T_true") == pytest.approx(rec2.column("T_true"))


@pytest.mark.slow
def test_a_dcf_mapping_follows_the_drive_to_its_node_id(tmp_path):
    """The CiA 402 CST mapping (drive-cst.dcf, ``$NODEID+0x180``): the controller
    configures the drive at node-ID 7 and exchanges its PDOs at 0x187/0x207."""
    at2, _ = _run(tmp_path, 2, "cst")
    at7, trace7 = _run(tmp_path, 7, "cst")
    _close(at2.as_dict()["torque"], at7.as_dict()["torque"], "torque")
    assert at7.as_dict()["frames"]["control 0x187 DRIVE_TPDO1"] > 400
    from hdhil.can.traces.sidecar import read_metadata

    assert read_metadata(trace7)["drive_pdos"]["tpdo1"]["cob_id"] == 0x187


def test_the_pdo_cob_ids_follow_the_node_id_and_a_dcf_is_configured_at_it():
    from hdhil.canopen.dcf import configuration_writes
    from hdhil.dbc import dcf_path

    drive = canopen.import_od(str(eds_path("drive")), 5)
    assert [drive[i][1].default for i in (0x1800, 0x1801, 0x1400)] == [0x185, 0x285, 0x205]
    controller = canopen.import_od(str(eds_path("controller")), 3)
    assert controller[0x1800][1].default == 0x183
    writes = configuration_writes(dcf_path("drive-cst.dcf"), 9)
    cob_ids = {int.from_bytes(v, "little") & 0x7FF for i, s, v in writes if (i, s) == (0x1800, 1)}
    assert cob_ids == {0x189}


def test_the_controller_addresses_its_drive_at_its_node_id():
    from hdhil.firmware.config import FirmwareConfig
    from hdhil.firmware.controller import ControllerNode

    bus = can.Bus(interface="virtual", channel=f"hdhil-nodeid-{time.monotonic_ns()}")
    try:
        node = ControllerNode(bus, FirmwareConfig(), drive_node_id=9)
        io = node.io
        assert (io.command_msg.arbitration_id, io.telemetry_msg.arbitration_id) == (0x209, 0x181)
        assert node.services.read(0x1400, 1) & 0x7FF == 0x189
        assert node.services.read(0x1401, 1) & 0x7FF == 0x289
    finally:
        bus.shutdown()


@pytest.mark.realtime
@pytest.mark.slow
def test_a_stock_canopen_master_finds_a_drive_at_node_id_5(serve_drive):
    """python canopen's own master: its scanner finds the served drive at node-ID 5,
    reads its PDO COB-IDs (0x185 ...) and walks it to OPERATION ENABLED."""
    cfg = DriveConfig(node_id=5, controller_heartbeat_timeout_ms=0, command_hold_cycles=0,
                      actuation="immediate")  # fmt: skip
    drive, args = serve_drive(lambda bus: DriveNode(bus, Plant(PlantConfig()), cfg))
    network = canopen.Network()
    network.connect(interface="virtual", channel=args[args.index("--channel") + 1])
    try:
        deadline = time.monotonic() + 2
        while drive.nmt_state.name != "PRE_OPERATIONAL" and time.monotonic() < deadline:
            time.sleep(0.01)
        network.scanner.search()
        deadline = time.monotonic() + 2
        while 5 not in network.scanner.nodes and time.monotonic() < deadline:
            time.sleep(0.02)
        assert network.scanner.nodes == [5]
        node = canopen.BaseNode402(5, str(eds_path("drive")))
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 1.0
        node.tpdo.read()
        node.rpdo.read()
        assert [node.tpdo[n].cob_id for n in (1, 2)] == [0x185, 0x285]
        assert node.rpdo[1].cob_id == 0x205
        node.setup_402_state_machine(read_pdos=False)
        node.nmt.state = "OPERATIONAL"
        node.state = "OPERATION ENABLED"
        status = node.sdo["statusword"].raw
        assert state_from_statusword(status) is State.OPERATION_ENABLED
    finally:
        network.disconnect()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "--drive-node-id", "1"], "drive node-ID 1 is the controller's"),
        (["run", "--drive-node-id", "128"], "--drive-node-id: must be <= 127"),
        (["run", "--drive-node-id", "0"], "--drive-node-id: must be >= 1"),
        (["emulate", "--node-id", "1", "--interface", "virtual"], "node-ID 1 is the controller's"),
        (["firmware", "--drive-node-id", "200", "--interface", "virtual"], "must be <= 127"),
        (["dbc", "export", "x.dbc", "--drive-node-id", "1"], "node-ID 1 is the controller's"),
    ],
)
def test_a_bad_node_id_is_one_line_and_exit_2(args, message, capsys, tmp_path, monkeypatch):
    from hdhil.cli import main

    monkeypatch.chdir(tmp_path)
    assert main([*args, "--trace", ""] if args[0] == "run" else args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hdhil: error: ") and message in err


@pytest.mark.realtime
def test_a_log_of_a_drive_at_node_id_5_records_its_layout(tmp_path, capsys):
    """``hdhil log --drive-node-id 5``: the sidecar's layout, so ``dump`` and ``evaluate``
    decode the drive's frames at 0x185 ... by name."""
    from hdhil.can.traces.sidecar import read_metadata
    from hdhil.canopen.mapping import trace_decoder
    from hdhil.cli import main

    trace = tmp_path / "log5.blf"
    channel = f"hdhil-log-{time.monotonic_ns()}"
    args = ["log", str(trace), "--interface", "virtual", "--channel", channel,
            "--drive-node-id", "5", "--duration", "0.05"]  # fmt: skip
    assert main(args) == 0, capsys.readouterr().err
    assert read_metadata(trace)["layout"]["drives"] == [{"node_id": 5, "bus": "control"}]
    assert trace_decoder(trace).by_name["DRIVE_TPDO1"][1].frame_id == 0x185


def test_the_api_takes_the_drive_node_id():
    import hdhil.api
    from hdhil.core.dataconf import ConfigError

    assert hdhil.api.resolve(drive_node_id=5).layout.drives[0].node_id == 5
    with pytest.raises(ConfigError, match="drive_node_id must be >= 2, got 1"):
        hdhil.api.resolve(drive_node_id=1)
    with pytest.raises(TypeError):
        hdhil.api.run(drive_node_id=True)
