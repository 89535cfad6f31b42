"""``gpdepth3d map`` from images alone (pycolmap SfM) on the shared sequences, and the sigma of pycolmap's points.

Usage::

    python bench/sfm.py [--out bench/results/sfm.json] [--sequences 7scenes hololens]

1. Each ``gpdepth3d map`` line of docs/mapping.md on ../shared/data without ``--poses`` runs as a user
   starts it (a fresh ``python -m gpdepth3d.cli`` process from the repository root): wall time, CPU time
   of the process (user + system, all threads), the load average before and after, and from its
   metrics.json the images registered, the pieces, each piece's metric scale with its bootstrap sigma,
   and the F-score at 5 cm of the map and of the MDE alone against the mesh fused from the sensor depth.
2. The depth sigma of the points of the SfM models that run wrote (``OUT/sparse/<k>``): every
   (point, image) observation is projected with the image's SfM pose and compared with the sensor depth
   at its pixel. With the scale that fits the sensor best (one factor per piece: a metric SLAM's points)
   the relative errors calibrate `PointSigmaRule` (`fit_sigma_rule`, ±2 sigma covering 95 %) on
   7-Scenes; the coverage of each rule is then measured on both sequences. With the scale the run took
   from the network, the coverage of the sigma the mapper was given (rule and scale uncertainty).

Wall-clock seconds on a shared machine: compare rows of one run. Results: a table on stdout and
``bench/results/sfm.json`` (written atomically); ``python bench/report.py`` renders them in docs/results.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shlex
import sys
import time
from pathlib import Path

import numpy as np
from map_recipes import run_command  # a sibling script: bench/ is on the path

REPO = Path(__file__).resolve().parents[1]
FIT_ON = "7scenes"
"""The sequence the sigma rule is fitted on; the other one confirms it."""


def recipes() -> dict[str, str]:
    """The docs' ``gpdepth3d map`` lines on the shared data without ``--poses``, by sequence folder name."""
    text = (REPO / "docs" / "mapping.md").read_text(encoding="utf-8")
    lines = [line.strip() for line in re.findall(r"^gpdepth3d map [^\n]*", text, flags=re.M)]
    lines = [line for line in lines if "../shared/data" in line and "--poses" not in line and "--points" not in line]
    return {re.search(r"\.\./shared/data/(\w+)", line).group(1): line for line in lines}


def run(line: str) -> dict:
    """Runs one command line in a fresh process; its wall and CPU time, load and metrics.json."""
    summary, process = run_command(line)
    pieces = summary["pieces"]
    metrics = summary.get("metrics") or {}
    return {
        "command": line,
        "output": process["output"],
        "process_wall_s": process["process_wall_s"],
        "process_cpu_s": process["process_cpu_s"],
        "frames": pieces["frames"],
        "registered": pieces["registered"],
        "pieces": pieces["pieces"],
        "timing_s": pieces["timing_s"],
        "fscore_map": (metrics.get("map") or {}).get("fscore"),
        "fscore_mde_only": (metrics.get("mde") or {}).get("fscore"),
        "loadavg_before": process["loadavg_before"],
        "loadavg_after": process["loadavg_after"],
    }


def _sequence_files(line: str):
    """Images, camera, sensor-depth reader arguments of a recipe line."""
    from gpdepth3d.datasets.posed import IMAGE_SUFFIXES, list_files, read_intrinsics
    from gpdepth3d.io import load_rgb

    argv = shlex.split(line)[1:]
    opt = {argv[i]: argv[i + 1] for i in range(0, len(argv) - 1) if argv[i].startswith("--")}
    files = list_files(str(REPO / opt["--images"]), IMAGE_SUFFIXES, "color", "images")
    h, w = load_rgb(files[0]).shape[:2]
    camera = read_intrinsics(opt["--intrinsics"] if "," in opt["--intrinsics"] else REPO / opt["--intrinsics"], w, h)
    depth_kw = {"depth": str(REPO / opt["--depth"])}
    if "--depth-invalid" in opt:
        depth_kw["depth_invalid"] = int(opt["--depth-invalid"])
    if "--depth-intrinsics" in opt:
        depth_kw["depth_intrinsics"] = str(REPO / opt["--depth-intrinsics"])
    return files, camera, depth_kw


def observations(model: Path, files: list[Path], camera, depth_kw: dict) -> dict[str, np.ndarray]:
    """Every (point, image) observation of a model against the sensor depth at its projected pixel.

    Returns arrays: ``z`` (model depth, model units), ``sensor`` (metres), ``distance`` (model units),
    ``reprojection_error`` (pixels), ``angle_deg`` (largest ray angle) of each valid observation.
    """
    from gpdepth3d.camera import transform_points
    from gpdepth3d.datasets.posed import PosedSequence
    from gpdepth3d.mapping.points.given_points import read_given_points
    from gpdepth3d.io.poses import invert_pose

    piece = read_given_points(model)[0]
    by_name = {Path(im.name).name: iid for iid, im in piece.model.images.items()}
    frames = [(f, by_name[f.name]) for f in files if f.name in by_name]
    seq = PosedSequence([f for f, _ in frames], np.tile(np.eye(4), (len(frames), 1, 1)), camera, **depth_kw)
    cols: dict[str, list] = {k: [] for k in ("z", "sensor", "distance", "reprojection_error", "angle_deg")}
    for k, (_, iid) in enumerate(frames):
        sensor = seq.frame(k).depth
        rows = piece.observed_by(iid)
        p_cam = transform_points(invert_pose(piece.model.images[iid].T_world_camera), piece.points[rows])
        front = p_cam[:, 2] > 0
        uv, _ = camera.project(p_cam[front])
        inside = camera.in_image(uv)
        iu = np.rint(uv[inside]).astype(np.int64)
        d = sensor[iu[:, 1], iu[:, 0]]
        ok = d > 0
        sel = rows[front][inside][ok]
        cols["z"].append(p_cam[front][inside][ok][:, 2])
        cols["sensor"].append(d[ok])
        cols["distance"].append(np.linalg.norm(p_cam[front][inside][ok], axis=1))
        cols["reprojection_error"].append(piece.reprojection_error[sel])
        cols["angle_deg"].append(piece.angle_deg[sel])
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}


def sigma_study(runs: dict[str, dict], lines: dict[str, str]) -> dict:
    """Fits the sigma rule on `FIT_ON` (sensor-fitted scale) and measures each rule's ±2 sigma coverage."""
    from gpdepth3d.mapping.points.given_points import PointSigmaRule, fit_sigma_rule, sigma_coverage

    obs: dict[str, list] = {}
    focal = {}
    for name, r in runs.items():
        files, camera, depth_kw = _sequence_files(lines[name])
        focal[name] = camera.fx
        obs[name] = []
        for k, piece in enumerate(r["pieces"]):
            model = Path(r["output"]) / "sparse" / str(k)
            if piece["error"] is None and model.is_dir():
                o = observations(model, files, camera, depth_kw)
                o["fitted_scale"] = float(np.median(o["sensor"] / o["z"]))
                o["run_scale"] = piece["scale"]["scale"]
                o["run_scale_rel_sigma"] = piece["scale"]["sigma"] / piece["scale"]["scale"]
                obs[name].append(o)

    def rel_errors(name, which):
        return np.concatenate([(o[which] * o["z"] - o["sensor"]) / o["sensor"] for o in obs[name]])

    def cat(name, key):
        return np.concatenate([o[key] for o in obs[name]])

    fitted = fit_sigma_rule(
        rel_errors(FIT_ON, "fitted_scale"),
        reprojection_error=cat(FIT_ON, "reprojection_error"),
        angle_deg=cat(FIT_ON, "angle_deg"),
        focal=focal[FIT_ON],
    )
    rules = {
        "flat 2 %": PointSigmaRule(relative=0.02, geometric=0.0),
        "reprojection and angle only": PointSigmaRule(relative=1e-6, geometric=1.0),
        "fitted": fitted,
        "default": PointSigmaRule(),
    }
    table: dict = {"fitted_on": FIT_ON, "rules": {k: vars(v) for k, v in rules.items()}, "sequences": {}}
    for name in obs:
        if not obs[name]:
            continue
        e_fit = rel_errors(name, "fitted_scale")
        row = {
            "observations": int(e_fit.size),
            "median_abs_rel_error": float(np.median(np.abs(e_fit))),
            # the network's scale against the one that fits the sensor, per piece (largest first)
            "scale_error": [o["run_scale"] / o["fitted_scale"] - 1.0 for o in obs[name]],
        }
        for rule_name, rule in rules.items():
            width = rule.sigma(
                np.ones_like(e_fit),
                reprojection_error=cat(name, "reprojection_error"),
                angle_deg=cat(name, "angle_deg"),
                focal=focal[name],
            )
            row[rule_name] = {
                "coverage_2sigma": sigma_coverage(e_fit, width),
                "median_sigma_rel": float(np.median(width)),
            }
        # as mapped: the network's scale, and the default rule widened by the scale's uncertainty
        e_run = rel_errors(name, "run_scale")
        base = PointSigmaRule().sigma(
            np.ones_like(e_run),
            reprojection_error=cat(name, "reprojection_error"),
            angle_deg=cat(name, "angle_deg"),
            focal=focal[name],
        )
        scale_rel = np.concatenate([np.full(o["z"].size, o["run_scale_rel_sigma"]) for o in obs[name]])
        row["as mapped"] = {
            "coverage_2sigma": sigma_coverage(e_run, np.sqrt(base**2 + scale_rel**2)),
            "median_abs_rel_error": float(np.median(np.abs(e_run))),
        }
        table["sequences"][name] = row
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "sfm.json")
    parser.add_argument("--sequences", nargs="*", default=None, help="folder names under ../shared/data")
    parser.add_argument(
        "--sigma-only", action="store_true", help="keep the runs of --out, measure the sigma again on their models"
    )
    args = parser.parse_args()
    sys.path.insert(0, str(REPO))
    from gpdepth3d.io import write_json

    lines = {k: v for k, v in recipes().items() if args.sequences is None or k in args.sequences}
    runs = json.loads(args.out.read_text())["runs"] if args.sigma_only else {}
    for name, line in lines.items():
        if args.sigma_only:
            continue
        runs[name] = r = run(line)
        scale = r["pieces"][0]["scale"] if r["pieces"] else None
        print(
            f"{name:9s} registered {r['registered']}/{r['frames']} in {len(r['pieces'])} piece(s), "
            f"scale {scale['scale']:.4f} ± {scale['sigma']:.4f}, F map {r['fscore_map']}, "
            f"MDE alone {r['fscore_mde_only']}, {r['process_wall_s']:.0f} s wall, {r['process_cpu_s']:.0f} s CPU "
            f"(load {r['loadavg_before'][0]:.1f})",
            flush=True,
        )
    study = sigma_study(runs, lines) if FIT_ON in runs else None
    if study:
        for name, row in study["sequences"].items():
            cov = ", ".join(f"{k} {v['coverage_2sigma']:.1%}" for k, v in row.items() if isinstance(v, dict))
            print(f"{name:9s} ±2σ coverage: {cov}")
    previous = json.loads(args.out.read_text()) if args.sigma_only else {}
    write_json(
        args.out,
        {
            **previous,
            "date": previous.get("date") or time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "runs": runs,
            "sigma": study,
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
