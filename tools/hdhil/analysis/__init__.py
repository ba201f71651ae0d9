"""The analyses behind the commands, usable from Python: identification of the joint
from a chirp, maximum-likelihood tuning of the ripple filter, soak runs checked per
block, benchmarks, the paper figures and the LQG design report.

One module per job; each takes data (a trace path, arrays, a scenario, a configuration)
and returns results, report text or figures.  The command modules in
:mod:`hdhil.commands` only parse options, call these, print and choose the exit code.
Nothing is imported here, so loading one analysis never loads the libraries of another.
"""
