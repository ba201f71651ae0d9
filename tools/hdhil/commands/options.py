"""Command-line options several commands share."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_fault_arguments(p: argparse.ArgumentParser, what: str = "") -> None:
    """``--fault KEY=VALUE`` (repeatable) and ``--fault-log FILE``."""
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="inject a fault: a key of the scenario's [faults] table, dotted, and a TOML "
        "value, merged over the table (the flag wins; repeatable), e.g. "
        "control.loss_rate=0.05, control.jitter_us=200, sensors.tacho_spike_rate=0.001, "
        "seed=3, 'control.silence=[{node=2,start_s=1,duration_s=0.5}]'" + what,
    )
    p.add_argument(
        "--fault-log",
        type=Path,
        default=None,
        metavar="FILE",
        help="write every injected fault as JSON lines",
    )
