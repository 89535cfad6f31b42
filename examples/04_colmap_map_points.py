"""Maps a posed sequence with the 3-D points of a system we did not write: COLMAP (pycolmap).

pycolmap extracts SIFT features, matches each image with the next ones and triangulates points with
the sequence's poses held fixed; the `Mapper` then refines FastDepth's depth with those points (each
given a σ of 3 % of its distance) and fuses the frames into a mesh. Any COLMAP model works the same
way: `read_colmap_model("sparse/0")` gives the poses and points of a reconstruction you ran yourself.

    python examples/04_colmap_map_points.py --data ../shared/data/hololens --frames 20 --output outputs/example04
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import gpdepth3d as g
from gpdepth3d.io import load_rgb
from gpdepth3d.mapping.points.colmap_points import triangulate_with_colmap
from gpdepth3d.io.poses import read_colmap_model, read_flat_poses


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/hololens"), help="the HoloLens folder")
    parser.add_argument("--models", type=Path, default=Path("../shared/models"), help="folder with FastDepth")
    parser.add_argument("--frames", type=int, default=20, help="number of images")
    parser.add_argument("--output", type=Path, default=Path("outputs/example04"), help="output folder")
    args = parser.parse_args(argv)

    paths = sorted((args.data / "images").glob("*.png"))[: args.frames]
    rgbs = [load_rgb(p) for p in paths]
    poses = read_flat_poses(args.data / "poses_images.txt").poses[: len(paths)]
    height, width = rgbs[0].shape[:2]
    camera = g.PinholeCamera.from_K(np.loadtxt(args.data / "K.txt"), width, height)

    model = read_colmap_model(triangulate_with_colmap(rgbs, poses, camera, args.output / "colmap"))
    frame = {image_id: int(Path(image.name).stem) for image_id, image in model.images.items()}  # k -> "0000k.png"

    mde = g.load_frontend("fastdepth", models_dir=args.models)
    mapper = g.Mapper(camera, g.MapperConfig(working_scale=320 / width, triangulate=False), mde=mde)
    for image_id in sorted(model.images, key=frame.get):
        k = frame[image_id]
        points = model.map_points(image_id)
        sigma = 0.03 * np.linalg.norm(points - poses[k][:3, 3], axis=1)  # 3 % of the distance
        mapper.add_frame(rgbs[k], poses[k], map_points_world=points, map_points_sigma=sigma, keyframe_id=k)
    mapper.flush()
    mesh_path = mapper.save_mesh(args.output / "mesh.ply")
    print(f"{len(model.points)} pycolmap points over {len(model.images)} images; wrote {mesh_path}")
    return {"points": len(model.points), "images": len(model.images), "mesh": mesh_path}


if __name__ == "__main__":
    main()
