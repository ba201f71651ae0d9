"""Fuzzing: random frames at both nodes while they run, and SDO/DBC property tests.

The fuzz run (:func:`fuzz_run`) is a minimal copy of ``hdhil run``'s lockstep cycle
(``tick`` both nodes, ``send_sync``, poll until quiet) with the controller and the drive
on one ``simbus`` channel and a third "fuzzer" bus on the same channel.  Between the
cycles the fuzzer sends a batch of random frames, one at a time, each followed by
polling both nodes until the bus is quiet, so each node receives every fuzz frame (and
the answers they provoke) while it runs.  The frames (seeded ``random.Random``):

- standard identifiers 0..0x7FF uniformly, and the identifiers the nodes use (NMT,
  SYNC, EMCY, PDOs, SDO, heartbeat), half of those with their DBC length;
- extended identifiers (random, the truth channel's, and the nodes' with IDE set);
- DLC 0..8 with random payloads, remote frames, error frames;
- SDO requests with CiA 301 command specifiers to objects of the node's OD.

The channel runs without timing (``bitrate=0``): a batch is many times what a 1 Mbit/s
wire carries in a period, and the nodes time everything with the ``now`` of ``tick``.
When the controller reaches a final phase (a random NMT reset, a controlword that faults
the drive twice, ...) it stays there for a few cycles of fuzzing, then both nodes are
replaced by new ones (CiA 301: recovery is a restart).

How the counters add up (checked per node)
------------------------------------------
Every frame a node receives (fuzz frames, its peer's frames and answers) goes through a
wrapper of its ``on_message`` that compares the node's *tally* before and after: the
sum of every per-frame counter of the node (``unknown_frames``, ``error_frames``, the
diagnostics' frame counters, the CiA 301 services' counters).  A frame either moves the
tally (handled and counted) or belongs to one of the classes a node ignores by design:

- ``not_addressed``: a DBC frame of another node (``hdhil.can.node``: frames of the bus's
  DBC not addressed to the node are ignored), remote frames on those identifiers
  included;
- ``nmt_other_node``: an NMT command for another node-ID (CiA 301);
- ``sdo_response_unawaited``: an SDO response the controller's client did not ask for.

So ``received == counted + not_addressed + nmt_other_node + sdo_response_unawaited``
per node, and ``received == fuzz frames + frames its peer sent`` (simbus delivers every
frame to every other bus on the channel).
"""

from __future__ import annotations

import copy
import math
import os
import random
import struct
import time
from collections import Counter
from dataclasses import dataclass, field

import can
import pytest
from conftest import BusHarness
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hdhil.canopen import services as canopen_services
from hdhil.canopen.cia402 import state_from_statusword
from hdhil.canopen.services import ABORT_TEXT, NmtState
from hdhil.dbc import codec, database
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode, Phase
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig

TS = 1e-3
CTRL_ID, DRIVE_ID = 1, 2
#: Fuzz frames per node (the issue's figure); FUZZ_FRAMES overrides it for experiments.
FUZZ_FRAMES = int(os.environ.get("FUZZ_FRAMES", "100000"))
FRAMES_PER_CYCLE = 50
#: Cycles a node pair stays in a final phase (fuzzed all the while) before it is replaced.
FINAL_CYCLES = 5

#: The identifiers the two nodes use (CiA 301 predefined connection set, control.dbc).
NODE_IDS = sorted(
    {m.frame_id for m in database("control").messages}
    | {0x703, 0x083, 0x603, 0x583, 0x7FF, 0x77F, 0x0FF}
)
DBC_LENGTH = {m.frame_id: m.length for m in database("control").messages}
TRUTH_IDS = [m.frame_id for m in database("truth").messages]
#: SDO client command bytes: expedited downloads (1-4 bytes, with and without size),
#: segmented initiate, download/upload segments, upload, abort, block up/download.
SDO_COMMANDS = (0x2F, 0x2B, 0x27, 0x23, 0x22, 0x21, 0x20, 0x00, 0x01, 0x10, 0x1F,
                0x40, 0x60, 0x70, 0x80, 0xA0, 0xA4, 0xC0, 0xC4, 0xE0)  # fmt: skip


def _od_entries(node) -> list[tuple[int, int]]:
    entries = []
    for index, obj in node.services.od.items():
        if hasattr(obj, "subindices"):
            entries += [(index, sub) for sub in obj.subindices]
        else:
            entries.append((index, 0))
    return sorted(set(entries))


class FrameFuzzer:
    """Random CAN frames, deterministic by seed (module docstring)."""

    def __init__(self, seed: int, od_entries: dict[int, list[tuple[int, int]]]) -> None:
        self.rng = random.Random(seed)
        self.od_entries = od_entries
        self.kinds: Counter[str] = Counter()

    def _payload(self, n: int) -> bytes:
        return self.rng.randbytes(n)

    def frame(self) -> can.Message:
        rng = self.rng
        r = rng.random()
        ext = remote = error = False
        if r < 0.35:
            kind, can_id = "standard", rng.randrange(0x800)
            data = self._payload(rng.randrange(9))
        elif r < 0.65:
            kind, can_id = "node", rng.choice(NODE_IDS)
            n = DBC_LENGTH.get(can_id, 8) if rng.random() < 0.5 else rng.randrange(9)
            data = self._payload(n)
        elif r < 0.77:
            kind, can_id, data = "sdo", *self._sdo()
        elif r < 0.773:
            kind, can_id = "nmt", 0x000
            cs = rng.choice((0x01, 0x02, 0x80, 0x81, 0x82, rng.randrange(256)))
            data = bytes((cs, rng.choice((0, 1, 2, 3, rng.randrange(256)))))
        elif r < 0.87:
            kind, ext = "extended", True
            can_id = rng.choice(
                (rng.randrange(1 << 29), rng.choice(TRUTH_IDS), rng.choice(NODE_IDS))
            )
            data = self._payload(rng.randrange(9))
        elif r < 0.97:
            kind, remote = "remote", True
            can_id = rng.choice((rng.randrange(0x800), rng.choice(NODE_IDS)))
            data = b""
        else:
            kind, error = "error", True
            can_id = rng.choice((0, rng.randrange(0x800), rng.choice(NODE_IDS)))
            data = self._payload(rng.randrange(9))
        self.kinds[kind] += 1
        return can.Message(
            arbitration_id=can_id,
            is_extended_id=ext,
            is_remote_frame=remote,
            is_error_frame=error,
            dlc=rng.randrange(9) if remote else len(data),
            data=data,
            check=False,
        )

    def _sdo(self) -> tuple[int, bytes]:
        rng = self.rng
        node = rng.choice((CTRL_ID, DRIVE_ID))
        cs = rng.choice(SDO_COMMANDS) if rng.random() < 0.9 else rng.randrange(256)
        if rng.random() < 0.7:
            index, sub = rng.choice(self.od_entries[node])
        else:
            index, sub = rng.randrange(0x10000), rng.randrange(256)
        data = struct.pack("<BHB", cs, index, sub) + self._payload(4)
        if rng.random() < 0.1:
            data = data[: rng.randrange(8)]
        return 0x600 + node, data


def _tally(node) -> int:
    """Sum of the node's per-frame counters (module docstring)."""
    s = node.services.counters
    total = (
        sum(node.unknown_frames.values())
        + node.error_frames
        + s.nmt_commands
        + s.sdo_requests
        + s.heartbeats_received
        + s.emcy_received
        + s.malformed_frames
        + s.ignored_in_state
    )
    d = node.diagnostics
    if isinstance(node, ControllerNode):
        return total + (
            d.malformed_frames
            + d.pdos_ignored
            + d.sensor_frames
            + d.extra_sensor_frames
            + d.statusword_frames
            + d.statusword_sdo_answers
            + d.sdo_aborts
        )
    return total + d.syncs + d.commands + d.malformed_frames + d.pdos_ignored


def _service_ids(node_id: int) -> set[int]:
    others = [n for n in range(1, 128) if n != node_id]
    return {0x000, 0x600 + node_id} | {0x700 + n for n in others} | {0x080 + n for n in others}


@dataclass
class Accounting:
    """Per-node frame accounting (module docstring)."""

    received: int = 0
    counted: int = 0
    ignored: Counter[str] = field(default_factory=Counter)
    uncounted: list[can.Message] = field(default_factory=list)

    def wrap(self, node) -> None:
        on_message = node.on_message
        services = _service_ids(node.services.node_id)
        is_controller = isinstance(node, ControllerNode)

        def accounted(msg: can.Message) -> None:
            before = _tally(node)
            on_message(msg)
            self.received += 1
            if _tally(node) > before:
                self.counted += 1
                return
            key = (msg.arbitration_id, msg.is_extended_id)
            plain = not (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame)
            if plain and msg.arbitration_id in services:
                if (
                    msg.arbitration_id == 0
                    and len(msg.data) == 2
                    and msg.data[1]
                    not in (
                        0,
                        node.services.node_id,
                    )
                ):
                    self.ignored["nmt_other_node"] += 1
                    return
            elif is_controller and key == (0x582, False):
                self.ignored["sdo_response_unawaited"] += 1
                return
            elif key in node._known and key not in node._handlers:
                self.ignored["not_addressed"] += 1
                return
            self.uncounted.append(msg)

        node.on_message = accounted


class CountingBus:
    """Counts what a node sends (wraps its bus's ``send``)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.sent = 0
        send = bus.send

        def counted(msg: can.Message, timeout: float | None = None) -> None:
            self.sent += 1
            send(msg, timeout)

        bus.send = counted  # type: ignore[method-assign]


_parsed_od: dict[tuple[str, int], object] = {}
_load_od = canopen_services.load_od


def _cached_load_od(source, node_id):
    """``load_od`` parsing each EDS once per process (a fresh deep copy per node): the
    fuzz run replaces its nodes a few hundred times."""
    key = (str(source), node_id)
    if key not in _parsed_od:
        _parsed_od[key] = _load_od(source, node_id)
    return copy.deepcopy(_parsed_od[key])


@pytest.fixture
def fast_od(monkeypatch):
    monkeypatch.setattr(canopen_services, "load_od", _cached_load_od)


class Pair(BusHarness):
    """Controller and drive in lockstep on the shared bus harness (no timing), its host
    the fuzzer's bus, with accounting."""

    def __init__(self, seed: int) -> None:
        super().__init__("fuzz", bitrate=0, record=False)
        self.fuzz_bus = self.host
        ctrl_bus, drive_bus = self.bus(), self.bus()
        self.ctrl_sent, self.drive_sent = CountingBus(ctrl_bus), CountingBus(drive_bus)
        self.controller = ControllerNode(ctrl_bus, FirmwareConfig())
        self.drive = DriveNode(drive_bus, Plant(PlantConfig(), seed), DriveConfig())
        self.add(self.drive)
        self.add(self.controller, sync=True)
        self.accounts = {"controller": Accounting(), "drive": Accounting()}
        self.accounts["controller"].wrap(self.controller)
        self.accounts["drive"].wrap(self.drive)
        self.fuzz_sent = 0
        self.drive.boot(0.0)
        self.controller.boot(0.0)

    def inject(self, msg: can.Message) -> None:
        self.fuzz_bus.send(msg)
        self.fuzz_sent += 1
        self.pump()


def check_consistent(pair: Pair) -> None:
    """The nodes' state after a cycle: valid, finite, in a known phase."""
    drive, controller = pair.drive, pair.controller
    assert state_from_statusword(drive.statusword) is drive.drive_state
    assert math.isfinite(drive.amplifier_input_V)
    for value in drive.plant.truth()[:10]:  # what the truth channel carries
        assert math.isfinite(value)
    assert isinstance(controller.phase, Phase)
    assert controller.services.state in tuple(NmtState)
    assert drive.services.state in tuple(NmtState)


@dataclass
class FuzzReport:
    frames: int = 0
    cycles: int = 0
    sessions: int = 0
    phases: Counter[str] = field(default_factory=Counter)
    kinds: Counter[str] = field(default_factory=Counter)
    received: dict[str, int] = field(default_factory=lambda: {"controller": 0, "drive": 0})
    counted: dict[str, int] = field(default_factory=lambda: {"controller": 0, "drive": 0})
    ignored: dict[str, Counter[str]] = field(
        default_factory=lambda: {"controller": Counter(), "drive": Counter()}
    )


def fuzz_run(seed: int, frames: int, per_cycle: int = FRAMES_PER_CYCLE) -> FuzzReport:
    """Inject ``frames`` random frames at both nodes while they run (module docstring)."""
    report = FuzzReport()
    pair = Pair(seed)
    entries = {CTRL_ID: _od_entries(pair.controller), DRIVE_ID: _od_entries(pair.drive)}
    fuzzer = FrameFuzzer(seed, entries)
    final_for = 0
    session = 0

    def finish(p: Pair) -> None:
        p.pump()
        for name, peer_sent in (("controller", p.drive_sent.sent), ("drive", p.ctrl_sent.sent)):
            acc = p.accounts[name]
            assert not acc.uncounted, (
                f"{name}: frames neither handled nor counted: {acc.uncounted[:5]}"
            )
            assert acc.received == p.fuzz_sent + peer_sent, name
            assert acc.received == acc.counted + sum(acc.ignored.values()), name
            report.received[name] += acc.received
            report.counted[name] += acc.counted
            report.ignored[name].update(acc.ignored)
        p.close()

    try:
        while report.frames < frames:
            pair.cycle()
            report.cycles += 1
            for _ in range(min(per_cycle, frames - report.frames)):
                pair.inject(fuzzer.frame())
                report.frames += 1
            check_consistent(pair)
            report.phases[str(pair.controller.phase)] += 1
            final_for = final_for + 1 if pair.controller.phase in ("stopped", "safe") else 0
            if final_for >= FINAL_CYCLES:
                finish(pair)
                session += 1
                pair = Pair(seed + session)
                final_for = 0
        finish(pair)
    except BaseException:
        pair.close()
        raise
    report.sessions = session + 1
    report.kinds = fuzzer.kinds
    return report


# --------------------------------------------------------------------- the fuzz run


@pytest.mark.slow
def test_fuzz_both_nodes_while_running(fast_od):
    t0 = time.perf_counter()
    report = fuzz_run(seed=20240601, frames=FUZZ_FRAMES)
    wall = time.perf_counter() - t0
    print(
        f"\nfuzz: {report.frames} frames per node, {report.cycles} cycles, "
        f"{report.sessions} sessions, {wall:.1f} s; phases {dict(report.phases)}; "
        f"kinds {dict(report.kinds)}; received {report.received}; counted {report.counted}; "
        f"ignored { ({k: dict(v) for k, v in report.ignored.items()}) }"
    )
    assert report.frames == FUZZ_FRAMES
    # Every node saw every fuzz frame plus its peer's traffic.
    for name in ("controller", "drive"):
        assert report.received[name] > report.frames
    # The run spent time in operation, not only in restarts.
    assert report.phases["operational"] > report.cycles // 10


# ------------------------------------------------------- regressions found by the fuzz


@pytest.mark.parametrize("node_kind", ["controller", "drive"])
def test_error_frames_are_counted_and_never_dispatched_as_data(node_kind):
    """The fuzz found error frames with a handled identifier (e.g. 0x182 with 8 bytes)
    dispatched to the handler as if they were data: the controller ran its interrupt on
    them.  Error frames go to ``error_frames`` now, whatever identifier they carry."""
    pair = Pair(seed=1)
    try:
        for _ in range(8):
            pair.cycle()
        assert pair.controller.phase == "operational"
        node = pair.controller if node_kind == "controller" else pair.drive
        can_id = 0x182 if node_kind == "controller" else 0x202
        before = (node.diagnostics.malformed_frames, node.error_frames, _tally(node))
        handled = (
            pair.controller.diagnostics.sensor_frames
            if node_kind == "controller"
            else pair.drive.diagnostics.commands
        )
        frame = can.Message(
            arbitration_id=can_id, is_error_frame=True, data=bytes(range(8)), check=False
        )
        frame.dlc = 8 if node_kind == "controller" else 5
        frame.data = frame.data[: frame.dlc]
        pair.inject(frame)
        assert node.error_frames == before[1] + 1
        assert node.diagnostics.malformed_frames == before[0]
        assert _tally(node) == before[2] + 1
        after = (
            pair.controller.diagnostics.sensor_frames
            if node_kind == "controller"
            else pair.drive.diagnostics.commands
        )
        assert after == handled
    finally:
        pair.close()


# ------------------------------------------------------------ SDO property tests

_sdo_rigs: dict[str, tuple[object, can.BusABC]] = {}


def _sdo_rig(kind: str):
    """A booted (PRE-OPERATIONAL) node and a client bus; one per kind, reused."""
    if kind not in _sdo_rigs:
        harness = BusHarness("fuzz-sdo", bitrate=0)
        client = harness.host
        node_bus = harness.bus()
        if kind == "controller":
            node = ControllerNode(node_bus, FirmwareConfig())
        else:
            node = DriveNode(node_bus, Plant(PlantConfig(), 1), DriveConfig())
        node.boot(0.0)
        harness.frames()  # the boot-up
        _sdo_rigs[kind] = (node, client)
    return _sdo_rigs[kind]


_OD_ENTRIES = {
    "controller": _od_entries(_sdo_rig("controller")[0]),
    "drive": _od_entries(_sdo_rig("drive")[0]),
}


def _exchange(node, client: can.BusABC, data: bytes) -> list[bytes]:
    client.send(can.Message(arbitration_id=0x600 + node.services.node_id, data=data,
                            is_extended_id=False))  # fmt: skip
    node.poll()
    responses = []
    while (msg := client.recv(0)) is not None:
        assert msg.arbitration_id == 0x580 + node.services.node_id
        assert not msg.is_extended_id and not msg.is_remote_frame
        assert len(msg.data) == 8
        responses.append(bytes(msg.data))
    return responses


def _assert_abort(response: bytes, index: int, sub: int) -> None:
    assert response[0] == 0x80
    assert struct.unpack_from("<HB", response, 1) == (index, sub)
    code = struct.unpack_from("<I", response, 4)[0]
    assert code in ABORT_TEXT, f"abort 0x{code:08X} is no CiA 301 abort code"


def _index_sub(kind: str):
    return st.one_of(
        st.sampled_from(_OD_ENTRIES[kind]),
        st.tuples(st.integers(0, 0xFFFF), st.integers(0, 0xFF)),
    )


def _state(node):
    pending = getattr(node, "_pending", None)
    return copy.deepcopy(node.services.node.data_store), pending


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["controller", "drive"])
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_sdo_writes_answer_a_response_or_an_abort_and_aborts_change_nothing(kind, data):
    """Random index/sub/value/length to each node's SDO server (CiA 301 §7.2.4.3):
    expedited downloads of 1-4 bytes, segmented downloads of 5-7 bytes (one segment).
    Each request gets exactly one answer: the download response echoing index/sub (then
    the segment response) or an abort with a CiA 301 code, and after an abort the object
    dictionary (and the controller's staged parameters) are unchanged."""
    node, client = _sdo_rig(kind)
    index, sub = data.draw(_index_sub(kind), label="index/sub")
    value = data.draw(st.binary(min_size=1, max_size=7), label="value")
    before = _state(node)
    n = len(value)
    if n <= 4:
        cs = 0x23 | (4 - n) << 2
        request = struct.pack("<BHB", cs, index, sub) + value.ljust(4, b"\0")
        (response,) = _exchange(node, client, request)
        if response[0] == 0x80:
            _assert_abort(response, index, sub)
            assert _state(node) == before
        else:
            assert response[0] == 0x60
            assert struct.unpack_from("<HB", response, 1) == (index, sub)
        return
    request = struct.pack("<BHBI", 0x21, index, sub, n)
    (response,) = _exchange(node, client, request)
    if response[0] == 0x80:
        _assert_abort(response, index, sub)
        assert _state(node) == before
        return
    assert response[0] == 0x60
    assert struct.unpack_from("<HB", response, 1) == (index, sub)
    segment = bytes(((7 - n) << 1 | 0x01,)) + value.ljust(7, b"\0")
    (response,) = _exchange(node, client, segment)
    if response[0] == 0x80:
        _assert_abort(response, index, sub)
        assert _state(node) == before
    else:
        assert response[0] == 0x20  # segment response, toggle 0


@pytest.mark.parametrize("kind", ["controller", "drive"])
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_sdo_reads_answer_a_response_or_an_abort_and_change_nothing(kind, data):
    node, client = _sdo_rig(kind)
    index, sub = data.draw(_index_sub(kind), label="index/sub")
    before = _state(node)
    (response,) = _exchange(node, client, struct.pack("<BHB4x", 0x40, index, sub))
    if response[0] == 0x80:
        _assert_abort(response, index, sub)
    else:
        assert response[0] & 0xE0 == 0x40  # upload response (expedited or segmented)
        assert struct.unpack_from("<HB", response, 1) == (index, sub)
        if not response[0] & 0x02:  # segmented: read it out so no transfer stays open
            toggle = 0
            for _ in range(64):
                (seg,) = _exchange(node, client, bytes((0x60 | toggle,)) + bytes(7))
                assert seg[0] & 0xE0 == 0x00 and seg[0] & 0x10 == toggle
                if seg[0] & 0x01:
                    break
                toggle ^= 0x10
            else:
                pytest.fail("segmented upload did not end")
    assert _state(node) == before


# ------------------------------------------------------------ DBC payload round trip

ALL_MESSAGES = [(bus, m.name) for bus in ("control", "truth") for m in database(bus).messages]


@pytest.mark.slow
@pytest.mark.parametrize(("bus", "name"), ALL_MESSAGES)
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_any_payload_decodes_and_encodes_back_to_the_same_bytes(bus, name, data):
    """tests/test_dbc_codec.py round-trips values through cantools; this is the other
    direction, over every payload a frame can carry (what the fuzz feeds the nodes):
    bytes -> decode -> encode gives the same bytes, and wrong lengths raise ValueError."""
    c = codec(bus, name)
    payload = data.draw(st.binary(min_size=c.length, max_size=c.length))
    assert c.encode(*c.decode(payload)) == payload
    wrong = data.draw(st.binary(max_size=8).filter(lambda b: len(b) != c.length))
    with pytest.raises(ValueError):
        c.decode(wrong)
