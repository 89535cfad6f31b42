"""What ``gpdepth3d map`` leaves on disk: the same bytes from two identical runs, one set after a kill, and
one error line under a file-size limit. Each runs the console entry point in a subprocess on the first
HoloLens images (``--frames``), with ``TMPDIR`` pointing at a folder of the test's own to see leftovers."""

from __future__ import annotations

import os
import random
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gpdepth3d import io as gio

ROOT = Path(__file__).resolve().parents[2]
NAMES = ["cloud.ply", "keyframes.npz", "mapper.json", "mesh.ply", "metrics.json", "volume.json", "volume.npz"]
SET_MEMBERS = ["mesh.ply", "mesh.glb", "mesh.obj", *NAMES]


@pytest.fixture()
def run_map(shared_data, tmp_path):
    """``run_map(output, frames, **popen)`` -> the `subprocess.Popen` of a `map` run on the first HoloLens images."""
    models = ROOT.parent / "shared" / "models"
    if not (models / "fast_depth_224.tflite").is_file():
        pytest.skip("FastDepth model not found in ../shared/models")
    holo = shared_data / "hololens"
    scratch = tmp_path / "tmpdir"
    scratch.mkdir()
    env = {**os.environ, "GPDEPTH3D_MODELS": str(models), "TMPDIR": str(scratch), "PYTHONPATH": str(ROOT)}

    def start(output: Path, frames: int, **kw) -> subprocess.Popen:
        argv = [sys.executable, "-m", "gpdepth3d.cli", "map", "--images", str(holo / "images"), "--poses"]
        argv += [str(holo / "poses_images.txt"), "--intrinsics", str(holo / "K.txt"), "--depth", str(holo / "depth")]
        argv += ["--frames", str(frames), "--output", str(output)]
        return subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)

    start.scratch = scratch
    return start


def _files(folder: Path) -> dict[str, bytes]:
    """Every entry of ``folder`` (hidden ones included) with its bytes."""
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())} if folder.is_dir() else {}


def _f_line(out: str) -> str:
    return next(line for line in out.splitlines() if line.startswith("F-score at"))


@pytest.mark.slow
def test_two_identical_runs_write_the_same_mesh_and_cloud(run_map, tmp_path):
    """The mesh and the cloud are in a canonical order (Open3D's threads give another order each run) and
    the F-score is computed over that order: two runs give the same bytes and print the same F."""
    outs = []
    for k in range(2):
        proc = run_map(tmp_path / f"run{k}", 6)
        out, err = proc.communicate(timeout=900)
        assert proc.returncode == 0, err[-2000:]
        outs.append(out)
    a, b = _files(tmp_path / "run0"), _files(tmp_path / "run1")
    assert sorted(a) == NAMES
    for name in ("mesh.ply", "cloud.ply"):
        assert a[name] == b[name], name
    assert _f_line(outs[0]) == _f_line(outs[1])
    assert re.search(r"wrote 7 files \([0-9.]+ MB\)", outs[0])


@pytest.mark.slow
def test_file_size_limit_gives_one_error_line_and_keeps_the_old_set(run_map, tmp_path):
    """Under ``ulimit -f`` a write fails with EFBIG (Python ignores SIGXFSZ): one error line, exit 1, the
    set written before is kept whole, and nothing is left in the output folder or in $TMPDIR."""
    out_dir = tmp_path / "out"
    proc = run_map(out_dir, 3)
    assert proc.wait(timeout=900) == 0, proc.stderr.read()[-2000:]
    before = _files(out_dir)
    assert sorted(before) == NAMES
    limit = 1_500_000  # bytes: the mesh, the cloud and the keyframe store fit, the volume does not

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = run_map(out_dir, 4, preexec_fn=limited)
    out, err = proc.communicate(timeout=900)
    errors = [line for line in err.splitlines() if line.startswith("gpdepth3d: error:")]
    assert proc.returncode == 1, err[-2000:]
    assert len(errors) == 1 and "Traceback" not in err, err[-2000:]
    assert "volume.npz: cannot write: file too large: the file size limit (ulimit -f) was reached" in errors[0]
    assert errors[0].count("cannot write") == 1, errors[0]
    print(errors[0])
    assert _files(out_dir) == before  # the old set, nothing hidden beside it
    assert list(run_map.scratch.iterdir()) == []


@pytest.mark.slow
def test_killed_map_leaves_the_old_or_the_new_set_and_nothing_else(run_map, tmp_path):
    """SIGKILL of `map` at random moments (in its frames, its writes, its commit): after the output
    folder's recovery (`Mapper.load`) it holds the old set or the new one, $TMPDIR stays empty, and
    the next run leaves exactly its set."""
    from gpdepth3d.mapping.mapper import Mapper

    out_dir = tmp_path / "out"
    t0 = time.monotonic()
    proc = run_map(out_dir, 3)
    assert proc.wait(timeout=900) == 0, proc.stderr.read()[-2000:]
    duration = time.monotonic() - t0
    old = _files(out_dir)
    rng = random.Random(0)
    outcome = {"killed": 0, "finished": 0, "old set": 0, "new set": 0}
    rounds = int(os.environ.get("GPDEPTH3D_KILL_ROUNDS", "3"))
    for k in range(rounds):
        proc = run_map(out_dir, 4 + k % 2)
        time.sleep(rng.uniform(0.6, 1.1) * duration)
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        proc.communicate()
        outcome["killed" if proc.returncode == -signal.SIGKILL else "finished"] += 1
        Mapper.load(out_dir)  # the output folder's recovery: finishes a begun commit or removes temporaries
        gio.clean_output_set(out_dir / "map", SET_MEMBERS)
        got = _files(out_dir)
        assert sorted(got) == NAMES, f"round {k}: {sorted(got)}"
        outcome["old set" if got == old else "new set"] += 1
        old = got
        assert list(run_map.scratch.iterdir()) == [], f"round {k}: staging left in $TMPDIR"
    print(f"kills of map: {outcome}")
    assert outcome["killed"] >= 1
    proc = run_map(out_dir, 3)
    assert proc.wait(timeout=900) == 0
    assert sorted(_files(out_dir)) == NAMES  # the next run: its set, no temporary
