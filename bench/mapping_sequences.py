"""Mapping on the two shared posed sequences with one set of defaults: mesh F-score, points, sigma, time.

Usage::

    python bench/mapping_sequences.py [--data ../shared/data] [--model ../shared/models/fast_depth_224.tflite]
                                      [--sequences 7scenes hololens] [--frames N] [--colmap]
                                      [--set FIELD=VALUE ...] [--out bench/results/mapping_sequences.json]
                                      [--save-frames DIR] [--perturb CM,DEG ...] [--seed S]
    python bench/mapping_sequences.py --refuse DIR --sweep weight_threshold=0.2,0.5 [--sweep FIELD=V1,V2 ...]
    python bench/mapping_sequences.py --select gp.lengthscale=32.0,64.0 [--select FIELD=V1,V2[@SEQ] ...]
                                      [--choose-on hololens]
    python bench/mapping_sequences.py --rechoose [--choose-on hololens]

Per sequence (``7scenes``: 60 frames 640x480; ``hololens``: 94 frames 540x360, ~30 m walk), the
`gpdepth3d.mapping.Mapper` with the default `MapperConfig` at a 320-px working width, FastDepth as
the MDE, the library's own triangulated points (no sensor depth used), and in the same pass:

* ``mde_only``: the MDE depth of every frame fused with uniform weights (``MapperConfig(refine=False)``);
* ``reference``: the sensor depth fused with uniform weights (the mesh every other one is scored against);
* with ``--colmap``: a second Mapper fed pycolmap's points (`gpdepth3d.mapping.points.colmap_points`; features,
  matching and triangulation with the sequence's poses held fixed) as SLAM map points, no own points,
  each with a depth sigma of ``--colmap-sigma`` times its distance.

Measured: `gpdepth3d.metrics.mesh_metrics` at 5 cm (50k samples), the points per frame, the +-2 sigma
coverage of the points against the sensor depth, frames fused with points / without, and the
milliseconds of ``Mapper.add_frame`` (its own stages plus the MDE run on the frame it adds).
``--perturb CM,DEG`` (repeatable) maps each sequence again with every pose given to the Mapper and to the
MDE-only volume moved by CM centimetres and turned by DEG degrees, in random directions, independently per frame
(`perturb_poses`, seeded by ``--seed``): a SLAM back-end's poses; the reference volume keeps the sensor's poses.
``--set`` overrides a MapperConfig field (``window=8``) or a nested one (``fusion.sigma_ref=0.1``,
``triangulation.max_features=800``) for experiments; the JSON records the config used. Timings
are wall-clock on a shared 2-core machine: compare within one run. Results go to
``bench/results/mapping_sequences.json`` (written atomically).

``--save-frames DIR`` also writes what the Mapper fused (depth, variance, pose, RGB and point count of
every frame, and the sensor depth) to ``DIR/<sequence>.npz``; ``--refuse DIR`` then skips the Mapper and
fuses those frames again for every combination of the ``--sweep`` `FusionConfig` values (weights as the
Mapper computes them), scoring each mesh as above: a fusion setting is tried without running the Mapper again.
Its results go to ``bench/results/mapping_fusion_sweep.json``.

``--select FIELD=V1,V2`` runs the Mapper with each value of one `MapperConfig` field (the others at their
defaults) on both sequences, takes the value of best F on ``--choose-on`` (or on SEQ for
``FIELD=V1,V2@SEQ``) among those whose points keep an honest sigma there (+-2 sigma covers 90-98 % of
their errors) and that the other sequence confirms (its F there within `CONFIRM_MARGIN` of the best
value's): chosen on one sequence, confirmed on the other (`choose`). ``--rechoose`` applies that rule
again to the results file without running the Mapper. Results go to
``bench/results/mapping_selection.json``.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import platform
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
WORKING_WIDTH = 320


def load_hololens(root: Path, max_frames: int | None = None) -> list:
    """The HoloLens layout: images/*.png, depth/*.png (uint16 mm, 0 invalid), poses_images.txt, K.txt."""
    import cv2

    from gpdepth3d.camera import PinholeCamera
    from gpdepth3d.datasets.base import Frame

    K = np.loadtxt(root / "K.txt").reshape(3, 3)
    poses = np.loadtxt(root / "poses_images.txt").reshape(-1, 4, 4)
    names = sorted(p.name for p in (root / "images").glob("*.png"))
    if len(names) != len(poses):
        raise SystemExit(f"{root}: {len(names)} images but {len(poses)} poses")
    frames = []
    for name, pose in list(zip(names, poses))[:max_frames]:
        rgb = cv2.cvtColor(cv2.imread(str(root / "images" / name), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(root / "depth" / name), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
        camera = PinholeCamera.from_K(K, rgb.shape[1], rgb.shape[0])
        frames.append(Frame(name=name, rgb=rgb, camera=camera, depth=depth, pose=pose))
    return frames


def load_7scenes(root: Path, max_frames: int | None = None) -> list:
    """7-Scenes frames with the depth registered to the colour camera (the reader's default)."""
    from gpdepth3d.datasets.sevenscenes import SevenScenes

    reader = SevenScenes(root)
    n = len(reader) if max_frames is None else min(len(reader), max_frames)
    return [reader[i] for i in range(n)]


LOADERS = {"7scenes": load_7scenes, "hololens": load_hololens}


def perturb_poses(poses: list, cm: float, deg: float, seed: int = 0) -> list:
    """Each ``T_world_camera`` with its own independent error: as a SLAM back-end's poses are off from the truth.

    Frame k's camera is turned by exactly ``deg`` degrees about a random axis and moved by exactly ``cm``
    centimetres in a random direction (both uniform on the sphere, in the camera's frame):
    ``T' = T @ [exp(w) | d]``. Seeded (``numpy.random.default_rng(seed)``), so a run is repeatable.

    Args:
        poses: 4x4 ``T_world_camera`` poses.
        cm: Translation error of every frame, centimetres (>= 0).
        deg: Rotation error of every frame, degrees (>= 0).
        seed: Seed of the random directions.

    Returns:
        The perturbed poses (new arrays), in order.
    """
    import cv2

    if not (np.isfinite(cm) and np.isfinite(deg) and cm >= 0 and deg >= 0):
        raise ValueError(f"perturbation: cm and deg must be finite and >= 0, got {cm}, {deg}")
    rng = np.random.default_rng(seed)
    out = []
    for T in poses:
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        direction /= np.linalg.norm(direction)
        delta = np.eye(4)
        delta[:3, :3] = cv2.Rodrigues(axis * np.radians(deg))[0]
        delta[:3, 3] = direction * cm / 100.0
        out.append(np.asarray(T, dtype=np.float64) @ delta)
    return out


def _override(config, key: str, value):
    """``replace`` on a frozen config with a dotted field name (``fusion.sigma_ref``)."""
    head, _, rest = key.partition(".")
    if rest:
        return replace(config, **{head: _override(getattr(config, head), rest, value)})
    return replace(config, **{head: value})


def load_sequence(data: Path, seq: str, max_frames: int | None, mde) -> tuple[list, list]:
    """A shared sequence's frames and each frame's MDE depth with the seconds the network took."""
    frames = LOADERS[seq](data / seq, max_frames)
    mde_depths = []
    for f in frames:
        t0 = time.perf_counter()
        mde_depths.append((mde(f.rgb), time.perf_counter() - t0))
    return frames, mde_depths


def mapper_config(frames: list | None = None, sets: list[str] = ()):
    """The default `MapperConfig` (at the 320-px working width of ``frames`` when given), with ``--set`` overrides."""
    from gpdepth3d.mapping.mapper_config import MapperConfig

    config = MapperConfig() if frames is None else MapperConfig(working_scale=WORKING_WIDTH / frames[0].camera.width)
    for item in sets:
        key, value = item.split("=", 1)
        config = _override(config, key, ast.literal_eval(value))
    return config


def point_coverage(result, frame, camera) -> tuple[int, int]:
    """(points within +-2 sigma of the sensor depth, points with a sensor depth) of one frame."""
    sp = result.sparse
    if not len(sp):
        return 0, 0
    iu = np.clip(np.rint(sp.u).astype(np.int64), 0, camera.width - 1)
    iv = np.clip(np.rint(sp.v).astype(np.int64), 0, camera.height - 1)
    d = frame.depth[iv, iu]
    ok = np.isfinite(d) & (d > 0) & np.isfinite(sp.sigma)
    inside = np.abs(sp.depth[ok] - d[ok]) <= 2 * sp.sigma[ok]
    return int(inside.sum()), int(ok.sum())


def save_fused_frames(path: Path, fused: list, sensor: list, camera) -> Path:
    """Writes what a Mapper pass fused (`run_sequence`'s ``fused`` records) and the sensor depth to one ``.npz``.

    Per frame: the fused depth and its variance (working size, m and m^2), the pose, the working-size
    RGB, the points it had, and the sensor depth at the working size (the reference), so that
    `refuse` can fuse the same posteriors again with other `FusionConfig` settings in seconds.
    """
    from gpdepth3d.io import atomic_path

    stack = {k: np.stack([f[k] for f in fused]) for k in ("depth", "variance", "pose", "rgb")}
    stack["points"] = np.array([f["points"] for f in fused], np.int64)
    stack["sensor_depth"] = np.stack([s["depth"] for s in sensor]).astype(np.float32)
    stack["sensor_pose"] = np.stack([s["pose"] for s in sensor])
    stack["sensor_rgb"] = np.stack([s["rgb"] for s in sensor])
    stack["camera"] = np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height])
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **stack)
    return path


def refuse(path: Path, fusion_configs: dict) -> dict:
    """Fuses the frames `save_fused_frames` wrote with each of ``fusion_configs`` (name -> FusionConfig) and scores
    each mesh against the sensor-depth mesh (F at 5 cm, precision, recall); weights as the `Mapper` computes them."""
    from gpdepth3d.camera import PinholeCamera
    from gpdepth3d.mapping.tsdf.fusion import TSDFFusion
    from gpdepth3d.metrics import mesh_metrics

    data = np.load(path)
    fx, fy, cx, cy, width, height = data["camera"]
    camera = PinholeCamera(fx, fy, cx, cy, int(width), int(height))
    first = next(iter(fusion_configs.values()))
    ref = TSDFFusion(camera, replace(first, weighting="uniform", integrate_variance=False))
    for depth, pose, rgb in zip(data["sensor_depth"], data["sensor_pose"], data["sensor_rgb"]):
        ref.integrate(depth, pose, rgb=rgb)
    reference = ref.extract_mesh()
    out = {}
    for name, cfg in fusion_configs.items():
        volume = TSDFFusion(camera, replace(cfg, integrate_variance=False))
        for depth, var, pose, rgb, points in zip(
            data["depth"], data["variance"], data["pose"], data["rgb"], data["points"]
        ):
            weights = volume.weights_for(var, depth, points=int(points))
            if weights is None or np.any(weights > 0):
                volume.integrate(depth, pose, rgb=rgb, weights=weights, variance=var)
        mesh = volume.extract_mesh(allow_empty=True)
        out[name] = mesh_metrics(mesh, reference) if len(mesh.faces) else None
        if out[name]:
            print(f"  {name}: F {out[name]['fscore']:.3f} P {out[name]['precision']:.3f} R {out[name]['recall']:.3f}")
    return out


def run_sequence(
    frames: list, mde_depths: list, config, *, map_points=None, save_frames: Path | None = None, poses=None
) -> dict:
    """One Mapper pass (plus the MDE-only and reference volumes) over a loaded sequence; with ``save_frames``
    what it fused is also written there (`save_fused_frames`).

    ``poses`` (default: the frames' own) are the poses the Mapper and the MDE-only volume are given (e.g.
    `perturb_poses`); the reference volume always fuses the sensor depth with the frames' own poses."""
    from gpdepth3d.mapping.tsdf.fusion import TSDFFusion
    from gpdepth3d.mapping.frame_inputs import resize_depth
    from gpdepth3d.mapping.mapper import Mapper
    from gpdepth3d.metrics import mesh_metrics

    camera = frames[0].camera
    given = [f.pose for f in frames] if poses is None else list(poses)
    mapper = Mapper(camera, config)
    work = mapper.work_camera
    uniform = replace(config.fusion, weighting="uniform", integrate_variance=False)
    mde_volume, ref_volume = TSDFFusion(work, uniform), TSDFFusion(work, uniform)
    rows, results, fused, sensor = [], [], [], []

    def record(result) -> None:
        frame = frames[result.keyframe_id]
        if save_frames is not None:
            work_rgb = mapper._work_rgb(frame.rgb)
            sensor.append({"depth": resize_depth(frame.depth, work.shape), "pose": frame.pose, "rgb": work_rgb})
            if result.fused:
                fused.append(
                    {
                        "depth": result.depth.astype(np.float32),
                        "variance": result.variance.astype(np.float32),
                        "pose": given[result.keyframe_id],
                        "rgb": work_rgb,
                        "points": len(result.sparse) if config.refine else 0,
                    }
                )
        if result.mde.size:
            mde_volume.integrate(result.mde, given[result.keyframe_id], rgb=mapper._work_rgb(frame.rgb))
        ref_volume.integrate(resize_depth(frame.depth, work.shape), frame.pose, rgb=mapper._work_rgb(frame.rgb))
        inside, known = point_coverage(result, frame, camera)
        rows.append(
            {
                "frame": result.keyframe_id,
                "points": len(result.sparse),
                "fused": result.fused,
                "within_2sigma": inside,
                "with_sensor_depth": known,
                "error": result.error,
                "fallback_weight": result.fallback_weight,
                "map_scale": result.map_scale,
                "pose_warning": any("feature tracks agree" in w for w in result.warnings),
                "mde_fallback": bool(getattr(result, "mde_fallback", False)),
            }
        )
        results.append(result)

    add_ms = []
    for i, frame in enumerate(frames):
        t0 = time.perf_counter()
        pts, sigma = (None, None) if map_points is None else map_points.get(i, (np.zeros((0, 3)), None))
        if sigma is not None and not len(sigma):
            sigma = None
        result = mapper.add_frame(
            frame.rgb, given[i], mde_depth=mde_depths[i][0], keyframe_id=i, map_points_world=pts, map_points_sigma=sigma
        )
        add_ms.append(1000 * (time.perf_counter() - t0 + mde_depths[i][1]))
        if result is not None:
            record(result)
    for result in mapper.flush():
        record(result)
    reference = ref_volume.extract_mesh()
    if save_frames is not None:
        save_fused_frames(save_frames, fused, sensor, work)
    out = {}
    for name, volume in (("mapper", mapper.fusion), ("mde_only", mde_volume)):
        mesh = volume.extract_mesh(allow_empty=True)
        out[name] = mesh_metrics(mesh, reference) if len(mesh.faces) else None
    inside = sum(r["within_2sigma"] for r in rows)
    known = sum(r["with_sensor_depth"] for r in rows)
    points = np.array([r["points"] for r in rows])
    return {
        "metrics": out,
        "fscore": out["mapper"]["fscore"] if out["mapper"] else 0.0,
        "fscore_mde_only": out["mde_only"]["fscore"] if out["mde_only"] else 0.0,
        "points_per_frame_median": float(np.median(points)),
        "frames_with_under_20_points": int(np.sum(points < 20)),
        "points_within_2sigma": inside / known if known else None,
        "points_with_sensor_depth": known,
        "frames_fused": int(sum(r["fused"] for r in rows)),
        "frames_pose_warned": int(sum(r["pose_warning"] for r in rows)),
        "frames_mde_fallback": int(sum(r["mde_fallback"] for r in rows)),
        "frame_errors": [r["error"] for r in rows if r["error"]],
        "mde_ms": {"median": float(np.median([1000 * t for _, t in mde_depths]))},
        "add_frame_ms": {
            "median": float(np.median(add_ms)),
            "mean": float(np.mean(add_ms)),
            "p90": float(np.percentile(add_ms, 90)),
        },
        "resolution": list(work.shape),
        "per_frame": rows,
    }


def colmap_run(frames: list, mde_depths: list, config, relative_sigma: float) -> dict:
    """pycolmap's points (poses held fixed) as the Mapper's map points, each frame given those it observes."""
    import tempfile

    from gpdepth3d.mapping.points.colmap_points import triangulate_with_colmap
    from gpdepth3d.io.poses import read_colmap_model

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        model = read_colmap_model(
            triangulate_with_colmap([f.rgb for f in frames], [f.pose for f in frames], frames[0].camera, work)
        )
    seconds = time.perf_counter() - t0
    by_frame = {}
    for image_id, image in model.images.items():
        pts = model.map_points(image_id)
        by_frame[int(image.name[:5])] = (
            pts,
            relative_sigma * np.linalg.norm(pts - frames[int(image.name[:5])].pose[:3, 3], axis=1),
        )
    row = run_sequence(frames, mde_depths, config, map_points=by_frame)
    return {
        "fscore": row["fscore"],
        "points": int(len(model.points)),
        "seconds_pycolmap": seconds,
        "relative_sigma_given": relative_sigma,
        "points_within_2sigma": row["points_within_2sigma"],
        "points_per_frame_median": row["points_per_frame_median"],
        "metrics": row["metrics"],
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--model", type=Path, default=REPO.parent / "shared" / "models" / "fast_depth_224.tflite")
    parser.add_argument("--sequences", nargs="+", default=["7scenes", "hololens"], choices=sorted(LOADERS))
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--colmap", action="store_true", help="also map with pycolmap's points")
    parser.add_argument(
        "--colmap-sigma", type=float, default=0.03, help="their depth sigma, a fraction of the distance"
    )
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    parser.add_argument(
        "--perturb",
        action="append",
        default=[],
        metavar="CM,DEG",
        help="also map with every pose perturbed by CM centimetres and DEG degrees (perturb_poses; repeatable)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of --perturb")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--save-frames", type=Path, default=None, metavar="DIR", help="write DIR/<sequence>.npz")
    parser.add_argument(
        "--refuse",
        type=Path,
        default=None,
        metavar="DIR",
        help="no Mapper: fuse DIR/<sequence>.npz (from --save-frames) again for each --sweep setting",
    )
    parser.add_argument(
        "--sweep", action="append", default=[], metavar="FIELD=V1,V2", help="FusionConfig values (with --refuse)"
    )
    parser.add_argument(
        "--select", action="append", default=[], metavar="FIELD=V1,V2", help="MapperConfig values to choose from"
    )
    parser.add_argument("--choose-on", default="hololens", choices=sorted(LOADERS))
    parser.add_argument("--rechoose", action="store_true", help="apply the --select rule again to --out's values")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="default: bench/results/mapping_sequences.json, with --refuse bench/results/mapping_fusion_sweep.json",
    )
    args = parser.parse_args(argv)
    results = REPO / "bench" / "results"
    if args.out is None:
        selecting = args.select or args.rechoose
        name = "mapping_fusion_sweep" if args.refuse else "mapping_selection" if selecting else "mapping_sequences"
        args.out = results / f"{name}.json"

    import torch

    torch.set_num_threads(args.threads)
    from gpdepth3d.io import atomic_write, to_jsonable
    from gpdepth3d.mde.tflite import FastDepthTFLite

    if args.refuse is not None:
        return refuse_main(args)
    if args.rechoose:
        return rechoose_main(args)
    mde = FastDepthTFLite(args.model)
    if args.select:
        return select_main(args, mde)
    load_before = os.getloadavg()[0]
    report = {"sequences": {}, "overrides": args.set, "perturb": args.perturb, "seed": args.seed}
    for seq in args.sequences:
        frames, mde_depths = load_sequence(args.data, seq, args.frames, mde)
        config = mapper_config(frames, args.set)
        save = None if args.save_frames is None else args.save_frames / f"{seq}.npz"
        if save is not None:
            save.parent.mkdir(parents=True, exist_ok=True)
        row = run_sequence(frames, mde_depths, config, save_frames=save)
        row["frames"] = len(frames)
        row["fscore_gain_over_mde_only"] = row["fscore"] - row["fscore_mde_only"]
        if args.colmap:
            row["colmap"] = colmap_run(frames, mde_depths, replace(config, triangulate=False), args.colmap_sigma)
        row["config"] = asdict(config)
        report["sequences"][seq] = row
        _print_row(seq, row)
        row["perturbed"] = {}
        for item in args.perturb:
            cm, deg = (float(v) for v in item.split(","))
            poses = perturb_poses([f.pose for f in frames], cm, deg, seed=args.seed)
            sub = run_sequence(frames, mde_depths, config, poses=poses)
            sub.pop("per_frame")
            sub.update(cm=cm, deg=deg, seed=args.seed, frames=len(frames))
            row["perturbed"][item] = sub
            _print_row(f"{seq} poses perturbed by {cm:g} cm, {deg:g} deg", sub)
    report["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    report["machine"] = {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "load_average_1min": {"before": load_before, "after": os.getloadavg()[0]},
    }
    atomic_write(args.out, lambda tmp: Path(tmp).write_text(json.dumps(to_jsonable(report), indent=1)))
    return report


def _print_row(name: str, row: dict) -> None:
    print(
        f"{name}: F {row['fscore']:.3f} (MDE only {row['fscore_mde_only']:.3f}), points/frame "
        f"{row['points_per_frame_median']:.0f}, <20 points in {row['frames_with_under_20_points']} frames, "
        f"+-2 sigma {row['points_within_2sigma']}, pose warnings {row['frames_pose_warned']}, MDE fallbacks "
        f"{row['frames_mde_fallback']}, add_frame median {row['add_frame_ms']['median']:.0f} ms"
        + (f", pycolmap points F {row['colmap']['fscore']:.3f}" if "colmap" in row else ""),
        flush=True,
    )


SIGMA_COVERAGE = (0.90, 0.98)
"""The +-2 sigma coverage of the points against the sensor depth that an honest sigma gives (``--select``)."""


CONFIRM_MARGIN = 0.01
"""A value is confirmed on the other sequence when its F there is within this of the best value's (``--select``):
about twice the spread of F between repeated runs."""


def _honest(coverage: float | None) -> bool:
    return coverage is None or SIGMA_COVERAGE[0] <= coverage <= SIGMA_COVERAGE[1]


def choose(rows: dict, choose_on: str) -> str:
    """The value of best F on ``choose_on`` among those with an honest sigma there and confirmed on the others.

    Confirmed: F on each other sequence within `CONFIRM_MARGIN` of the best value's there. When no honest
    value is confirmed, the honest value the other sequences do best with (their smallest F the largest).

    Args:
        rows: value -> sequence -> {"fscore", "points_within_2sigma"}.
        choose_on: The sequence the value is chosen on.
    """
    others = [q for q in next(iter(rows.values())) if q != choose_on]
    best = {q: max(r[q]["fscore"] for r in rows.values()) for q in others}
    honest = [v for v in rows if _honest(rows[v][choose_on]["points_within_2sigma"])] or list(rows)
    confirmed = [v for v in honest if all(rows[v][q]["fscore"] >= best[q] - CONFIRM_MARGIN for q in others)]
    if confirmed:
        return max(confirmed, key=lambda v: rows[v][choose_on]["fscore"])
    return max(honest, key=lambda v: min(rows[v][q]["fscore"] for q in others))


def select_main(args, mde) -> dict:
    """``--select``: each value of each field on both sequences; the best on ``--choose-on``, confirmed on the other."""
    from gpdepth3d.io import atomic_write, to_jsonable

    loaded = {seq: load_sequence(args.data, seq, args.frames, mde) for seq in args.sequences}
    report = {"choose_on": args.choose_on, "fields": {}}
    for item in args.select:
        key, values = item.split("=", 1)
        values, _, choose_on = values.partition("@")
        choose_on = choose_on or args.choose_on
        rows = {}
        for value in values.split(","):
            rows[value] = {}
            for seq, (frames, mde_depths) in loaded.items():
                config = _override(mapper_config(frames), key, ast.literal_eval(value))
                run = run_sequence(frames, mde_depths, config)
                rows[value][seq] = {
                    "fscore": run["fscore"],
                    "points_within_2sigma": run["points_within_2sigma"],
                    "metrics": run["metrics"]["mapper"],
                }
                print(f"{key}={value} {seq}: F {run['fscore']:.3f}", flush=True)
        report["fields"][key] = {"values": rows, "chosen": choose(rows, choose_on), "chosen_on": choose_on}
    report["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    report["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count()}
    atomic_write(args.out, lambda tmp: Path(tmp).write_text(json.dumps(to_jsonable(report), indent=1)))
    return report


def rechoose_main(args) -> dict:
    """``--rechoose``: every field of a ``--select`` results file chosen again on ``--choose-on`` (`choose`)."""
    from gpdepth3d.io import atomic_write

    path = args.out
    report = json.loads(path.read_text(encoding="utf-8"))
    for entry in report["fields"].values():
        entry["chosen"], entry["chosen_on"] = choose(entry["values"], args.choose_on), args.choose_on
    report["choose_on"] = args.choose_on
    atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(report, indent=1)))
    return report


def refuse_main(args) -> dict:
    """``--refuse``: every combination of the ``--sweep`` values (on top of the Mapper's fusion and ``--set``)."""
    import itertools

    from gpdepth3d.io import atomic_write, to_jsonable

    base = mapper_config(sets=args.set)
    axes = []
    for item in args.sweep:
        key, values = item.split("=", 1)
        axes.append([(key, ast.literal_eval(v)) for v in values.split(",")])
    configs = {}
    for combo in itertools.product(*axes):
        cfg = base.fusion
        for key, value in combo:
            cfg = _override(cfg, key, value)
        configs[" ".join(f"{k}={v}" for k, v in combo) or "default"] = cfg
    report = {"sweep": args.sweep, "overrides": args.set, "sequences": {}}
    for seq in args.sequences:
        print(seq, flush=True)
        metrics = refuse(args.refuse / f"{seq}.npz", configs)
        report["sequences"][seq] = {
            name: {"fusion": asdict(configs[name]), "metrics": m} for name, m in metrics.items()
        }
    report["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count()}
    atomic_write(args.out, lambda tmp: Path(tmp).write_text(json.dumps(to_jsonable(report), indent=1)))
    return report


if __name__ == "__main__":
    main()
