"""``python -m hdhil``: the same as the ``hdhil`` command."""

import sys

from hdhil.cli import main

sys.exit(main())
