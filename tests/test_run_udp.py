"""``hdhil run --interface udp_multicast`` (the in-process lockstep rig on python-can's
udp_multicast bus) inside a private network namespace (loopback only): evaluated in the
cycle time like the simulated bus.  Skipped, with the reason, where a namespace cannot be
created."""

from __future__ import annotations

import json

import pytest
from test_multiprocess import _hdhil

from hdhil.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.netns]

GROUP = "239.74.163.6"


def _firmware_rms(evaluation):
    firmware = [c for c in evaluation["candidates"] if c["name"].startswith("firmware")]
    return firmware[0]["rms_error"]


def test_run_on_udp_multicast_is_evaluated_like_the_simulated_bus(netns, capsys):
    """udp_multicast stamps a received frame with the kernel's receive time (the sender's
    timestamp in the packet is replaced), so the tap stamps control frames with the cycle
    clock as on ``virtual``.  A frame that reaches the tap's socket only after its cycle
    closed is stamped with the next cycle, so the sample count may differ by a few; the
    filtered RMS error stays within 5 % of simbus's (same reasoning as the virtual test
    in test_run_integration.py)."""
    proc = _hdhil(netns, "run", "--duration", "1", "--interface", "udp_multicast",
                  "--channel", GROUP, "--json")  # fmt: skip
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    udp = json.loads(out)["evaluation"]
    assert main(["run", "--duration", "1", "--json"]) == 0
    sim = json.loads(capsys.readouterr().out)["evaluation"]
    assert sim["samples"] > 600
    assert abs(udp["samples"] - sim["samples"]) <= 0.02 * sim["samples"]
    assert _firmware_rms(udp) == pytest.approx(_firmware_rms(sim), rel=0.05)
