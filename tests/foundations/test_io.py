"""Tests of gpdepth3d.io: atomic writes, depth PNG/npy/npz, sparse point lists, RGB images."""

from __future__ import annotations

import os
import warnings

import cv2
import numpy as np
import pytest

from gpdepth3d import io as gio
from gpdepth3d.errors import DataFormatError, InvalidDepthError, InvalidInputError, OutputError, ShapeError
from gpdepth3d.io import (
    KITTI_PNG_SCALE,
    atomic_path,
    atomic_write,
    load_depth,
    load_rgb,
    load_sparse,
    save_depth_png,
    save_npz,
)


def listing(folder):
    return sorted(p.name for p in folder.iterdir())


class TestAtomicPath:
    def test_success_moves_into_place(self, tmp_path):
        target = tmp_path / "sub" / "out.txt"
        with atomic_path(target) as tmp:
            assert tmp.parent == target.parent and tmp != target
            tmp.write_text("hello")
            assert not target.exists()
        assert target.read_text() == "hello"
        assert listing(target.parent) == ["out.txt"]

    def test_result_has_the_usual_permissions(self, tmp_path):
        import os

        mask = os.umask(0)
        os.umask(mask)
        target = tmp_path / "out.txt"
        with atomic_path(target) as tmp:
            tmp.write_text("x")
        assert target.stat().st_mode & 0o777 == 0o666 & ~mask

    def test_failure_leaves_nothing(self, tmp_path):
        target = tmp_path / "out.txt"
        with pytest.raises(RuntimeError):
            with atomic_path(target) as tmp:
                tmp.write_text("half")
                raise RuntimeError("writer died")
        assert listing(tmp_path) == []

    def test_failure_keeps_an_existing_file(self, tmp_path):
        target = tmp_path / "out.txt"
        target.write_text("old")
        with pytest.raises(RuntimeError):
            with atomic_path(target) as tmp:
                tmp.write_text("new but broken")
                raise RuntimeError("writer died")
        assert target.read_text() == "old" and listing(tmp_path) == ["out.txt"]


class TestAtomicWrite:
    def test_writes(self, tmp_path):
        out = atomic_write(tmp_path / "a.bin", lambda p: p.write_bytes(b"abc"))
        assert out.read_bytes() == b"abc"

    def test_failing_writer_leaves_no_file_and_no_temp(self, tmp_path):
        def writer(p):
            p.write_bytes(b"partial")
            raise OSError("disk full")

        with pytest.raises(OSError):
            atomic_write(tmp_path / "a.bin", writer)
        assert listing(tmp_path) == []


class TestSaveNpz:
    def test_round_trip(self, tmp_path):
        a = np.arange(12.0).reshape(3, 4)
        path = save_npz(tmp_path / "x.npz", depth=a, other=np.int16(3))
        with np.load(path) as d:
            np.testing.assert_array_equal(d["depth"], a)
            assert int(d["other"]) == 3

    def test_failure_leaves_nothing(self, tmp_path, monkeypatch):
        def broken(f, **arrays):
            f.write(b"PK\x03\x04 partial zip")
            raise OSError("disk full")

        monkeypatch.setattr(gio.durable.np, "savez_compressed", broken)
        with pytest.raises(OSError):
            save_npz(tmp_path / "x.npz", depth=np.ones(3))
        assert listing(tmp_path) == []


class TestSaveDepthPng:
    def test_round_trip_kitti_convention(self, tmp_path):
        rng = np.random.default_rng(0)
        d = rng.uniform(0.5, 80.0, size=(7, 9))
        d[0, 0] = 0.0
        d[1, 1] = np.nan
        d[2, 2] = -3.0  # invalid: written as 0
        path = save_depth_png(tmp_path / "d.png", d)
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (7, 9)
        assert raw[0, 0] == raw[1, 1] == raw[2, 2] == 0
        assert raw[3, 3] == np.rint(d[3, 3] * 256)
        back = load_depth(path)
        valid = np.isfinite(d) & (d > 0)
        np.testing.assert_allclose(back[valid], d[valid], atol=0.5 / 256)
        assert np.all(back[~valid] == 0)

    def test_suffix_and_scale(self, tmp_path):
        path = save_depth_png(tmp_path / "d.npy", np.full((2, 2), 1.234), png_scale=1e-3)
        assert path.suffix == ".png" and path.exists()
        np.testing.assert_allclose(load_depth(path, png_scale=1e-3), 1.234)

    def test_too_deep_raises_and_writes_nothing(self, tmp_path):
        with pytest.raises(InvalidDepthError):
            save_depth_png(tmp_path / "d.png", np.full((2, 2), 300.0))  # 300 m > 255.99 m at 1/256
        assert listing(tmp_path) == []

    def test_bad_shape(self, tmp_path):
        with pytest.raises(ShapeError):
            save_depth_png(tmp_path / "d.png", np.ones((2, 2, 3)))
        assert listing(tmp_path) == []


class TestLoadDepth:
    def test_npy_and_npz(self, tmp_path):
        d = np.array([[1.0, np.nan], [np.inf, 2.0]])
        np.save(tmp_path / "d.npy", d)
        np.testing.assert_array_equal(load_depth(tmp_path / "d.npy"), [[1.0, 0.0], [0.0, 2.0]])
        np.savez(tmp_path / "one.npz", anything=d[..., None])  # (H, W, 1) is squeezed
        assert load_depth(tmp_path / "one.npz").shape == (2, 2)
        np.savez(tmp_path / "two.npz", depth=np.ones((2, 2)), rgb=np.zeros((2, 2, 3)))
        np.testing.assert_array_equal(load_depth(tmp_path / "two.npz"), np.ones((2, 2)))
        np.savez(tmp_path / "post.npz", variance=np.zeros((2, 2)), mean=np.full((2, 2), 3.0))
        np.testing.assert_array_equal(load_depth(tmp_path / "post.npz"), np.full((2, 2), 3.0))
        np.testing.assert_array_equal(load_depth(tmp_path / "post.npz", key="variance"), np.zeros((2, 2)))

    def test_npz_key_errors(self, tmp_path):
        np.savez(tmp_path / "amb.npz", a=np.ones((2, 2)), b=np.ones((2, 2)))
        with pytest.raises(DataFormatError, match="key="):
            load_depth(tmp_path / "amb.npz")
        with pytest.raises(DataFormatError, match="no array"):
            load_depth(tmp_path / "amb.npz", key="depth")

    def test_png_invalid_value(self, tmp_path):
        raw = np.array([[1000, 65535], [0, 2500]], dtype=np.uint16)
        cv2.imwrite(str(tmp_path / "k.png"), raw)
        d = load_depth(tmp_path / "k.png", png_scale=1e-3, invalid_value=65535)
        np.testing.assert_allclose(d, [[1.0, 0.0], [0.0, 2.5]])

    def test_8bit_png_rejected(self, tmp_path):
        cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((4, 4, 3), np.uint8))
        with pytest.raises(DataFormatError, match="16-bit"):
            load_depth(tmp_path / "rgb.png")

    @pytest.mark.parametrize(
        "name, content",
        [
            ("d.npy", b"not a depth map"),
            ("d.npz", b"not a depth map"),
            ("d.npz", b"PK\x03\x04 truncated"),
            ("d.png", b"\x89PNG\r\n"),
        ],
    )
    def test_corrupt_files(self, tmp_path, name, content):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(DataFormatError):
            load_depth(tmp_path / name)

    def test_missing_unknown_and_wrong_rank(self, tmp_path):
        with pytest.raises(DataFormatError, match="not found"):
            load_depth(tmp_path / "missing.npy")
        (tmp_path / "d.tiff").write_bytes(b"II*\x00")
        with pytest.raises(DataFormatError, match="unknown"):
            load_depth(tmp_path / "d.tiff")
        np.save(tmp_path / "cube.npy", np.ones((2, 2, 2)))
        with pytest.raises(DataFormatError, match="2-D"):
            load_depth(tmp_path / "cube.npy")
        np.save(tmp_path / "obj.npy", np.array([None, 1], dtype=object), allow_pickle=True)
        with pytest.raises(DataFormatError):
            load_depth(tmp_path / "obj.npy")  # pickles are refused

    def test_seven_scenes_depth(self, seven_scenes_frame):
        d = seven_scenes_frame.depth
        assert d.shape == (480, 640)
        valid = d > 0
        assert 0.7 < valid.mean() <= 1.0
        assert 0.3 < d[valid].min() and d[valid].max() < 8.0  # Kinect range, millimetres read as metres


class TestLoadSparse:
    def test_npz_point_list(self, tmp_path):
        np.savez(tmp_path / "p.npz", u=[1.0, 50.0], v=[2.0, 1.0], depth=[3.0, 4.0], sigma=[0.1, 0.2])
        with pytest.raises(InvalidDepthError, match="1 of 2 rows"):  # the second point is outside: refused
            load_sparse(tmp_path / "p.npz", (10, 20))
        with pytest.warns(UserWarning, match="dropped 1 of 2 rows"):  # or dropped, with its count
            s = load_sparse(tmp_path / "p.npz", (10, 20), drop_invalid=True)
        assert len(s) == 1 and (s.u[0], s.v[0], s.depth[0], s.sigma[0]) == (1.0, 2.0, 3.0, 0.1)
        with pytest.raises(ShapeError):
            load_sparse(tmp_path / "p.npz")

    def test_text_point_lists(self, tmp_path):
        (tmp_path / "p.txt").write_text("1 2 3.5\n4 5 6.5\n")
        s = load_sparse(tmp_path / "p.txt", (10, 10))
        np.testing.assert_array_equal(s.depth, [3.5, 6.5])
        assert np.all(np.isnan(s.sigma))
        (tmp_path / "p.csv").write_text("1,2,3.5,0.01\n")
        s = load_sparse(tmp_path / "p.csv", (10, 10))
        assert s.sigma[0] == 0.01
        (tmp_path / "empty.txt").write_text("")
        with warnings.catch_warnings():  # numpy may warn that the file holds no data
            warnings.simplefilter("ignore", UserWarning)
            assert len(load_sparse(tmp_path / "empty.txt", (10, 10))) == 0
        with pytest.raises(ShapeError):
            load_sparse(tmp_path / "p.txt")

    def test_text_errors(self, tmp_path):
        (tmp_path / "cols.txt").write_text("1 2\n3 4\n")
        with pytest.raises(DataFormatError, match="columns"):
            load_sparse(tmp_path / "cols.txt", (10, 10))
        (tmp_path / "junk.txt").write_text("u v depth\nfoo bar baz\n")
        with pytest.raises(DataFormatError):
            load_sparse(tmp_path / "junk.txt", (10, 10))
        with pytest.raises(DataFormatError):
            load_sparse(tmp_path / "missing.txt", (10, 10))

    def test_sparse_depth_map(self, tmp_path):
        m = np.zeros((6, 8))
        m[1, 2] = 4.0
        m[5, 7] = 12.5
        save_depth_png(tmp_path / "s.png", m)
        s = load_sparse(tmp_path / "s.png")
        assert s.image_size == (6, 8) and len(s) == 2
        np.testing.assert_allclose(s.to_depth_map(), m, atol=0.5 / 256)
        with pytest.raises(ShapeError):
            load_sparse(tmp_path / "s.png", (12, 16))
        np.save(tmp_path / "s.npy", m)
        np.testing.assert_array_equal(load_sparse(tmp_path / "s.npy").to_depth_map(), m)

    @pytest.mark.parametrize("content", [b"garbage", b"PK\x03\x04 truncated zip"])
    def test_corrupt_npz(self, tmp_path, content):
        (tmp_path / "bad.npz").write_bytes(content)
        with pytest.raises(DataFormatError):
            load_sparse(tmp_path / "bad.npz", (4, 4))

    def test_invalid_sigma_in_point_list(self, tmp_path):
        np.savez(tmp_path / "p.npz", u=[1.0], v=[2.0], depth=[3.0], sigma=[-0.1])
        with pytest.raises(InvalidDepthError):
            load_sparse(tmp_path / "p.npz", (10, 20))

    def test_ibims_samples(self, shared_data):
        gt = load_depth(shared_data / "ibims_sample" / "gt.npz")
        s = load_sparse(shared_data / "ibims_sample" / "sparse_100.npz", gt.shape)
        assert 90 <= len(s) <= 100
        np.testing.assert_allclose(s.depth, gt[s.v.astype(int), s.u.astype(int)], rtol=1e-6)


class TestLoadRgb:
    def test_round_trip(self, tmp_path):
        rgb = np.zeros((4, 5, 3), np.uint8)
        rgb[..., 0] = 200  # red
        cv2.imwrite(str(tmp_path / "c.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        out = load_rgb(tmp_path / "c.png")
        np.testing.assert_array_equal(out, rgb)

    def test_errors(self, tmp_path):
        with pytest.raises(DataFormatError):
            load_rgb(tmp_path / "missing.png")
        (tmp_path / "bad.jpg").write_bytes(b"not a jpeg")
        with pytest.raises(DataFormatError):
            load_rgb(tmp_path / "bad.jpg")

    def test_seven_scenes_colour(self, seven_scenes_frame):
        assert seven_scenes_frame.rgb.shape == (480, 640, 3) and seven_scenes_frame.rgb.dtype == np.uint8


def test_kitti_png_scale_constant():
    assert KITTI_PNG_SCALE == 1.0 / 256.0


class TestOutputSets:
    def writers(self, text: str, names=("s.txt", "s.csv")):
        return {n: (lambda p, n=n: p.write_text(f"{text}:{n}")) for n in names}

    def read(self, folder, names=("s.txt", "s.csv")):
        return [(folder / n).read_text() if (folder / n).exists() else None for n in names]

    def test_set_is_replaced_as_a_whole(self, tmp_path):
        written = gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        assert written == [tmp_path / "s.txt", tmp_path / "s.csv"]
        assert self.read(tmp_path) == ["v1:s.txt", "v1:s.csv"]
        gio.atomic_write_set(tmp_path / "s", self.writers("v2"))
        assert self.read(tmp_path) == ["v2:s.txt", "v2:s.csv"]
        # plain files and nothing else: no links, no hidden lock, pointer or folder
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt"]
        assert not any(p.is_symlink() for p in tmp_path.iterdir())

    def test_failing_writer_keeps_the_old_set(self, tmp_path):
        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))

        def fails(p):
            p.write_text("half")
            raise OSError(28, "No space left on device")

        with pytest.raises(OutputError, match="disk full"):
            gio.atomic_write_set(tmp_path / "s", {"s.txt": lambda p: p.write_text("v2"), "s.csv": fails})
        assert self.read(tmp_path) == ["v1:s.txt", "v1:s.csv"]
        with pytest.raises(OutputError, match="no file"):  # a writer that writes nothing
            gio.atomic_write_set(tmp_path / "s", {"s.txt": lambda p: None, "s.csv": lambda p: None})
        with pytest.raises(OutputError, match="plain file name"):
            gio.atomic_write_set(tmp_path / "s", {"../s.txt": lambda p: None})
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt"]

    def test_members_not_written_leave_the_set(self, tmp_path):
        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        gio.atomic_write_set(tmp_path / "s", self.writers("v2", ("s.txt",)), members=("s.txt", "s.csv"))
        assert self.read(tmp_path) == ["v2:s.txt", None]
        assert not os.path.lexists(tmp_path / "s.csv")

    def test_output_set_gathers_every_write_of_the_block(self, tmp_path):
        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        with pytest.raises(RuntimeError):
            with gio.output_set(tmp_path / "s", members=("s.txt", "s.csv", "s.png")):
                gio.atomic_write_set(tmp_path / "s", self.writers("v2", ("s.txt",)))
                gio.atomic_write(tmp_path / "s.png", lambda p: p.write_text("v2:s.png"))
                assert self.read(tmp_path) == ["v1:s.txt", "v1:s.csv"]  # nothing renamed yet
                raise RuntimeError("a failing preview")
        assert self.read(tmp_path, ("s.txt", "s.csv", "s.png")) == ["v1:s.txt", "v1:s.csv", None]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt"]
        with gio.output_set(tmp_path / "s", members=("s.txt", "s.csv", "s.png")):
            gio.atomic_write_set(tmp_path / "s", self.writers("v3", ("s.txt",)))
            gio.atomic_write(tmp_path / "s.png", lambda p: p.write_text("v3:s.png"))
            gio.write_json(tmp_path / "other" / "o.json", {})  # another folder: not part of the set
            assert (tmp_path / "other" / "o.json").is_file()
        assert self.read(tmp_path, ("s.txt", "s.csv", "s.png")) == ["v3:s.txt", None, "v3:s.png"]

    def test_interrupted_commit_is_rolled_forward(self, tmp_path, monkeypatch):
        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        real = os.replace
        calls = {"n": 0}

        def killed_after_one(src, dst):  # the process dies between the renames of the commit
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
            return real(src, dst)

        monkeypatch.setattr(gio.durable.os, "replace", killed_after_one)
        with pytest.raises(KeyboardInterrupt):
            gio.atomic_write_set(tmp_path / "s", self.writers("v2"))
        monkeypatch.setattr(gio.durable.os, "replace", real)
        assert self.read(tmp_path) == ["v2:s.txt", "v1:s.csv"]  # the journal and a temporary stay
        gio.atomic_write_set(tmp_path / "t", self.writers("w", ("t.txt",)))  # another set: not touched
        assert self.read(tmp_path) == ["v2:s.txt", "v1:s.csv"]
        gio.clean_output_set(tmp_path / "s", ["s.txt", "s.csv"])  # what the next writer does first
        assert self.read(tmp_path) == ["v2:s.txt", "v2:s.csv"]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt", "t.txt"]

    def test_killed_commit_leaves_old_or_new_set(self, tmp_path):
        import multiprocessing

        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        ctx = multiprocessing.get_context("fork")
        proc = ctx.Process(target=_commit_then_die, args=(tmp_path,))
        proc.start()
        proc.join(60)
        assert proc.exitcode == 9
        names = sorted(p.name for p in tmp_path.iterdir())
        assert any(n.endswith(".journal") for n in names)  # killed after the first rename
        assert self.read(tmp_path) == ["v2:s.txt", "v1:s.csv"]
        assert gio.clean_output_set(tmp_path / "s", ["s.txt", "s.csv"]) >= 1
        assert self.read(tmp_path) == ["v2:s.txt", "v2:s.csv"]  # rolled forward: the complete new set
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt"]

    def test_write_together_commit_is_journalled(self, tmp_path, monkeypatch):
        for n in ("a.csv", "b.json"):
            gio.atomic_write(tmp_path / n, lambda p, n=n: p.write_text(f"old:{n}"))
        real = os.replace
        calls = {"n": 0}

        def interrupted(src, dst):
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
            return real(src, dst)

        monkeypatch.setattr(gio.durable.os, "replace", interrupted)
        with pytest.raises(KeyboardInterrupt):
            with gio.write_together():
                for n in ("a.csv", "b.json"):
                    gio.atomic_write(tmp_path / n, lambda p, n=n: p.write_text(f"new:{n}"))
        monkeypatch.setattr(gio.durable.os, "replace", real)
        assert [(tmp_path / n).read_text() for n in ("a.csv", "b.json")] == ["new:a.csv", "old:b.json"]
        with gio.write_together():  # the next run writing there finishes the interrupted commit first
            gio.atomic_write(tmp_path / "c.txt", lambda p: p.write_text("c"))
        assert [(tmp_path / n).read_text() for n in ("a.csv", "b.json")] == ["new:a.csv", "new:b.json"]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.json", "c.txt"]

    def test_clean_output_folder_finishes_every_set(self, tmp_path):
        import multiprocessing

        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        proc = multiprocessing.get_context("fork").Process(target=_commit_then_die, args=(tmp_path,))
        proc.start()
        proc.join(60)
        (tmp_path / ".t.abcdefgh.tmp.txt").write_text("a dead writer's temporary of another set")
        assert gio.clean_output_folder(tmp_path) >= 2
        assert self.read(tmp_path) == ["v2:s.txt", "v2:s.csv"]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt"]
        assert gio.clean_output_folder(tmp_path / "missing") == 0

    def test_clean_output_set_removes_only_dead_writers_leftovers(self, tmp_path):
        gio.atomic_write_set(tmp_path / "s", self.writers("v1"))
        (tmp_path / ".s.abcdefgh.tmp.txt").write_text("x")
        (tmp_path / ".t.abcdefgh.tmp.txt").write_text("other set")
        with gio.atomic_path(tmp_path / "s.csv") as live:  # a writer still running
            live.write_text("v2")
            assert gio.clean_output_set(tmp_path / "s", ["s.txt", "s.csv"]) == 1
            assert live.exists()
        assert (tmp_path / ".t.abcdefgh.tmp.txt").exists()
        assert self.read(tmp_path) == ["v1:s.txt", "v2"]

    def test_links_of_older_versions_become_plain_files(self, tmp_path):
        old = tmp_path / ".s.set-abcd1234"
        old.mkdir()
        for n in ("s.txt", "s.csv"):
            (old / n).write_text(f"old:{n}")
        os.symlink(old.name, tmp_path / ".s.current")
        for n in ("s.txt", "s.csv"):
            os.symlink(f".s.current/{n}", tmp_path / n)
        (tmp_path / ".s.lock").write_text("")
        gio.atomic_write_set(tmp_path / "s", self.writers("v2", ("s.txt",)), members=("s.txt", "s.csv"))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.txt"]
        assert not (tmp_path / "s.txt").is_symlink() and self.read(tmp_path) == ["v2:s.txt", None]
        old.mkdir()
        (old / "s.txt").write_text("old")
        os.symlink(old.name, tmp_path / ".s.current")
        os.symlink(".s.current/s.txt", tmp_path / "s.csv")
        gio.clean_output_set(tmp_path / "s", ["s.txt", "s.csv"])
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.txt"]
        assert (tmp_path / "s.csv").read_text() == "old" and not (tmp_path / "s.csv").is_symlink()

    def test_writers_that_write_atomically_themselves(self, tmp_path):
        """A set's writer may call an atomic writer (a mesh or PLY saver): its file joins the set whole."""
        writers = {
            name: (lambda p, name=name: gio.atomic_write(p, lambda q: q.write_text(name)))
            for name in ("s.a", "s.b", "s.c")
        }
        written = gio.atomic_write_set(tmp_path / "s", writers)
        assert [p.read_text() for p in written] == ["s.a", "s.b", "s.c"]
        assert listing(tmp_path) == ["s.a", "s.b", "s.c"]


def _commit_then_die(folder):
    """Writes a new set and dies (like SIGKILL: no clean-up) right after the first rename of the commit."""
    real = os.replace
    calls = {"n": 0}

    def die(src, dst):
        real(src, dst)
        calls["n"] += 1
        if calls["n"] == 1:
            os._exit(9)

    gio.durable.os.replace = die
    gio.atomic_write_set(folder / "s", {n: (lambda p, n=n: p.write_text(f"v2:{n}")) for n in ("s.txt", "s.csv")})


class TestOutputChecks:
    def test_check_output_path(self, tmp_path):
        assert gio.check_output_path(tmp_path / "new" / "x.npz") == tmp_path / "new" / "x.npz"
        (tmp_path / "d").mkdir()
        (tmp_path / "f").write_text("")
        for bad, text in (
            ("", "name"),
            (tmp_path / "d", "directory"),
            (tmp_path / "f" / "x", "not a folder"),
            (3, "file path"),
        ):
            with pytest.raises(OutputError, match=text):
                gio.check_output_path(bad)

    def test_check_output_folder(self, tmp_path, monkeypatch):
        assert gio.check_output_folder(tmp_path / "a" / "b") == tmp_path / "a" / "b"
        (tmp_path / "f").write_text("")
        for bad, text in (("", "name"), (tmp_path / "f", "in the way"), (tmp_path / "f" / "x", "not a folder")):
            with pytest.raises(OutputError, match=text):
                gio.check_output_folder(bad)
        monkeypatch.setattr(os, "access", lambda *a, **k: False)
        with pytest.raises(OutputError, match="not writable"):
            gio.check_output_folder(tmp_path / "a")

    def test_write_problem_names_the_cause(self):
        assert gio.write_problem(OSError(28, "x")) == "no space left on the device (disk full)"
        assert gio.write_problem(OSError(30, "x")) == "read-only file system"
        assert gio.write_problem(OSError(5, "Input/output error")) == "Input/output error"


class TestDepthPngValues:
    def test_values_and_range(self):
        v = gio.depth_png_values(np.array([[0.0, 1.0], [np.nan, -2.0]]))
        assert v.dtype == np.uint16 and v.tolist() == [[0, 256], [0, 0]]
        assert gio.depth_png_values(np.array([[255.99]])).item() == 65533
        with pytest.raises(InvalidDepthError, match="256.0 m"):
            gio.depth_png_values(np.array([[256.1]]))
        assert gio.depth_png_values(np.array([[60.0]]), 1e-3).item() == 60000
        with pytest.raises(ShapeError):
            gio.depth_png_values(np.ones(3))
        with pytest.raises(ShapeError):
            gio.depth_png_values(np.array([["a"]]))

    @pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "1", None, True])
    def test_check_png_scale(self, bad):
        with pytest.raises(InvalidInputError, match="png_scale"):
            gio.check_png_scale(bad)
        assert gio.check_png_scale(np.float32(0.5)) == 0.5


class TestWriteJson:
    def test_numpy_nan_paths_tuples(self, tmp_path):
        import json

        from gpdepth3d.io import to_jsonable, write_json

        data = {
            "a": np.float32(1.5),
            "b": np.int64(3),
            "c": float("nan"),
            "d": (1, np.inf),
            "e": np.arange(3),
            "f": tmp_path,
            "g": [np.bool_(True)],
        }
        path = write_json(tmp_path / "x.json", data)
        assert path == tmp_path / "x.json"
        loaded = json.loads(path.read_text())
        assert loaded == {"a": 1.5, "b": 3, "c": None, "d": [1, None], "e": [0, 1, 2], "f": str(tmp_path), "g": [True]}
        assert to_jsonable(data) == loaded
        assert path.read_text().endswith("\n") and not list(tmp_path.glob(".*tmp*"))

    def test_unserialisable_raises_and_writes_nothing(self, tmp_path):
        from gpdepth3d.io import write_json

        with pytest.raises(TypeError):
            write_json(tmp_path / "x.json", {"a": object()})
        assert not list(tmp_path.iterdir())
