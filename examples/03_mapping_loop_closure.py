"""Dense mapping with a loop closure: fuse 7-Scenes keyframes with one drifted pose, then correct it.

    python examples/03_mapping_loop_closure.py --data ../shared/data/7scenes --output outputs/example03

A SLAM back-end hands the `Mapper` posed keyframes and map points. Here the keyframes are the
first ``--frames`` frames of the 7-Scenes sequence, the depth network is FastDepth (TFLite), and
the map points stand in for a back-end's map: 150 Kinect depth samples per frame lifted to the
world with the keyframe's pose (measured points, not invented ones). Before the "loop closure" the
middle keyframe carries a drifted pose (10 degrees, 20 cm off), and its map points drift with it, as a
SLAM back-end's do; the map is fused with them (``mesh_before.ply``: that keyframe's surface is misplaced). Then the back-end's corrected pose arrives: `Mapper.update_poses`
re-integrates only the TSDF blocks that keyframe reached (``mesh_after.ply``). Both meshes are
compared with the mesh fused from the Kinect depth (``mesh_reference.ply``), as is the corrected keyframe's own
surface before and after (what a loop closure fixes), and the corrected
volume with fusing every keyframe from scratch with the corrected poses (it must be identical).
The map (volume and keyframe store) is saved to ``map/`` and loaded back (within its stored precision).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

import gpdepth3d as g
from gpdepth3d.datasets.sevenscenes import SevenScenes
from gpdepth3d.mapping import SEVEN_SCENES_RGB_K
from gpdepth3d.metrics import mesh_metrics


def _drifted(T: np.ndarray, degrees: float, metres: float) -> np.ndarray:
    import cv2

    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.array([0.0, np.deg2rad(degrees), 0.0]))[0] @ T[:3, :3]
    out[:3, 3] += [metres, 0.0, 0.0]
    return out


def _voxels(fusion: g.TSDFFusion) -> dict:
    vox = fusion.voxels()
    order = np.lexsort(vox["coords"].T)
    return {k: v[order] for k, v in vox.items()}


def _surface_distance(keyframe, camera: g.PinholeCamera, reference_samples: np.ndarray) -> float:
    """Median distance from a keyframe's fused depth, placed in the world by its pose, to the reference, metres."""
    from scipy.spatial import cKDTree

    pts, _ = camera.backproject(keyframe.depth)
    world = pts @ keyframe.T_world_camera[:3, :3].T + keyframe.T_world_camera[:3, 3]
    return float(np.median(cKDTree(reference_samples).query(world)[0]))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/7scenes"), help="a 7-Scenes folder")
    parser.add_argument(
        "--models", type=Path, default=Path("../shared/models"), help="folder holding FastDepth (fast_depth_224.tflite)"
    )
    parser.add_argument("--frames", type=int, default=8, help="number of keyframes")
    parser.add_argument("--output", type=Path, default=Path("outputs/example03"), help="output folder")
    args = parser.parse_args(argv)
    reader = SevenScenes(args.data)
    frames = [reader[i] for i in range(min(args.frames, len(reader)))]
    camera = g.PinholeCamera.from_K(SEVEN_SCENES_RGB_K, frames[0].camera.width, frames[0].camera.height)
    config = g.MapperConfig(working_scale=0.25, triangulate=False)
    mapper = g.Mapper(camera, config, mde=g.load_frontend("fastdepth", models_dir=args.models))
    reference = g.TSDFFusion(frames[0].camera.resized(160, 120), replace(config.fusion, weighting="uniform"))

    rng = np.random.default_rng(0)
    drifted_id = len(frames) // 2
    true_poses = {}
    for i, f in enumerate(frames):
        pts, _ = f.camera.backproject(f.depth)  # Kinect points (depth camera) -> world: the "map points"
        pts = pts[rng.choice(len(pts), 150, replace=False)]
        pose = _drifted(f.pose, 10.0, 0.20) if i == drifted_id else f.pose
        world = pts @ pose[:3, :3].T + pose[:3, 3]  # a drifted keyframe's points drift with it
        result = mapper.add_frame(f.rgb, pose, map_points_world=world, map_points_sigma=0.02, keyframe_id=i)
        true_poses[i] = f.pose
        reference.integrate(f.resized(0.25).depth, f.pose)
        print(
            f"keyframe {i}: {result.map_points.used} map points, "
            + ", ".join(f"{k} {1000 * v:.0f} ms" for k, v in result.timings.items())
            + ("" if result.fused else f"; not fused: {result.error}")
        )

    args.output.mkdir(parents=True, exist_ok=True)
    ref_mesh = reference.extract_mesh()
    g.save_mesh(ref_mesh, args.output / "mesh_reference.ply")
    before = mapper.mesh()
    g.save_mesh(before, args.output / "mesh_before.ply")
    m_before = mesh_metrics(before, ref_mesh, samples=20_000)
    ref_samples = ref_mesh.sample(50_000)
    off_before = _surface_distance(mapper.keyframes[drifted_id], mapper.work_camera, ref_samples)

    update = mapper.update_poses({drifted_id: true_poses[drifted_id]})
    after = mapper.mesh()
    g.save_mesh(after, args.output / "mesh_after.ply")
    m_after = mesh_metrics(after, ref_mesh, samples=20_000)
    off_after = _surface_distance(mapper.keyframes[drifted_id], mapper.work_camera, ref_samples)
    print(
        f"update_poses: keyframe {drifted_id} moved, {len(update.reintegrated)} keyframes re-integrated over "
        f"{update.blocks} blocks in {update.seconds:.2f} s"
    )
    print(
        f"keyframe {drifted_id}'s surface, median distance to the Kinect mesh: {100 * off_before:.1f} cm with the "
        f"drifted pose, {100 * off_after:.1f} cm with the corrected one"
    )
    # the whole map's F barely moves either way: one keyframe of several, whose neighbours cover its surface too
    print(f"F-score at 5 cm against the Kinect mesh: before {m_before['fscore']:.3f}, after {m_after['fscore']:.3f}")

    scratch = g.TSDFFusion(mapper.work_camera, mapper.fusion.config)
    for kf in mapper.keyframes.values():
        scratch.integrate(
            kf.depth,
            kf.T_world_camera,
            rgb=kf.rgb,
            weights=scratch.weights_for(kf.variance, kf.depth, points=kf.points),
            variance=kf.variance,
        )
    a, b = _voxels(mapper.fusion), _voxels(scratch)
    identical = a["coords"].shape == b["coords"].shape and all(np.array_equal(a[k], b[k]) for k in a)
    print(f"volume after update_poses identical to fusing from scratch with the corrected poses: {identical}")

    mapper.save(args.output / "map")
    loaded = g.Mapper.load(args.output / "map")
    reloaded = _voxels(loaded.fusion)
    # a saved map stores the volume compactly (16-bit distances, half-precision weights, 8-bit colours)
    same_after_load = np.array_equal(a["coords"], reloaded["coords"]) and all(
        np.allclose(a[k], reloaded[k], rtol=2.0**-10, atol=0.5 / 255) for k in a if k != "coords"
    )
    print(f"saved the map to {args.output / 'map'}; loaded back within its stored precision: {same_after_load}")
    return {
        "keyframe_distance_before": off_before,
        "keyframe_distance_after": off_after,
        "fscore_before": m_before["fscore"],
        "fscore_after": m_after["fscore"],
        "reintegrated": list(update.reintegrated),
        "blocks": update.blocks,
        "identical_to_scratch": identical,
        "identical_after_load": same_after_load,
        "faces_before": len(before.faces),
        "faces_after": len(after.faces),
    }


if __name__ == "__main__":
    main()
