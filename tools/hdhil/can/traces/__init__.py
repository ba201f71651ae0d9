"""CAN traces, one job per module, as python-can splits its I/O.

- :mod:`~hdhil.can.traces.formats`: the formats by extension (no python-can import);
- :mod:`~hdhil.can.traces.writer`: python-can's writer in a child process, atomic;
- :mod:`~hdhil.can.traces.tap`: the host tap handing a run's frames to listeners;
- :mod:`~hdhil.can.traces.sidecar`: the run's metadata in ``TRACE.json``;
- :mod:`~hdhil.can.traces.reader`: python-can's readers, with damage recorded;
- :mod:`~hdhil.can.traces.decode`: frames classified and decoded with the DBCs;
- :mod:`~hdhil.can.traces.stats`: per-identifier timing, bus load, counter gaps;
- :mod:`~hdhil.can.traces.export`: a decoded trace as a table or CSV (``hdhil dump``).

Importing the package loads none of them: import the module you need.
"""
