"""Shared fixtures."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest
from hypothesis import settings

from hdhil.hostsim.drive import DriveNode
from hdhil.rig.loop import serve

# In CI, property tests draw the same examples on every run, so a verdict can be
# reproduced from the commit alone; local runs keep exploring new examples.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

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
