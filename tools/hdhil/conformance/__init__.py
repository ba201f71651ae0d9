"""``hdhil conformance``: a CiA 301 + CiA 402 conformance and timing suite against one
node on any python-can bus, driven by the node's EDS or DCF.

:mod:`.suite` holds the cases' frame (options, the master's context, the runner),
:mod:`.cia301` and :mod:`.cia402` the cases, :mod:`.timing` the timing cases and
:mod:`.report` the text and JUnit XML reports.  The master is the ``canopen`` package
(network, SDO client); raw frames (NMT, boot-up, heartbeats, SYNC, EMCY, raw SDO
requests) go through python-can on the same bus.  Every object, type, default, limit and
PDO layout comes from the EDS/DCF; only what the standards fix (state patterns,
command codes, abort codes, CiA 402 data types) is written here.
"""

from hdhil.conformance.report import junit_xml, text_report
from hdhil.conformance.suite import (
    GROUPS,
    Case,
    Options,
    Outcome,
    SuiteResult,
    build_cases,
    run_suite,
)

__all__ = [
    "GROUPS",
    "Case",
    "Options",
    "Outcome",
    "SuiteResult",
    "build_cases",
    "junit_xml",
    "run_suite",
    "text_report",
]
