"""Time to the viewer's first frame: from starting ``gpdepth3d view`` to points drawn in a real browser.

Usage::

    python bench/viewer_startup.py [--posterior gpdepth3d_out/k0.npz] [--rgb ../shared/data/kitti_object/000000.png]
                                   [--repeats 3] [--out bench/results/viewer_startup.json]

The posterior is the one the README's ``complete`` line writes (KITTI object frame 0, full size,
RT-MonoDepth-S + projected LiDAR); it is made first when missing. Each repeat starts the command
line as a user does (a fresh ``python -m gpdepth3d.cli view`` process) and a headless Chromium
(Playwright driving Debian's ``chromium``) that opens the page as soon as the port answers. Events,
in seconds after the process start:

* ``page``: the page answered (the server is up);
* ``loading``: the panel shows the loading text ("Loading frame ...");
* ``first_frame``: the 3D area is no longer blank (points drawn);
* ``panel``: the controls are in the panel ("Max σ (m)").

Wall-clock seconds on whatever machine runs it (the development machine is a shared 2-core VM:
the load average is recorded; compare rows of one run). Results: a table on stdout and
``bench/results/viewer_startup.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _blank(png: bytes) -> bool:
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    region = img[:, : int(img.shape[1] * 0.6)]
    return float(np.mean(region.min(axis=2) < 235)) <= 0.02


def one_run(posterior: Path, rgb: Path, executable: str, timeout: float = 120.0) -> dict[str, float]:
    """Starts the viewer and a browser; returns the seconds from the process start to each event."""
    from playwright.sync_api import sync_playwright

    port = _free_port()
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [
        sys.executable,
        "-m",
        "gpdepth3d.cli",
        "view",
        "--posterior",
        str(posterior),
        "--rgb",
        str(rgb),
        "--port",
        str(port),
        "--duration",
        str(timeout),
    ]
    times: dict[str, float] = {}
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=executable, headless=True, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            url = f"http://127.0.0.1:{port}"
            while time.monotonic() - t0 < timeout:
                try:
                    page.goto(url, timeout=5_000)
                    break
                except Exception:  # noqa: BLE001 - not listening yet
                    time.sleep(0.05)
            times["page"] = time.monotonic() - t0
            end = t0 + timeout
            while time.monotonic() < end and len(times) < 4:
                if "loading" not in times and page.get_by_text("Loading frame").count():
                    times["loading"] = time.monotonic() - t0
                if "panel" not in times and page.get_by_text("Max σ (m)", exact=True).count():
                    times["panel"] = time.monotonic() - t0
                if "first_frame" not in times and not _blank(page.screenshot()):
                    times["first_frame"] = time.monotonic() - t0
                if "panel" in times and "first_frame" in times:
                    break
                time.sleep(0.05)
            browser.close()
    finally:
        proc.terminate()
        proc.wait(30)
    return times


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--posterior", type=Path, default=REPO / "gpdepth3d_out" / "k0.npz")
    parser.add_argument("--rgb", type=Path, default=SHARED / "data" / "kitti_object" / "000000.png")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "viewer_startup.json")
    args = parser.parse_args(argv)
    executable = "/usr/bin/chromium" if Path("/usr/bin/chromium").is_file() else shutil.which("chromium")
    if executable is None:
        raise SystemExit("chromium not installed (Debian: apt-get install chromium)")
    if not args.posterior.is_file():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "gpdepth3d.cli",
                "complete",
                "--rgb",
                str(args.rgb),
                "--mde",
                "rtmonodepth",
                "--lidar",
                str(SHARED / "data" / "kitti_object" / "000000.bin"),
                "--calib",
                str(SHARED / "data" / "kitti_object" / "calib_000000.txt"),
                "--output",
                str(args.posterior.with_suffix("")),
            ],
            check=True,
            cwd=REPO,
            env=dict(os.environ, PYTHONPATH=str(REPO)),
        )
    runs = []
    for _ in range(args.repeats):
        load = os.getloadavg()[0]
        times = one_run(args.posterior, args.rgb, executable)
        times["load_average"] = load
        runs.append(times)
    events = ("page", "loading", "first_frame", "panel")
    print(f"{'run':<5}" + "".join(f"{e + ' [s]':>17}" for e in events) + f"{'load avg':>10}")
    for i, r in enumerate(runs):
        print(
            f"{i:<5}"
            + "".join(f"{r[e]:>17.2f}" if e in r else f"{'-':>17}" for e in events)
            + f"{r['load_average']:>10.1f}"
        )
    median = {e: float(np.median([r[e] for r in runs if e in r])) for e in events if any(e in r for r in runs)}
    print("median " + ", ".join(f"{e} {v:.2f} s" for e, v in median.items()))
    result = {
        "what": "seconds from starting `gpdepth3d view` to each event in headless Chromium",
        "posterior": str(args.posterior),
        "rgb": str(args.rgb),
        "runs": runs,
        "median": median,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    sys.path.insert(0, str(REPO))
    from gpdepth3d.io import atomic_write

    atomic_write(args.out, lambda p: p.write_text(json.dumps(result, indent=2)))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
