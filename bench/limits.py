"""Peak memory of one completion per output and per MDE pixel: the costs `gpdepth3d.limits` plans with.

Usage::

    python bench/limits.py [--out bench/results/limits.json]

Each case runs the default completion (`gpdepth3d.complete`, ``DepthGPConfig()``) in a fresh
process on a synthetic MDE map with one point per 200 pixels and records the peak resident memory
above the process's memory before the call (``ru_maxrss``). A least-squares fit of
``peak = a * output pixels + b * MDE pixels`` over the cases gives the bytes per pixel; the
estimate of `gpdepth3d.limits.completion_bytes` is printed beside each measured peak. The limit is
lifted for the run (``GPDEPTH3D_MAX_MEMORY_MB``) so that the cases are measured, not refused.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CASES = [
    (240, 320, 240, 320),
    (240, 320, 960, 1280),
    (240, 320, 1920, 2560),
    (480, 640, 480, 640),
    (960, 1280, 960, 1280),
]

ONE_CASE = r"""
import json, resource, sys, time
import numpy as np
import gpdepth3d as g
h, w, ho, wo = map(int, sys.argv[1:5])
rng = np.random.default_rng(0)
mde = 2 + rng.random((h, w))
n = max(50, h * w // 200)
sp = g.SparseDepth.from_arrays(rng.uniform(0, w - 1, n), rng.uniform(0, h - 1, n), 2 + rng.random(n), (h, w))
g.complete(mde[:24, :32], g.SparseDepth.from_arrays(sp.u[:5] % 32, sp.v[:5] % 24, sp.depth[:5], (24, 32)))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t = time.perf_counter()
g.complete(mde, sp, output_shape=(ho, wo))
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"peak_bytes": peak - before, "seconds": time.perf_counter() - t}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "limits.json")
    args = parser.parse_args()
    sys.path.insert(0, str(REPO))
    from gpdepth3d import limits
    from gpdepth3d.io import write_json

    env = {**os.environ, "PYTHONPATH": str(REPO), limits.ENV_VAR: "1000000"}
    rows = []
    for h, w, ho, wo in CASES:
        run = subprocess.run(
            [sys.executable, "-c", ONE_CASE, str(h), str(w), str(ho), str(wo)],
            capture_output=True,
            text=True,
            env=env,
            check=True,
        )
        got = json.loads(run.stdout.strip().splitlines()[-1])
        rows.append(
            {
                "mde_shape": [h, w],
                "output_shape": [ho, wo],
                "peak_bytes": got["peak_bytes"],
                "seconds": round(got["seconds"], 2),
                "estimate_bytes": limits.completion_bytes((h, w), (ho, wo)),
            }
        )
        print(
            f"{h}x{w} -> {ho}x{wo}: peak {got['peak_bytes'] / 2**20:.0f} MiB, "
            f"estimate {rows[-1]['estimate_bytes'] / 2**20:.0f} MiB, {got['seconds']:.1f} s",
            flush=True,
        )
    a = np.array(
        [[r["output_shape"][0] * r["output_shape"][1], r["mde_shape"][0] * r["mde_shape"][1]] for r in rows], float
    )
    fit, *_ = np.linalg.lstsq(a, np.array([r["peak_bytes"] for r in rows], float), rcond=None)
    print(f"fit: {fit[0]:.0f} bytes per output pixel, {fit[1]:.0f} bytes per MDE pixel")
    write_json(
        args.out,
        {
            "what": "peak resident memory of one default completion above the process's memory before it",
            "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_average": os.getloadavg()},
            "date": time.strftime("%Y-%m-%d"),
            "fit_bytes_per_output_pixel": fit[0],
            "fit_bytes_per_mde_pixel": fit[1],
            "planned_bytes_per_output_pixel": limits.COMPLETION_BYTES_PER_OUTPUT_PIXEL,
            "planned_bytes_per_mde_pixel_outside_the_engine": limits.COMPLETION_BYTES_PER_INPUT_PIXEL,
            "rows": rows,
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
