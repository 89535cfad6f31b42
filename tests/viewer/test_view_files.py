"""`gpdepth3d view` opens any file the library writes: posteriors, meshes, point clouds, map folders."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("viser")
trimesh = pytest.importorskip("trimesh")

from gpdepth3d.cli import main  # noqa: E402
from gpdepth3d.cli.view import view_command  # noqa: E402
from gpdepth3d.completion.complete import DepthPosterior  # noqa: E402
from gpdepth3d.datasets.synthetic import make_scene  # noqa: E402
from gpdepth3d.errors import DataFormatError, EmptyInputError  # noqa: E402
from gpdepth3d.gp.model import DepthGPConfig  # noqa: E402
from gpdepth3d.mapping.cloud import ColoredCloud, backproject_depth  # noqa: E402
from gpdepth3d.viewer import show  # noqa: E402
from gpdepth3d.viewer.files import file_kind, load_cloud, load_geometry, load_map, ply_face_count  # noqa: E402


@pytest.fixture(scope="module")
def room():
    return make_scene(0, kind="room", width=48, height=36)


@pytest.fixture
def cloud(room) -> ColoredCloud:
    return backproject_depth(room.depth_gt, room.rgb, room.camera, T_world_camera=room.T_world_camera)


def _posterior(room) -> DepthPosterior:
    var = np.full(room.depth_gt.shape, 0.01**2)
    return DepthPosterior(
        mean=room.depth_gt, variance=var, mde=room.mde, sparse=room.lidar, config=DepthGPConfig(), depth_scale=1.0
    )


class TestFileKind:
    def test_every_kind_from_content(self, tmp_path, room, cloud):
        _posterior(room).save(tmp_path / "post.npz")
        box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
        box.export(tmp_path / "mesh.ply")
        box.export(tmp_path / "mesh.glb")
        cloud.save_ply(tmp_path / "cloud.ply")
        trimesh.PointCloud(np.random.default_rng(0).normal(size=(20, 3))).export(tmp_path / "plain.ply")
        assert file_kind(tmp_path / "post.npz") == "posterior"
        assert file_kind(tmp_path / "mesh.ply") == "mesh" and ply_face_count(tmp_path / "mesh.ply") == len(box.faces)
        assert file_kind(tmp_path / "mesh.glb") == "mesh"
        assert file_kind(tmp_path / "cloud.ply") == "cloud" and ply_face_count(tmp_path / "cloud.ply") == 0
        assert file_kind(tmp_path / "plain.ply") == "cloud"
        assert file_kind(tmp_path) == "map"  # a folder with mesh.ply / cloud.ply: a map's output folder

    def test_refusals_name_the_file(self, tmp_path):
        (tmp_path / "notes.txt").write_text("hello")
        (tmp_path / "fake.ply").write_text("not a ply")
        (tmp_path / "empty").mkdir()
        for path, match in [
            (tmp_path / "notes.txt", "not a file the viewer opens"),
            (tmp_path / "fake.ply", "not a PLY"),
            (tmp_path / "missing.ply", "not found"),
            (tmp_path / "empty", "without a map"),
        ]:
            with pytest.raises(DataFormatError, match=match) as info:
                file_kind(path)
            assert path.name in str(info.value)
        np.savez(tmp_path / "p.npz", mean=np.ones((2, 2)))
        with pytest.raises(DataFormatError, match="--posterior"):  # a posterior is a frame, not geometry
            load_geometry(tmp_path / "p.npz")


class TestClouds:
    def test_cloud_ply_reads_back_its_points_and_colours(self, tmp_path, cloud):
        cloud.save_ply(tmp_path / "cloud.ply")
        pc = load_cloud(tmp_path / "cloud.ply")
        np.testing.assert_allclose(pc.vertices, cloud.points, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(pc.colors)[:, :3], cloud.colors)

    def test_show_draws_a_cloud_given_as_a_mesh(self, tmp_path, cloud):
        """The issue's case: `view --mesh cloud.ply` said "no triangles"; the cloud is drawn as points."""
        cloud.save_ply(tmp_path / "cloud.ply")
        with show([], meshes=[tmp_path / "cloud.ply"], port=0) as v:
            assert len(v.meshes) == 1
            np.testing.assert_allclose(v.meshes[0].points, cloud.points.astype(np.float32), atol=1e-6)
            np.testing.assert_array_equal(v.meshes[0].colors, cloud.colors)

    def test_view_command_opens_a_cloud_and_a_posterior(self, tmp_path, room, cloud, capsys):
        cloud.save_ply(tmp_path / "cloud.ply")
        _posterior(room).save(tmp_path / "post.npz")
        view_command(files=(tmp_path / "cloud.ply", tmp_path / "post.npz"), port=0, duration=0)
        out = capsys.readouterr().out
        assert "1 frame(s) and 1 mesh(es) or cloud(s) on the page" in out and "viewer stopped" in out

    def test_cli_names_a_file_it_cannot_open(self, tmp_path, capsys):
        (tmp_path / "notes.txt").write_text("hello")
        assert main(["view", "--files", str(tmp_path / "notes.txt"), "--port", "0", "--duration", "0"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "notes.txt" in err[0] and "not a file the viewer opens" in err[0]

    def test_nothing_to_show(self):
        with pytest.raises(EmptyInputError):
            view_command(port=0, duration=0)


class TestMapFolders:
    def test_output_folder_of_map_opens_its_files(self, tmp_path, cloud, monkeypatch):
        """A `map --output` folder: its mesh and cloud files, without loading the saved map."""
        from gpdepth3d.mapping.mapper import Mapper

        trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(tmp_path / "mesh.ply")
        cloud.save_ply(tmp_path / "cloud.ply")
        monkeypatch.setattr(Mapper, "load", lambda *a, **k: pytest.fail("the files are there: no Mapper.load"))
        items = load_map(tmp_path)
        assert len(items) == 2 and len(items[0].faces) == 12 and len(items[1].vertices) == len(cloud)

    def test_saved_map_opens_through_mapper_load(self, tmp_path, room):
        """A folder written by `Mapper.save` alone: the map's mesh and surface points, as `map --view` drew them."""
        pytest.importorskip("open3d")
        from gpdepth3d.mapping import Mapper, MapperConfig
        from gpdepth3d.mapping.tsdf.fusion_config import FusionConfig

        config = MapperConfig(
            triangulate=False, working_scale=1.0, fusion=FusionConfig(voxel_size=0.05, truncation=0.15)
        )
        mapper = Mapper(room.camera, config)
        for _ in range(2):
            mapper.add_frame(room.rgb, room.T_world_camera, mde_depth=room.mde, sparse=room.lidar)
        mapper.save(tmp_path / "saved")
        mesh, points = mapper.mesh(), mapper.point_cloud()
        assert len(mesh.faces) and len(points)
        items = load_map(tmp_path / "saved")
        assert file_kind(tmp_path / "saved") == "map"
        assert len(items) == 2 and len(items[0].faces) == len(mesh.faces)
        np.testing.assert_allclose(
            np.sort(items[1].vertices, axis=0), np.sort(points.points, axis=0), atol=1e-4
        )  # stored volume: 16-bit distances
        with show([], meshes=[tmp_path / "saved"], port=0) as v:
            assert len(v.meshes) == 2 and len(v.meshes[1].points) == len(points)
