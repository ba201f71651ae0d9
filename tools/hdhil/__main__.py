"""``python -m hdhil``: the same as the ``hdhil`` command."""

from hdhil.console import run

run()
