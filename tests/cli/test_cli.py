"""The command line end to end: demo, complete (7-Scenes with sampled points, KITTI raw Velodyne), errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gpdepth3d.cli import main
from gpdepth3d.completion.complete import DepthPosterior
from gpdepth3d.io import load_depth
from gpdepth3d.measurements import downsample_depth


def _write_7scenes_inputs(root: Path, tmp_path: Path, n_points: int = 300):
    """Stand-in MDE (Kinect depth blurred, scaled, noised: not a network) and points sampled from the depth."""
    import cv2

    gt = load_depth(root / "7scenes" / "frame-000000.depth.png", png_scale=1e-3, invalid_value=65535)
    gt = downsample_depth(gt, 4)
    rng = np.random.default_rng(0)
    filled = np.where(gt > 0, gt, np.median(gt[gt > 0]))
    mde = cv2.GaussianBlur(filled, (0, 0), 3) * 1.15 * np.exp(rng.normal(0, 0.02, gt.shape))
    np.save(tmp_path / "mde.npy", mde)
    v, u = np.nonzero(gt > 0)
    pick = rng.choice(v.size, n_points, replace=False)
    np.savetxt(tmp_path / "points.txt", np.stack([u[pick], v[pick], gt[v[pick], u[pick]]], 1))
    np.save(tmp_path / "gt.npy", gt)
    return gt, mde


class TestCompleteCommand:
    def test_7scenes_prior_and_sampled_points(self, shared_data, tmp_path, capsys):
        gt, mde = _write_7scenes_inputs(shared_data, tmp_path)
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "mde.npy"),
                "--sparse",
                str(tmp_path / "points.txt"),
                "--output",
                str(tmp_path / "out" / "frame0"),
                "--gt",
                str(tmp_path / "gt.npy"),
                "--preset",
                "residual",
            ]
        )
        assert code == 0
        out = capsys.readouterr().out
        assert "wrote" in out and "RMSE [mm]" in out and "iRMSE [1/km]" in out  # units in the table header
        assert "+-2 sigma" in out and "median |error| / sigma" in out and "AUSE" in out  # the calibration line
        for kind in ("depth", "sigma", "error"):  # previews a person can look at, beside the 16-bit PNGs
            preview = tmp_path / "out" / f"frame0_{kind}_preview.png"
            assert preview.is_file() and f"wrote {preview}" in out
        post = DepthPosterior.load(tmp_path / "out" / "frame0.npz")
        assert post.mean.shape == gt.shape
        valid = gt > 0
        rmse_mde = np.sqrt(np.mean((mde[valid] - gt[valid]) ** 2))
        rmse_gp = np.sqrt(np.mean((post.mean[valid] - gt[valid]) ** 2))
        assert rmse_gp < 0.6 * rmse_mde
        assert np.all(post.variance > 0)
        png = load_depth(tmp_path / "out" / "frame0_mean.png")  # KITTI convention metres * 256
        np.testing.assert_allclose(png, post.mean, atol=1 / 256)

    def test_fitted_hyperparameters_from_the_command_line(self, shared_data, tmp_path, capsys):
        from gpdepth3d.completion.complete import DepthCompleter
        from gpdepth3d.completion.marginal_fit import log_marginal_likelihood
        from gpdepth3d.gp.model import DepthGPConfig
        from gpdepth3d.io import load_sparse

        gt, mde = _write_7scenes_inputs(shared_data, tmp_path, n_points=150)
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "mde.npy"),
                "--sparse",
                str(tmp_path / "points.txt"),
                "--output",
                str(tmp_path / "fit"),
                "--no-png",
                "--preset",
                "residual",
                "--gp.fit",
            ]
        )
        assert code == 0 and "wrote" in capsys.readouterr().out
        post = DepthPosterior.load(tmp_path / "fit.npz")
        valid = gt > 0
        assert np.sqrt(np.mean((post.mean[valid] - gt[valid]) ** 2)) < np.sqrt(np.mean((mde[valid] - gt[valid]) ** 2))
        # the written posterior is the one of hyperparameters fitted to this frame (higher likelihood)
        sparse = load_sparse(tmp_path / "points.txt", mde.shape)
        fixed = DepthGPConfig.residual()
        fitted = DepthCompleter(fixed.replace(fit=True))(mde, sparse)
        np.testing.assert_allclose(post.mean, fitted.mean, atol=1e-6)
        assert log_marginal_likelihood(mde, sparse, fitted.config.replace(fit=False)) > log_marginal_likelihood(
            mde, sparse, fixed
        )

    def test_kitti_raw_velodyne_projected_by_the_library(self, shared_data, tmp_path, capsys):
        from scipy.ndimage import distance_transform_edt, gaussian_filter

        import gpdepth3d as g

        folder = shared_data / "kitti_object"
        calib = g.LidarCalibration.from_kitti(folder / "calib_000000.txt")
        lidar = calib.project(g.load_velodyne(folder / "000000.bin"), (375, 1242))
        small = downsample_depth(lidar.to_depth_map(), 3)
        _, (ri, ci) = distance_transform_edt(small == 0, return_indices=True)
        np.save(tmp_path / "mde.npy", gaussian_filter(small[ri, ci] * 1.3, 2.0))  # stand-in MDE, 125 x 414
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "mde.npy"),
                "--lidar",
                str(folder / "000000.bin"),
                "--calib",
                str(folder / "calib_000000.txt"),
                "--lidar-image-size",
                "375",
                "1242",
                "--output",
                str(tmp_path / "kitti"),
                "--no-png",
                "--preset",
                "residual",
            ]
        )
        assert code == 0
        post = DepthPosterior.load(tmp_path / "kitti.npz")
        assert post.mean.shape == (125, 414)
        assert len(post.sparse) > 3000
        # At the measured pixels the posterior follows the LiDAR closely.
        r, c = post.sparse.v.astype(int), post.sparse.u.astype(int)
        assert np.median(np.abs(post.mean[r, c] - post.sparse.depth)) < 0.2
        assert "wrote" in capsys.readouterr().out


class TestErrors:
    def test_missing_file_is_one_line_and_exit_1(self, tmp_path, capsys):
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "nope.npy"),
                "--sparse",
                str(tmp_path / "p.txt"),
                "--output",
                str(tmp_path / "o"),
            ]
        )
        assert code == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "nope.npy" in err[0] and "not found" in err[0]
        assert not list(tmp_path.iterdir())

    def test_both_sources_rejected(self, tmp_path, capsys):
        np.save(tmp_path / "mde.npy", np.ones((8, 8)))
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "mde.npy"),
                "--sparse",
                "a.txt",
                "--lidar",
                "b.bin",
                "--output",
                str(tmp_path / "o"),
            ]
        )
        assert code == 1
        assert "--sparse / --lidar" in capsys.readouterr().err
        assert not (tmp_path / "o.npz").exists()

    def test_intrinsics_that_do_not_fit_the_image(self, tmp_path, capsys):
        np.save(tmp_path / "mde.npy", np.ones((48, 64)))
        np.savetxt(tmp_path / "K.txt", [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
        np.savetxt(tmp_path / "xyz.txt", [[0.0, 0.0, 1.0]])
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "mde.npy"),
                "--sparse",
                str(tmp_path / "xyz.txt"),
                "--sparse-points",
                "xyz",
                "--intrinsics",
                str(tmp_path / "K.txt"),
                "--output",
                str(tmp_path / "o"),
            ]
        )
        assert code == 1
        assert "principal point" in capsys.readouterr().err


class TestIntrinsicsTravelWithThePosterior:
    def test_complete_saves_k_of_the_output_grid_and_view_reads_it(self, tmp_path, capsys):
        from gpdepth3d.viewer.scene_data import stored_intrinsics

        np.save(tmp_path / "mde.npy", np.full((48, 64), 2.0))
        np.savetxt(tmp_path / "xyz.txt", [[0.0, 0.0, 2.1], [0.5, 0.2, 2.2], [-0.4, -0.3, 1.9]])
        code = main(
            [
                "complete",
                "--mde",
                str(tmp_path / "mde.npy"),
                "--sparse",
                str(tmp_path / "xyz.txt"),
                "--sparse-points",
                "xyz",
                "--intrinsics",
                "50,50,31.5,23.5",
                "--output-size",
                "96",
                "128",
                "--output",
                str(tmp_path / "o"),
            ]
        )
        assert code == 0, capsys.readouterr().err
        K = stored_intrinsics(tmp_path / "o.npz")
        np.testing.assert_allclose(K, [[100.0, 0.0, 63.5], [0.0, 100.0, 47.5], [0.0, 0.0, 1.0]])  # scaled to 128x96


class TestOneLineErrors:
    @pytest.mark.parametrize(
        "argv, line",
        [
            (
                ["complete", "--mdee", "x"],
                "gpdepth3d complete: missing --mde, --output; unrecognised --mdee x (did you mean --mde?) (see gpdepth3d complete --help)",
            ),
            (["batch"], "gpdepth3d batch: missing --data, --output (see gpdepth3d batch --help)"),
            (
                ["complete", "--mde", "m.npy", "--output", "o", "--engine.name", "nope"],
                "--engine.name: expected one of exact, kissgp, fast, got nope (see gpdepth3d complete --help)",
            ),
            (["complete", "--mde"], "--mde: too few values (see gpdepth3d complete --help)"),
            (["--frob"], "gpdepth3d: unrecognised --frob (see gpdepth3d --help)"),
        ],
    )
    def test_parse_errors_are_one_line_naming_the_option(self, argv, line, capsys):
        assert main(argv) == 1
        out = capsys.readouterr()
        assert out.err.strip().splitlines() == [f"gpdepth3d: error: {line}"] and out.out == ""

    def test_events_of_other_tyro_versions_still_give_one_line(self):
        from gpdepth3d.cli._main import describe_parse_error

        class NewKindOfFailure:
            prog = "gpdepth3d"

        assert describe_parse_error(NewKindOfFailure(), "view") == (
            "gpdepth3d view: invalid command line (see gpdepth3d view --help)"
        )

    def test_a_tyro_without_the_hook_still_gives_one_line(self, monkeypatch, capsys):
        import gpdepth3d.cli._main as cli_main

        monkeypatch.setattr(cli_main, "_parse_error_hook", lambda command: None)
        assert main(["complete", "--mdee", "x"]) == 1
        out = capsys.readouterr()
        assert out.err.strip().splitlines() == [
            "gpdepth3d: error: gpdepth3d complete: invalid command line (see gpdepth3d complete --help)"
        ]
        with pytest.raises(SystemExit) as info:
            main(["complete", "--help"])
        assert info.value.code == 0 and "--mde" in capsys.readouterr().out

    def test_bad_option_value_is_one_line_exit_1(self, tmp_path, capsys):
        code = main(
            ["complete", "--mde", "m.npy", "--output", str(tmp_path / "o"), "--preset", "paper", "--gp.nu", "3.7"]
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and len(err) == 1
        assert (
            err[0]
            == "gpdepth3d: error: --gp.nu: expected 0.5, 1.5 or 2.5, got float 3.7 (see gpdepth3d complete --help)"
        )

    def test_help_is_untouched(self, capsys):
        import pytest

        with pytest.raises(SystemExit) as info:
            main(["complete", "--help"])
        assert info.value.code == 0
        out = capsys.readouterr()
        assert "--mde" in out.out and "error" not in out.err

    def test_unexpected_errors_are_one_line_too(self, tmp_path, capsys, monkeypatch):
        import pytest

        import gpdepth3d.io as gio

        def broken(*a, **k):
            raise TypeError("a bug")

        monkeypatch.setattr(gio, "load_depth", broken)
        argv = ["complete", "--mde", "m.npy", "--sparse", "p.txt", "--output", str(tmp_path / "o")]
        assert main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert err == ["gpdepth3d: error: unexpected TypeError: a bug (set GPDEPTH3D_DEBUG=1 for the traceback)"]
        monkeypatch.setenv("GPDEPTH3D_DEBUG", "1")
        with pytest.raises(TypeError):
            main(argv)

    def test_dropped_points_warn_on_one_line(self, tmp_path, capsys):
        np.save(tmp_path / "mde.npy", np.full((12, 16), 2.0))
        np.savetxt(tmp_path / "p.txt", [[1, 1, 2.0], [2, 2, np.nan], [40, 2, 2.0]])
        argv = [
            "complete",
            "--mde",
            str(tmp_path / "mde.npy"),
            "--sparse",
            str(tmp_path / "p.txt"),
            "--output",
            str(tmp_path / "o"),
            "--preset",
            "residual",
            "--engine.name",
            "exact",
        ]
        assert main(argv) == 1 and "2 of 3 rows" in capsys.readouterr().err
        assert main(argv[:7] + ["--drop-invalid-points"] + argv[7:]) == 0
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            f"gpdepth3d: warning: {tmp_path / 'p.txt'}: dropped 2 of 3 rows (1 with a NaN/inf/<= 0 depth, "
            "the others outside the 16x12 image)"
        ]


class TestDemoCommand:
    @pytest.mark.slow  # several seconds (CPU) on 2 cores: run by .ci/run (-m slow)
    def test_demo_runs_from_the_installed_entry_point(self, tmp_path):
        proc = subprocess.run(
            [sys.executable, "-m", "gpdepth3d.cli", "demo", "--output", str(tmp_path / "demo")],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert proc.returncode == 0, proc.stderr
        assert "outputs are in" in proc.stdout
        lines = {
            line.split()[0]: line for line in proc.stdout.splitlines() if line[:3] in ("mde", "gp-") and ":" not in line
        }
        rmse = {k: float(v.split()[1]) for k, v in lines.items()}
        mae = {k: float(v.split()[2]) for k, v in lines.items()}
        assert rmse["gp-residual"] < rmse["mde"] and rmse["gp-paper"] < rmse["mde"]
        # A global scale helps on average but not the far, large errors that RMSE weighs: compare MAE.
        assert mae["gp-residual"] < mae["mde+scale"] < mae["mde"]
        assert (tmp_path / "demo" / "gp-paper.npz").is_file()
        # the figure and the cloud show the default model; the table says why a global scale can lose in RMSE
        assert (tmp_path / "demo" / "gp-default.png").is_file() and (
            tmp_path / "demo" / "gp-default_cloud.ply"
        ).is_file()
        assert "mde+scale is the MDE times one global scale" in proc.stdout


class TestThirdPartyNoise:
    def test_numba_tbb_warning_is_silenced_and_colour_codes_stripped(self, monkeypatch, capsys, tmp_path):
        import functools
        import warnings

        import gpdepth3d.cli.demo as demo

        original = demo.demo_command

        @functools.wraps(original)
        def noisy(**kwargs):
            warnings.warn_explicit(
                "\x1b[1mThe TBB threading layer requires TBB version 2021 update 6\x1b[0m",
                UserWarning,
                "parallel.py",
                1,
                module="numba.np.ufunc.parallel",
            )
            warnings.warn_explicit("\x1b[1mSomething a user\nshould see\x1b[0m", UserWarning, "x.py", 1, module="other")

        monkeypatch.setattr(demo, "demo_command", noisy)
        assert main(["demo", "--output", str(tmp_path / "d")]) == 0
        err = capsys.readouterr().err.strip().splitlines()
        assert err == ["gpdepth3d: warning: Something a user should see"]


@pytest.mark.parametrize("given, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_command_lets_idle_threads_sleep_unless_told(given, expected, monkeypatch, capsys):
    """``gpdepth3d`` runs with OMP_WAIT_POLICY=PASSIVE (spinning threads slow a shared machine); a user's own
    setting stands."""
    import os

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    if given is not None:
        monkeypatch.setenv("OMP_WAIT_POLICY", given)
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    assert os.environ["OMP_WAIT_POLICY"] == expected
