"""Saved maps: compact array forms, the block format of volumes, maps of the earlier format, one set per save,
recovery of an interrupted save by `Mapper.load`, kills at every file-system step, canonical meshes and clouds."""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.io import durable as gio
from gpdepth3d.camera import PinholeCamera
from gpdepth3d.errors import DataFormatError
from gpdepth3d.mapping.compact_arrays import (
    FIXED_STEPS,
    from_fixed,
    read_npz_members,
    sigma_of,
    to_fixed,
    to_half,
    variance_of,
)
from gpdepth3d.mapping.tsdf.fusion import FusionConfig, TSDFFusion
from gpdepth3d.mapping.map_store import load_keyframes, recover_map_folder, save_keyframes
from gpdepth3d.mapping.mapper import Mapper
from gpdepth3d.mapping.mapper_config import MapperConfig
from gpdepth3d.mapping.tsdf.extraction import canonical_mesh
from gpdepth3d.measurements import SparseDepth

DATA = Path(__file__).parent / "data"
OLD_MAP = DATA / "map_before_block_format"
"""A map written by the library before the block format (Open3D's archive, float32 keyframes)."""
CAM = PinholeCamera(40.0, 40.0, 19.5, 14.5, 40, 30)
MAP_NAMES = ["keyframes.npz", "mapper.json", "volume.json", "volume.npz"]


class TestCompactArrays:
    def test_half_keeps_zero_nonzero_nan_and_sign(self):
        a = np.array([0.0, 1e-9, -1e-9, 1.5, np.nan, -2.25, 1e-3], np.float32)
        h = to_half(a)
        assert h.dtype == np.float16
        assert h[0] == 0 and h[1] > 0 and h[2] < 0 and np.isnan(h[4])
        np.testing.assert_allclose(h[[3, 5, 6]].astype(np.float32), a[[3, 5, 6]], rtol=2.0**-11)
        assert to_half(np.array([1e6, 1.0])).dtype == np.float32  # does not fit: kept as it was

    def test_sigma_keeps_small_variances(self):
        v = np.array([0.0, 1e-8, 1e-6, 0.04, np.nan, -1.0], np.float32)
        back = variance_of(sigma_of(v))
        np.testing.assert_allclose(back[1:4], v[1:4], rtol=2.0**-10)
        assert back[0] == 0 and np.isnan(back[4]) and back[5] == 0 and np.all(back[~np.isnan(back)] >= 0)

    def test_fixed_point(self):
        a = np.array([-1.0, -1e-7, 0.0, 1e-7, 0.3, 1.0, 2.0], np.float32)
        q = to_fixed(a)
        assert q.dtype == np.int16 and list(np.sign(q)) == [-1, -1, 0, 1, 1, 1, 1]
        np.testing.assert_allclose(from_fixed(q)[[0, 2, 4, 5]], a[[0, 2, 4, 5]], atol=0.5 / FIXED_STEPS)
        assert from_fixed(q)[6] == 1.0  # clipped to [-1, 1]

    def test_read_npz_members(self, tmp_path):
        np.savez_compressed(tmp_path / "a.npz", x=np.arange(5), y=np.ones((2, 3)))
        got = read_npz_members(tmp_path / "a.npz", ["y", "x"])
        assert list(got) == ["y", "x"] and np.array_equal(got["x"], np.arange(5))
        with pytest.raises(KeyError):
            read_npz_members(tmp_path / "a.npz", ["z"])


def _mapper(frames: int = 3, shade: int = 0) -> Mapper:
    """A small map of a slanted plane from ``frames`` posed frames (``shade`` changes its colour)."""
    config = MapperConfig(
        triangulate=False,
        working_scale=1.0,
        fusion=FusionConfig(
            voxel_size=0.05, truncation=0.15, relative_sigma_ref=None, block_count=64, block_resolution=4
        ),
    )
    mapper = Mapper(CAM, config)
    rng = np.random.default_rng(0)
    for i in range(frames):
        T = np.eye(4)
        T[0, 3] = 0.05 * i
        depth = np.full((30, 40), 1.0) + 0.2 * np.linspace(0, 1, 40)[None]
        u, v = rng.uniform(0, 39, 40), rng.uniform(0, 29, 40)
        sparse = SparseDepth(u, v, 1.0 + 0.2 * u / 39, (30, 40), np.full(40, 0.01))
        rgb = np.full((30, 40, 3), 60 + 40 * i + shade, np.uint8)
        assert mapper.add_frame(rgb, T, mde_depth=depth * 1.1, sparse=sparse).fused
    return mapper


def _save_dying_at(folder: str, shade: int, step: int) -> None:
    """In a fresh interpreter: saves `_mapper(shade=shade)` to ``folder``, dying (``os._exit(3)``, no clean-up)
    at its ``step``-th file-system change; exit code 0 when the save finishes first."""
    try:
        mapper = _mapper(shade=shade)
        counter = {"n": 0}

        def dying(fn):
            def call(*a, **k):
                counter["n"] += 1
                if counter["n"] == step:
                    os._exit(3)
                return fn(*a, **k)

            return call

        for mod, name in ((os, "replace"), (os, "unlink"), (gio.tempfile, "mkstemp"), (os, "fsync")):
            setattr(mod, name, dying(getattr(mod, name)))
        mapper.save(folder)
        os._exit(0)
    except BaseException:
        os._exit(4)


def _voxels(mapper: Mapper) -> dict:
    vox = mapper.fusion.voxels()
    order = np.lexsort(vox["coords"].T)
    return {k: v[order] for k, v in vox.items()}


class TestEarlierFormat:
    def test_map_of_the_earlier_format_loads(self, tmp_path):
        """The fixture was written by the library before the block format; it loads, goes on and saves anew."""
        folder = tmp_path / "old"
        shutil.copytree(OLD_MAP, folder)
        assert "format" not in json.loads((folder / "volume.json").read_text())
        with np.load(folder / "keyframes.npz") as d:
            assert "variance" in d.files and "sigma" not in d.files and d["depth"].dtype == np.float32
            old_depth = d["depth"]
        with np.load(folder / "volume.npz") as d:  # Open3D's archive: the blocks and attributes as stored
            names = {int(d[f"attr_name_{n}"][0]): n for n in ("tsdf", "weight", "color")}
            stored = {n: d[f"value_{i:03d}"] for i, n in names.items()}
            blocks = d["key"].shape[0]
        mapper = Mapper.load(folder)
        assert sorted(mapper.keyframes) == [0, 1, 2] and mapper.frames == 3
        np.testing.assert_array_equal(np.stack([mapper.keyframes[k].depth for k in range(3)]), old_depth)
        assert mapper.fusion.vbg.hashmap().size() == blocks
        vox = _voxels(mapper)
        assert len(vox["tsdf"]) == int((stored["weight"] > 0).sum())
        np.testing.assert_allclose(np.sort(vox["weight"]), np.sort(stored["weight"][stored["weight"] > 0]))
        assert len(mapper.mesh().faces) > 0
        mapper.save(tmp_path / "new")  # saved again: the block format, the same voxels within its precision
        assert json.loads((tmp_path / "new" / "volume.json").read_text())["format"] == "gpdepth3d-blocks-1"
        again = _voxels(Mapper.load(tmp_path / "new"))
        np.testing.assert_array_equal(again["coords"], vox["coords"])
        np.testing.assert_allclose(again["tsdf"], vox["tsdf"], atol=1.01 / FIXED_STEPS)
        np.testing.assert_allclose(again["weight"], vox["weight"], rtol=2.0**-11)


class TestSaveAsOneSet:
    def test_keyframes_decompressed_once(self, tmp_path, monkeypatch):
        """Each member of the keyframe store is read once, not once per keyframe (the load was quadratic)."""
        mapper = _mapper()
        save_keyframes(tmp_path / "k.npz", mapper.keyframes, mapper.work_camera.shape)
        reads = []
        real = zipfile.ZipFile.open

        def counting(self, name, *a, **k):
            reads.append(name)
            return real(self, name, *a, **k)

        monkeypatch.setattr(zipfile.ZipFile, "open", counting)
        back = load_keyframes(tmp_path / "k.npz")
        assert len(back) == 3 and len(reads) == len(set(reads)) <= 9
        for k, kf in mapper.keyframes.items():
            np.testing.assert_allclose(back[k].depth, kf.depth, rtol=2.0**-11)
            np.testing.assert_allclose(back[k].variance, kf.variance, rtol=2.0**-10)
            np.testing.assert_array_equal(back[k].rgb, kf.rgb)

    def test_interrupted_commit_is_finished_by_load(self, tmp_path, monkeypatch):
        """A kill between the renames of a save's commit: `Mapper.load` rolls the new map forward."""
        folder = tmp_path / "m"
        _mapper(shade=0).save(folder)
        new = _mapper(shade=20)
        calls = {"n": 0}
        real = gio.os.replace

        def dies_after_one(src, dst):
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt  # like a kill: nothing after this runs
            return real(src, dst)

        monkeypatch.setattr(gio.os, "replace", dies_after_one)
        with pytest.raises(KeyboardInterrupt):
            new.save(folder)
        monkeypatch.setattr(gio.os, "replace", real)
        assert any(n.endswith(".journal") for n in os.listdir(folder))
        loaded = Mapper.load(folder)
        assert sorted(os.listdir(folder)) == MAP_NAMES  # finished: nothing hidden left
        np.testing.assert_array_equal(loaded.keyframes[0].rgb, new.keyframes[0].rgb)  # the new map throughout
        np.testing.assert_allclose(_voxels(loaded)["color"], _voxels(new)["color"], atol=0.5 / 255)

    def test_kill_before_the_commit_keeps_the_old_map(self, tmp_path):
        """A writer killed while writing its temporaries: the old map stays, `Mapper.load` removes them."""
        folder = tmp_path / "m"
        old = _mapper(shade=0)
        old.save(folder)
        (folder / ".volume.AbCdEfGh.tmp.npz").write_bytes(b"half a volume")  # a dead writer's (unlocked) temporary
        (folder / ".keyframes.12345678.tmp.npz").write_bytes(b"")
        assert recover_map_folder(folder) == 2 and recover_map_folder(folder) == 0
        (folder / ".mapper.87654321.tmp.json").write_text("{")
        loaded = Mapper.load(folder)
        assert sorted(os.listdir(folder)) == MAP_NAMES
        np.testing.assert_array_equal(loaded.keyframes[1].rgb, old.keyframes[1].rgb)

    def test_recovery_that_cannot_finish_is_named(self, tmp_path, monkeypatch):
        folder = tmp_path / "m"
        _mapper().save(folder)
        (folder / ".map.0123abcd.journal").write_text(json.dumps({"renames": [["gone", "mapper.json"]], "remove": []}))
        (folder / "gone").write_text("{}")

        def refused(src, dst):  # a folder that cannot be written (read-only medium)
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(gio.os, "replace", refused)
        with pytest.raises(DataFormatError, match="interrupted save"):
            Mapper.load(folder)

    @pytest.mark.slow  # a fresh interpreter per step (a forked child of a threaded process can deadlock)
    def test_save_killed_at_every_step_leaves_old_or_new_map(self, tmp_path):
        import multiprocessing

        folder = tmp_path / "m"
        shades = (0, 30)
        maps = [_mapper(shade=s) for s in shades]
        maps[0].save(folder)
        shade = {int(m.keyframes[0].rgb[0, 0, 0]): i for i, m in enumerate(maps)}
        step, finished, seen = 1, False, set()
        spawn = multiprocessing.get_context("spawn")
        while not finished:
            child = spawn.Process(target=_save_dying_at, args=(str(folder), shades[1 - step % 2], step))
            child.start()
            child.join()
            code = child.exitcode
            assert code in (0, 3), f"step {step}: child failed with {code}"
            finished = code == 0
            loaded = Mapper.load(folder)  # finishes or rolls back what the kill left
            assert sorted(os.listdir(folder)) == MAP_NAMES, f"step {step}: {sorted(os.listdir(folder))}"
            which = shade[int(loaded.keyframes[0].rgb[0, 0, 0])]
            meta = json.loads((folder / "volume.json").read_text())
            assert meta["blocks"] == loaded.fusion.vbg.hashmap().size()
            np.testing.assert_allclose(
                _voxels(loaded)["color"], _voxels(maps[which])["color"], atol=0.5 / 255, err_msg=f"step {step}"
            )  # the volume is of the same map as the keyframes
            seen.add(which)
            step += 1
            assert step < 80
        assert seen == {0, 1}
        print(f"Mapper.save killed at each of its {step - 2} file-system steps: always one whole map")


class TestCanonical:
    def test_mesh_order_does_not_matter(self):
        import trimesh

        mapper = _mapper()
        mesh = mapper.fusion.extract_mesh()
        soup = mapper.mesh()  # the incremental extraction's triangle soup: the same surface
        rng = np.random.default_rng(1)
        faces = np.roll(mesh.faces[rng.permutation(len(mesh.faces))], 1, axis=1)
        shuffled = trimesh.Trimesh(mesh.vertices, faces, vertex_colors=mesh.visual.vertex_colors, process=False)
        a, b, c = (canonical_mesh(m) for m in (mesh, shuffled, soup))
        assert a.export(file_type="ply") == b.export(file_type="ply") == c.export(file_type="ply")
        assert len(a.faces) == len(mesh.faces) and len(a.vertices) <= len(mesh.vertices)
        assert np.all(np.diff(a.faces[:, 0]) >= 0) and np.all(a.faces[:, 0] == a.faces.min(axis=1))
        np.testing.assert_allclose(a.area, mesh.area)
        assert np.allclose(np.sort(a.face_normals, axis=0), np.sort(mesh.face_normals, axis=0))  # winding kept

    def test_cloud_is_sorted(self):
        cloud = _mapper().point_cloud()
        assert len(cloud) > 0
        order = np.lexsort(np.concatenate([cloud.points, cloud.colors], axis=1).T[::-1])
        np.testing.assert_array_equal(order, np.arange(len(cloud)))

    def test_mesh_metrics_do_not_depend_on_the_order(self):
        import trimesh

        from gpdepth3d.metrics import mesh_metrics

        mapper = _mapper()
        mesh = mapper.fusion.extract_mesh()
        rng = np.random.default_rng(2)
        shuffled = trimesh.Trimesh(mesh.vertices, mesh.faces[rng.permutation(len(mesh.faces))], process=False)
        ref = mapper.mesh()
        assert mesh_metrics(mesh, ref, samples=2000) == mesh_metrics(shuffled, ref, samples=2000)


def test_volume_file_holds_only_allocated_blocks(tmp_path):
    fusion = _mapper().fusion
    path = fusion.save(tmp_path / "volume.npz")
    with np.load(path) as d:
        assert d["blocks"].shape[0] == fusion.vbg.hashmap().size() < fusion.vbg.hashmap().capacity()
        assert d["tsdf"].dtype == np.int16 and d["weight"].dtype == np.float16 and d["color"].dtype == np.uint8
    back = TSDFFusion.load(path)
    assert back.vbg.hashmap().size() == fusion.vbg.hashmap().size()
