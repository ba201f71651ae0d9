"""Shared fixtures and helpers: the bus harness, the frame recorder, the served drive, and
the prerequisites of the tiers that need more than Python (root and a network namespace,
can-utils).

A test whose prerequisite is missing skips with the prerequisite named (:func:`require`);
in CI (``CI=true``) every skip is a failure instead, so a tier that cannot run fails the
build rather than passing silently.  The one exception is a test that CI runs in another
step (the MF4 round trip, in a venv of its own): :func:`skip_covered_elsewhere` lets it
skip when the environment says so (``HDHIL_MF4_ELSEWHERE=1``, set by ``.ci/run``).
The markers (``slow``, ``subprocess``, ``netns``, ``realtime``, ``canutils``) are
registered in pyproject.toml; docs/testing.md lists the tiers.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Protocol

import can
import pytest
from hypothesis import settings

from hdhil.can.simbus import SimClock
from hdhil.dbc import CHANNEL_NUMBER, codec
from hdhil.hostsim.drive import DriveNode
from hdhil.rig.loop import serve

# The parse cache (hdhil.dbc.parsecache) of the whole session, and of every process it
# starts, lives in a temporary directory: the suite never writes into the user's home.
_PARSE_CACHE = tempfile.mkdtemp(prefix="hdhil-test-cache-")
os.environ["HDHIL_CACHE_DIR"] = _PARSE_CACHE


def pytest_unconfigure(config: pytest.Config) -> None:
    shutil.rmtree(_PARSE_CACHE, ignore_errors=True)


# In CI, property tests draw the same examples on every run, so a verdict can be
# reproduced from the commit alone; local runs keep exploring new examples.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


# ------------------------------------------------------------------ prerequisites

#: The start of a skip reason that CI accepts: the test runs in another CI step.
COVERED_ELSEWHERE = "covered by another CI step: "


def in_ci() -> bool:
    return os.environ.get("CI") == "true"


def require(available: bool, prerequisite: str) -> None:
    """Skip the calling test unless ``available``, naming the missing ``prerequisite``
    (in CI the skip becomes a failure, see :func:`_fail_skip_in_ci`)."""
    if not available:
        pytest.skip(f"missing prerequisite: {prerequisite}")


def require_tools(*names: str, package: str) -> None:
    """The programs ``names`` on PATH (from the system ``package``)."""
    missing = [name for name in names if shutil.which(name) is None]
    require(not missing, f"{package} ({', '.join(missing)} not on PATH)")


def skip_covered_elsewhere(available: bool, prerequisite: str, variable: str, step: str) -> None:
    """Like :func:`require`, but the test may skip in CI too when ``variable`` is 1: the
    CI ``step`` runs it where ``prerequisite`` is installed."""
    if available:
        return
    if os.environ.get(variable) == "1":
        pytest.skip(f"{COVERED_ELSEWHERE}{step}; {prerequisite} is not installed here "
                    f"({variable}=1)")  # fmt: skip
    require(False, prerequisite)


def _fail_skip_in_ci(report: pytest.TestReport | pytest.CollectReport) -> None:
    """In CI a skip is a failure, with its reason: a tier whose prerequisite is missing
    (not root, no ``ip netns``, no can-utils ...) must not pass silently."""
    if not (in_ci() and report.skipped) or hasattr(report, "wasxfail"):
        return
    reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    reason = reason.removeprefix("Skipped: ")
    if reason.startswith(COVERED_ELSEWHERE):
        return
    report.outcome = "failed"
    report.longrepr = f"skipped in CI (CI=true), where every test must run: {reason}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    outcome = yield
    _fail_skip_in_ci(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector) -> Iterator[None]:
    """A whole module skipped at import (``pytest.importorskip``) fails in CI too."""
    outcome = yield
    _fail_skip_in_ci(outcome.get_result())


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=False)


@pytest.fixture
def netns() -> Iterator[str]:
    """A private network namespace with loopback alone, multicast routed to ``lo``, so
    no frame of a udp_multicast bus can leave the machine; its name.  Needs root and
    iproute2 (``ip netns``)."""
    require_tools("ip", package="iproute2")
    require(os.geteuid() == 0, "root (creating a network namespace)")
    name = f"hdhil-test-{os.getpid()}"
    made = _ip("netns", "add", name)
    require(made.returncode == 0, f"a network namespace ({made.stderr.strip()})")
    try:
        for cmd in (["link", "set", "lo", "up"], ["link", "set", "lo", "multicast", "on"],
                    ["route", "add", "224.0.0.0/4", "dev", "lo"]):  # fmt: skip
            r = _ip("netns", "exec", name, "ip", *cmd)
            assert r.returncode == 0, r.stderr
        yield name
    finally:
        _ip("netns", "del", name)


# ------------------------------------------------------------------ frame recorder


class FrameRecorder(can.Listener):
    """Every frame it is handed, in order (``messages``), and how many hand-overs
    (``calls``): a listener of the lockstep runner's tap (``extra_listeners``) or of a
    :class:`can.Notifier`, or a collector of what waits on a bus (:meth:`drain`).

    ``batches=True`` gives it the tap's batch interface (``on_frames``: a poll's frames in
    one call); without it, it is a plain listener, handed frames one by one.
    """

    def __init__(self, batches: bool = False) -> None:
        self.messages: list[can.Message] = []
        self.calls = 0
        if batches:
            self.on_frames = self._on_frames

    def on_message_received(self, msg: can.Message) -> None:
        self.calls += 1
        self.messages.append(msg)

    def _on_frames(self, frames: list[can.Message]) -> None:
        self.calls += 1
        self.messages += frames

    def drain(self, bus: can.BusABC) -> list[can.Message]:
        """Every frame waiting on ``bus`` now, recorded and returned."""
        out = []
        while (msg := bus.recv(0)) is not None:
            out.append(msg)
        self.messages += out
        return out

    def records(self) -> list[tuple[Any, int, float, bytes]]:
        """(channel, ID, timestamp, data) of every frame: comparable between runs."""
        return [(m.channel, m.arbitration_id, m.timestamp, bytes(m.data)) for m in self.messages]

    def with_id(self, frame_id: int, extended: bool | None = None) -> list[can.Message]:
        return [
            m
            for m in self.messages
            if m.arbitration_id == frame_id and extended in (None, m.is_extended_id)
        ]

    def decoded(self, bus: str, message: str) -> list[tuple[float, tuple]]:
        """(timestamp, signal values) of every ``message`` of ``bus``'s DBC seen on that
        bus's trace channel (``hdhil.dbc.CHANNEL_NUMBER``)."""
        frame, channel = codec(bus, message), CHANNEL_NUMBER[bus]
        return [
            (m.timestamp, frame.decode(m.data))
            for m in self.messages
            if m.channel == channel and m.arbitration_id == frame.frame_id
        ]


# ------------------------------------------------------------------ bus harness


class LockstepNode(Protocol):
    def tick(self, now: float) -> object: ...

    def poll(self) -> int: ...


_channel_ids = itertools.count()


class BusHarness:
    """Nodes under test on one ``simbus`` channel, on a simulated clock, stepped in
    lockstep the way the runner steps them; a host handle on the channel plays every
    other node and tool (it sends frames, and keeps every frame the nodes sent in
    ``log`` as (cycle, ID, data) and in ``recorder``; ``record=False``: it reads nothing,
    for runs of millions of frames nobody looks at).

    A cycle (:meth:`cycle`): the clock at ``k * period_s``, every node's ``tick`` in the
    order they were added, SYNC (sent by the ``sync`` node, else by the host with a
    counter), then every node polled until the channel is quiet.
    """

    def __init__(
        self, name: str = "t", period_s: float = 1e-3, bitrate: int = 1_000_000,
        record: bool = True,
    ) -> None:  # fmt: skip
        self.clock = SimClock()
        self.channel = f"{name}-{os.getpid()}-{next(_channel_ids)}"
        self.bitrate = bitrate
        self.period_s = period_s
        self.buses: list[can.BusABC] = []
        self.nodes: list[LockstepNode] = []
        self.sync_node: Any = None
        self.sync_counter = 0
        self.k = 0
        self.log: list[tuple[int, int, bytes]] = []
        self.recorder = FrameRecorder()
        self.record = record
        self.host = self.bus()

    def bus(self, suffix: str = "", **kwargs: Any) -> can.BusABC:
        """A new handle on the harness's channel, or on the channel ``channel + suffix``
        (a second bus, e.g. the truth bus with ``bitrate=0``), on the harness's clock."""
        kwargs.setdefault("bitrate", self.bitrate)
        bus = can.Bus(interface="simbus", channel=self.channel + suffix, clock=self.clock,
                      **kwargs)  # fmt: skip
        self.buses.append(bus)
        return bus

    def add(self, node: Any, sync: bool = False) -> Any:
        """Step ``node`` in every cycle (after the nodes added before it); ``sync``: it
        sends the SYNC (``send_sync()``) instead of the host."""
        self.nodes.append(node)
        if sync:
            self.sync_node = node
        return node

    @property
    def now(self) -> float:
        return self.k * self.period_s

    def send(self, can_id: int, data: bytes, **kwargs: Any) -> None:
        """A standard frame from the host."""
        self.host.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False,
                                   **kwargs))  # fmt: skip

    def frames(self) -> list[tuple[int, bytes]]:
        """The frames the host received since the last call, as (ID, data)."""
        out = [(m.arbitration_id, bytes(m.data)) for m in self.recorder.drain(self.host)]
        self.log += [(self.k, i, d) for i, d in out]
        return out

    def pump(self) -> list[tuple[int, bytes]]:
        """Poll the nodes until none has anything left; the host's new frames."""
        while sum(node.poll() for node in self.nodes):
            pass
        return self.frames() if self.record else []

    def send_sync(self) -> None:
        if self.sync_node is not None:
            self.sync_node.send_sync()
        else:
            self.sync_counter = self.sync_counter % 240 + 1
            self.send(0x080, bytes((self.sync_counter,)))

    def tick(self) -> float:
        """The clock to this cycle's time, every node's tick; the time."""
        now = self.clock.now = self.now
        for node in self.nodes:
            node.tick(now)
        return now

    def cycle(
        self, sync: bool = True, stop: Callable[[], bool] | None = None
    ) -> list[tuple[int, bytes]] | None:
        """One lockstep cycle; the frames the host saw in it.  ``stop``, asked after the
        ticks: when true the cycle ends there (no SYNC) and returns None."""
        self.tick()
        if stop is not None and stop():
            return None
        if sync:
            self.send_sync()
        out = self.pump()
        self.k += 1
        return out

    def run(self, cycles: int) -> list[tuple[int, int, bytes]]:
        """``cycles`` cycles; the log entries they added."""
        start = len(self.log)
        for _ in range(cycles):
            self.cycle()
        return self.log[start:]

    def close(self) -> None:
        for bus in self.buses:
            bus.shutdown()

    def __enter__(self) -> BusHarness:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@pytest.fixture
def bus_harness() -> Iterator[Callable[..., BusHarness]]:
    """``bus_harness(name, ...)``: a new :class:`BusHarness`, closed after the test."""
    made: list[BusHarness] = []

    def make(*args: Any, **kwargs: Any) -> BusHarness:
        made.append(BusHarness(*args, **kwargs))
        return made[-1]

    yield make
    for harness in made:
        harness.close()


# ------------------------------------------------------------------ served drive

ServeDrive = Callable[[Callable[[can.BusABC], DriveNode]], tuple[DriveNode, list[str]]]


@pytest.fixture
def serve_drive() -> Iterator[ServeDrive]:
    """Serves a drive node in real time on a fresh python-can virtual channel, as
    ``hdhil emulate`` does; ``serve_drive(make_node)`` returns the node and the CLI
    arguments that reach it (``--interface virtual --channel ...``)."""
    served: list[tuple[threading.Event, threading.Thread, can.BusABC]] = []

    def start(make_node: Callable[[can.BusABC], DriveNode]) -> tuple[DriveNode, list[str]]:
        channel = f"hdhil-served-{time.monotonic_ns()}"
        bus = can.Bus(interface="virtual", channel=channel)
        node = make_node(bus)
        stop = threading.Event()

        def run() -> None:
            node.boot(time.monotonic())
            serve(node, stop.is_set)  # the node loop of `hdhil emulate`

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        served.append((stop, thread, bus))
        return node, ["--interface", "virtual", "--channel", channel]

    yield start
    for stop, thread, bus in served:
        stop.set()
        thread.join(5)
        bus.shutdown()


# ------------------------------------------------------------------ full disks
@pytest.fixture
def tiny_fs(tmp_path: Any) -> Iterator[Any]:
    """A 256 KiB tmpfs mounted for the test (root only: skipped otherwise, with the
    reason), unmounted after it."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    where = tmp_path / "tiny"
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(where)],
                          capture_output=True, text=True)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {done.stderr.strip()}")
    try:
        yield where
    finally:
        for _ in range(50):  # a process of the test may still hold a file open
            if subprocess.run(["umount", str(where)], capture_output=True).returncode == 0:
                break
            time.sleep(0.1)
        else:
            subprocess.run(["umount", "-l", str(where)], capture_output=True)


def fill_fs(fs: Any, leave: int = 0) -> None:
    """Fill the file system of ``fs`` so that ``leave`` bytes (whole pages) stay free."""
    st = os.statvfs(fs)
    free = st.f_bavail * st.f_frsize
    with open(fs / "filler", "wb") as fh:
        fh.write(b"\0" * max(free - leave, 0))


class CannedExecutor(concurrent.futures.Executor):
    """A campaign executor that runs nothing: each variant 'finishes' at once with a
    fixed error (and ``trace``'s bytes as its trace); ``submitted`` counts them."""

    submitted = 0
    trace: bytes | None = None

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        CannedExecutor.submitted += 1
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        fut.set_result({"result": None, "error": "RuntimeError: canned",
                        "trace": CannedExecutor.trace, "sidecar": None, "wall_s": 0.0,
                        "worker": "here:1"})  # fmt: skip
        return fut
