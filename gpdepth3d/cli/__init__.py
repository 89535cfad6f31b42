"""The ``gpdepth3d`` command line: one module per subcommand (parse, call the library, print).

Subcommands: `complete`, `demo`, `eval`, `fuse`, `view`, `batch`; `main` (in `_main`) runs
them and turns every failure into one line on stderr and exit code 1.
"""

from ._main import main as main
