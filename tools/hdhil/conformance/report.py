"""The suite's reports: a text table and JUnit XML (one testsuite per group)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from itertools import groupby

from hdhil.conformance.suite import SuiteResult

__all__ = ["junit_xml", "text_report"]

_MARK = {"pass": "ok  ", "fail": "FAIL", "skip": "skip", "error": "ERR "}


def text_report(result: SuiteResult, verbose: bool = False) -> str:
    """One line per case that failed or passed only on a retry (all cases with
    ``verbose``), a line per group and the totals."""
    lines = [f"hdhil conformance: node {result.options.node_id}, {result.eds}"]
    for group, items in groupby(result.outcomes, key=lambda o: o.case.group):
        outs = list(items)
        counts = {s: sum(o.status == s for o in outs) for s in _MARK}
        lines.append(f"[{group}] {counts['pass']} passed, {counts['fail'] + counts['error']} "
                     f"failed, {counts['skip']} skipped")  # fmt: skip
        for o in outs:
            if verbose or o.status in ("fail", "error") or _retried(o.detail):
                lines.append(f"  {_MARK[o.status]} {o.case.name}: {o.detail}")
    n = len(result.outcomes)
    failed = result.count("fail") + result.count("error")
    retried = sum(_retried(o.detail) for o in result.outcomes if o.status == "pass")
    again = f" ({retried} on a retry)" if retried else ""
    lines.append(f"{n} cases: {result.count('pass')} passed{again}, {failed} failed, "
                 f"{result.count('skip')} skipped in {result.seconds:.1f} s")  # fmt: skip
    return "\n".join(lines) + "\n"


def _retried(detail: str) -> bool:
    return "(passed on retry " in detail


def junit_xml(result: SuiteResult) -> str:
    """JUnit XML: one ``testsuite`` per group, one ``testcase`` per case (classname
    ``conformance.GROUP``), failures and skips with their detail."""
    root = ET.Element("testsuites", name="hdhil conformance",
                      tests=str(len(result.outcomes)),
                      failures=str(result.count("fail")), errors=str(result.count("error")),
                      skipped=str(result.count("skip")), time=f"{result.seconds:.3f}")  # fmt: skip
    for group, items in groupby(result.outcomes, key=lambda o: o.case.group):
        outs = list(items)
        suite = ET.SubElement(
            root, "testsuite", name=group, tests=str(len(outs)),
            failures=str(sum(o.status == "fail" for o in outs)),
            errors=str(sum(o.status == "error" for o in outs)),
            skipped=str(sum(o.status == "skip" for o in outs)),
            time=f"{sum(o.seconds for o in outs):.3f}",
        )  # fmt: skip
        for o in outs:
            tc = ET.SubElement(suite, "testcase", classname=f"conformance.{group}",
                               name=o.case.name, time=f"{o.seconds:.3f}")  # fmt: skip
            if o.status == "fail":
                ET.SubElement(tc, "failure", message=o.detail).text = o.detail
            elif o.status == "error":
                ET.SubElement(tc, "error", message=o.detail).text = o.detail
            elif o.status == "skip":
                ET.SubElement(tc, "skipped", message=o.detail)
            elif o.detail:
                ET.SubElement(tc, "system-out").text = o.detail
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, "unicode") + "\n"
