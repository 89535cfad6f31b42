"""The reliability sweeps of tests/test_reliability.py, run and counted for docs/reliability.md.

Usage::

    python bench/reliability.py [--cli-sweep] [--examples 400] [--out bench/results/reliability.json]

Runs ``pytest tests/test_reliability.py`` with ``GPDEPTH3D_RELIABILITY_OUT`` set, so each sweep adds its outcome
counts to the results file: the API cases (typed error per case), the CLI cases, the property sweep
(``GPDEPTH3D_FUZZ_EXAMPLES``) and, with ``--cli-sweep``, the CLI sweep (``GPDEPTH3D_FUZZ_CLI=1``, minutes).
``python bench/report.py`` then writes the table of docs/reliability.md from it: no count is typed by hand.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cli-sweep", action="store_true", help="also the CLI sweep (minutes)")
    parser.add_argument("--examples", type=int, default=400, help="examples of the property sweep")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "reliability.json")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import json

    from gpdepth3d.io import write_json

    with tempfile.TemporaryDirectory() as tmp:
        counts = Path(tmp) / "counts.json"
        env = {
            **os.environ,
            "PYTHONPATH": str(REPO),
            "GPDEPTH3D_RELIABILITY_OUT": str(counts),
            "GPDEPTH3D_FUZZ_EXAMPLES": str(args.examples),
            **({"GPDEPTH3D_FUZZ_CLI": "1"} if args.cli_sweep else {}),
        }
        selection = "api_case or cli_case or property" + (" or cli_sweep" if args.cli_sweep else "")
        load = os.getloadavg()
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", ""]
        command += ["tests/test_reliability.py", "-k", selection]
        proc = subprocess.run(command, cwd=REPO, env=env)
        if proc.returncode != 0:
            print("the sweeps failed: nothing written", file=sys.stderr)
            return 1
        sweeps = json.loads(counts.read_text())
    write_json(
        args.out,
        {
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
            "load_average_1min": {"before": round(load[0], 2), "after": round(os.getloadavg()[0], 2)},
            "examples": args.examples,
            "sweeps": sweeps,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
