"""``python -m gpdepth3d.cli``: the ``gpdepth3d`` command."""

import sys

from ._main import main

sys.exit(main())
