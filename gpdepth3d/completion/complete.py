"""Depth completion: the public entry point `complete()` and `DepthCompleter` for sequences.

Input rules (documented once, here):

* ``mde_depth``: (H, W) float z-depth in metres. 0, NaN and +/-inf mark pixels with no MDE
  depth (they are not observations). Negative depths raise `InvalidDepthError`.
* ``sparse``: `SparseDepth`. Its image may have another resolution than the MDE as long as it
  shows the same image (equal aspect ratio within 1 %): points are moved to the MDE grid keeping
  the closest point per pixel. An empty set is allowed: the result is then the GP given the MDE
  alone (balanced) or the prior (residual: the MDE with the prior's large variance).
* ``output_shape``: (Ho, Wo) of the result; defaults to the MDE shape and may be larger (the
  paper's M > N upsampling) or smaller. Output pixel centres are placed with the pixel-centre
  convention in the MDE grid.
"""

from __future__ import annotations

import contextlib
import json
import time
import warnings
import zipfile
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from ..errors import DataFormatError, GPDepthError, InvalidInputError, ProblemTooLargeError, describe
from ..gp import EngineConfig, SolveInfo, make_engine
from ..gp.model import DepthGPConfig, GridProblem, Kernel, output_coordinates, separable_correlation
from ..mde.align import AlignmentResult
from ..measurements import SparseDepth
from ..depthmap import fill_nearest, resize_map
from ._assemble import assemble
from .problem import _frame_inputs, build_problem, check_mde_depth


@dataclass(frozen=True)
class DepthPosterior:
    """GP posterior of the depth field on the output grid.

    Attributes:
        mean: (Ho, Wo) posterior mean z-depth, metres.
        variance: (Ho, Wo) posterior marginal variance of the depth, m^2.
        mde: (Ho, Wo) the input MDE depth resampled to the output grid (metres, 0 = none), for
            comparison.
        sparse: The measurements as used, on the GP grid (closest point per pixel).
        config: The model configuration.
        depth_scale: The depth scale (metres) that relative units were multiplied by.
        alignment: Scale/shift applied to the MDE (residual formulation), else identity.
        timings: Seconds spent per stage ("fit": hyperparameter fit when config.fit, "setup", "solve").
        rejected: (N,) bool over ``sparse``: points rejected as outliers (log_residual: their
            leave-one-out z-score given their neighbours exceeded ``config.outlier_threshold``).
        warnings: What the posterior could not support, one sentence each (also issued as
            `PosteriorWarning`): an MDE whose scale disagrees with the points by more than a
            factor of 2, almost no points, points covering little of the image, many rejected, an
            MDE whose depth differences the points barely follow (fitted slope < 0.2), an MDE
            error the points show to be > 1.25x the configured s (``raise_outputscale``); for the
            Gaussian formulations (``balanced``, ``residual``) the MDE's scale and pixels whose
            mean is <= 0 m.
        solve: The engine's facts of this call (`gpdepth3d.gp.SolveInfo`: route, seconds per
            stage); None for a posterior read from a file.
        mde_slope: log_residual: the MDE's log-depth coefficient fitted to this frame
            (`gpdepth3d.gp.slope`; 1 when not fitted): below 1 the points say the MDE over-states
            the depth differences of the scene.
    """

    mean: np.ndarray
    variance: np.ndarray
    mde: np.ndarray
    sparse: SparseDepth
    config: DepthGPConfig
    depth_scale: float
    alignment: AlignmentResult = field(default_factory=lambda: AlignmentResult(1.0, 0.0, 0))
    timings: dict = field(default_factory=dict)
    rejected: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    solve: SolveInfo | None = None
    mde_slope: float = 1.0

    @property
    def n_rejected(self) -> int:
        """Number of measurements rejected as outliers."""
        return 0 if self.rejected is None else int(np.count_nonzero(self.rejected))

    @property
    def std(self) -> np.ndarray:
        """(Ho, Wo) posterior standard deviation, metres."""
        return np.sqrt(np.maximum(self.variance, 0.0))

    @property
    def shape(self) -> tuple[int, int]:
        return self.mean.shape  # type: ignore[return-value]

    def save(self, path: str | Path, *, png: bool = False) -> list[Path]:
        """Writes ``mean``, ``variance``, ``std`` and ``mde`` to ``<path>.npz``, as one set with the PNGs.

        With ``png=True`` also writes ``<stem>_mean.png`` and ``<stem>_std.png`` as 16-bit PNG in
        the KITTI convention (value = metres * 256): values beyond the format's 256 m are stored
        as 65535 with a `gpdepth3d.io.PNGRangeWarning` counting them (the npz keeps the true
        values). The files of one call appear together or not at all, as plain files
        (`gpdepth3d.io.atomic_write_set`; inside a `gpdepth3d.io.output_set` they join it), and
        PNGs of an earlier call with ``png=True`` do not survive a later ``png=False`` call.

        Returns:
            The written paths (npz first).

        Raises:
            OutputError: the path is empty, a directory or too long, or a file cannot be written.
        """
        from ..io import atomic_write_set, check_output_path, depth_png_values, npz_writer, png_writer

        path = check_output_path(path)
        path = path.with_suffix(".npz")
        stem = path.stem
        npz_name, png_names = f"{stem}.npz", (f"{stem}_mean.png", f"{stem}_std.png")
        writers = {
            npz_name: npz_writer(
                mean=self.mean.astype(np.float32),
                variance=self.variance.astype(np.float32),
                std=self.std.astype(np.float32),
                mde=self.mde.astype(np.float32),
                sparse_uvd=np.stack([self.sparse.u, self.sparse.v, self.sparse.depth], 1).astype(np.float32),
                sparse_image_size=np.array(self.sparse.image_size),
                depth_scale=np.float64(self.depth_scale),
                alignment=np.array([self.alignment.scale, self.alignment.shift]),
                mde_slope=np.float64(self.mde_slope),
                config_json=np.array(json.dumps(asdict(self.config))),
                rejected=np.zeros(len(self.sparse), bool) if self.rejected is None else np.asarray(self.rejected, bool),
                warnings=np.array(self.warnings, dtype=str),
            )
        }
        if png:
            for name, values, arg in (
                (png_names[0], self.mean, "mean"),
                (png_names[1], self.std, "std"),
            ):
                values = depth_png_values(values, argument=f"posterior {arg} ({path.parent / name})", saturate=True)
                writers[name] = png_writer(values, path.parent / name)
        return atomic_write_set(path.with_suffix(""), writers, members=(npz_name, *png_names))

    @classmethod
    def load(cls, path: str | Path, config: DepthGPConfig | None = None) -> "DepthPosterior":
        """Reads a posterior written by `save`, with the config that made it.

        ``config`` replaces the stored config (files written before it was stored get
        ``config`` or `DepthGPConfig()`). A save a kill interrupted is finished first
        (`gpdepth3d.io.clean_output_set`), so the files read belong to one call.

        Raises:
            DataFormatError: a missing or corrupt file, a stored config that is not a JSON object,
                a mean with no finite value, or a variance that is negative or not finite.
        """
        from ..io import check_stored_array, clean_output_set

        path = Path(path)
        with contextlib.suppress(GPDepthError, OSError):  # a read-only folder: read what is there
            clean_output_set(path.with_suffix(""))
        if not path.is_file():
            raise DataFormatError(path, "posterior file not found")
        try:
            data = np.load(path, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError("an .npz archive expected (this is a single array)")
            with data as d:
                for k in ("mean", "variance", "mde", "sparse_uvd"):  # forged sizes refused before allocating
                    check_stored_array(path, k)
                uvd = d["sparse_uvd"].astype(np.float64)
                size = tuple(int(x) for x in d["sparse_image_size"])
                sparse = SparseDepth(uvd[:, 0], uvd[:, 1], uvd[:, 2], size)
                align = d["alignment"]
                mean, variance, mde = (d[k].astype(np.float64) for k in ("mean", "variance", "mde"))
                if mean.ndim != 2 or variance.shape != mean.shape or mde.shape != mean.shape:
                    raise ValueError(f"mean {mean.shape}, variance {variance.shape}, mde {mde.shape}: not one 2-D grid")
                if not np.any(np.isfinite(mean)):
                    raise ValueError("the mean has no finite value")
                if not np.all(np.isfinite(variance)) or np.any(variance < 0):
                    bad = int(np.count_nonzero(~(np.isfinite(variance) & (variance >= 0))))
                    raise ValueError(f"{bad} variances negative or not finite (a variance is finite and >= 0)")
                if config is None and "config_json" in d.files:
                    stored = json.loads(str(d["config_json"]))
                    if not isinstance(stored, dict):
                        raise ValueError(f"config_json: expected a JSON object, got a JSON {type(stored).__name__}")
                    known = {f.name for f in fields(DepthGPConfig)}
                    config = DepthGPConfig(**{k: v for k, v in stored.items() if k in known})
                rejected = d["rejected"].astype(bool) if "rejected" in d.files else None
                if rejected is not None and rejected.shape != (len(sparse),):
                    raise ValueError(f"rejected {rejected.shape}: not one flag per point ({len(sparse)})")
                return cls(
                    mean=mean,
                    variance=variance,
                    mde=mde,
                    sparse=sparse,
                    config=config or DepthGPConfig(),
                    depth_scale=float(d["depth_scale"]),
                    alignment=AlignmentResult(float(align[0]), float(align[1]), 0),
                    rejected=rejected,
                    warnings=tuple(str(w) for w in d["warnings"]) if "warnings" in d.files else (),
                    mde_slope=float(d["mde_slope"]) if "mde_slope" in d.files else 1.0,
                )
        except ProblemTooLargeError:
            raise
        except (KeyError, ValueError, TypeError, IndexError, OSError, EOFError, zipfile.BadZipFile, GPDepthError) as exc:
            raise DataFormatError(path, f"not a gpdepth3d posterior file: {exc}") from None


class PosteriorWarning(UserWarning):
    """The input of a frame cannot support a confident posterior (see `DepthPosterior.warnings`)."""


#: Thresholds of the posterior's warnings (log_residual).
SCALE_WARN_FACTOR = 2.0
FEW_POINTS = 10
COVERAGE_WARN = 0.5
COVERAGE_REACH = 6.0  # a pixel is far from the points beyond max(H, W) / 6 (taxicab)
REJECTED_WARN = 0.2
SCALE_VAR_SHARE = 0.05  # Var[b] below this share of tau^2: bounded, not solved for
SLOPE_WARN = 0.2  # a fitted MDE slope below this: the MDE's shape is barely used
OUTPUTSCALE_WARN = 1.25  # s raised by the points above this factor of the configured s
WEIGHT_FLOOR = 1e-3  # depth-aware correlation: pixels whose kriging weights sum below this keep rho = 1


def _edge_range_at(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """`_edge_range` over a 3 x 3 window, at the pixels (rows, cols) only (borders: the edge pixel repeated)."""
    h, w = depth.shape
    around = [depth[np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)] for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
    return np.max(around, axis=0) - np.min(around, axis=0)


_BLAS_CONTROLLER = None


def _single_threaded_blas():
    """Context limiting BLAS to one thread (the controller found once: finding the libraries costs ~3 ms)."""
    global _BLAS_CONTROLLER
    if _BLAS_CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _BLAS_CONTROLLER = ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")


def _edge_range(depth: np.ndarray, window: int) -> np.ndarray:
    """Local depth range (max - min) over a window x window neighbourhood, metres.

    OpenCV's dilate / erode: the same values as SciPy's maximum_filter / minimum_filter (whose
    border mirroring adds no new value to a max or min), ~4x faster (375 x 1242, window 7: 9 vs
    34 ms).
    """
    import cv2

    kernel = np.ones((window, window), np.uint8)
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    return cv2.dilate(depth, kernel) - cv2.erode(depth, kernel)


SPARSE_LATTICE_SHARE = 1 / 32
"""`lattice_stride`: points on at most this share of the pixels are sparse (mean spacing >= 5.7 px)."""
DETAIL_LATTICE_SHARE = 1 / 10
"""`lattice_stride`, nu = 0.5: points on at most this share of the pixels take every 2nd pixel, the detail kriged back (`gp.sublattice`)."""
DENSE_LATTICE_STRIDE = 4
"""`lattice_stride`, nu = 0.5: denser points take every 4th pixel, the detail kriged back from 10 x 10-pixel windows."""
MIN_LATTICE_LENGTHSCALE = 8.0
"""`lattice_stride`: a lattice of stride k only for length scales of at least k / 2 times this many pixels."""


def lattice_stride(config: DepthGPConfig, h: int, w: int, n_points: int, lengthscale: float,
                   output_shape: tuple[int, int] | None = None) -> int:
    """Pixels of the GP grid per node of the log-residual GP's lattice, per side.

    ``config.lattice_stride`` when set (reduced until the lattice has 2 nodes per side). Else, on a
    grid of at least 16 x 16 pixels: with nu = 0.5 and an output at least as fine as the grid
    (``output_shape``, None: the grid itself), where the field's detail below the lattice is kriged
    back from the points (`gpdepth3d.gp.sublattice`), 2 when the points are on at most
    `DETAIL_LATTICE_SHARE` of the h x w pixels and `DENSE_LATTICE_STRIDE` (4) above; otherwise 2 up to
    `SPARSE_LATTICE_SHARE` and 1 above. A stride k needs a length scale of at least
    k / 2 x `MIN_LATTICE_LENGTHSCALE` pixels (else the next finer stride that has one).

    Measured (bench/results/lattice.json, kitti_tiny at 1/3 = 125 x 414, 20 % of the LiDAR held out,
    RMSE and time against every pixel): up to 1/4 of the LiDAR (6 % of the pixels) stride 2 has
    0.97-1.00x the RMSE, +-2 sigma 94.7-95.2 % (every pixel 93.6-94.7 %), in about half the time;
    from 1/2 of the LiDAR on stride 4 has 0.99-1.01x the RMSE in 0.57-0.78x the time (stride 2:
    1.02x). Without the detail (nu != 0.5, coarser outputs) a coarse lattice costs 4 % RMSE at 1/4
    of the LiDAR and 21 % with all of it, so only sparse points take one there.
    """
    k = config.lattice_stride
    if k is None:
        detail = config.nu == 0.5 and (output_shape is None or (output_shape[0] >= h and output_shape[1] >= w))
        if min(h, w) < 16:
            k = 1
        elif n_points <= (DETAIL_LATTICE_SHARE if detail else SPARSE_LATTICE_SHARE) * h * w:
            k = 2
        else:
            k = DENSE_LATTICE_STRIDE if detail else 1
        while k > 1 and lengthscale < k / 2 * MIN_LATTICE_LENGTHSCALE:
            k //= 2
    while k > 1 and (-(-h // k) < 2 or -(-w // k) < 2):
        k -= 1
    return k


def _at_points(fields: np.ndarray, rows: np.ndarray, cols: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(m, n) values of (m, Ho, Wo) output fields at the GP-grid pixels (rows, cols); output >= grid.

    The output's own pixels where they coincide with the grid's (same shape), else bilinear
    between output pixels (the fields there are lattice read-outs, smooth at the output's spacing).
    """
    _, ho, wo = fields.shape
    h, w = grid
    if (ho, wo) == (h, w):
        return fields[:, rows, cols]
    from scipy.ndimage import map_coordinates

    y = (rows + 0.5) * ho / h - 0.5  # the inverse of output_coordinates
    x = (cols + 0.5) * wo / w - 0.5
    return np.stack([map_coordinates(f, [y, x], order=1, mode="nearest") for f in fields])


def _log_residual_posterior(
    engine,
    mde: np.ndarray,
    valid: np.ndarray,
    grid_sparse: SparseDepth,
    out_shape: tuple[int, int],
    config: DepthGPConfig,
    *,
    variance: bool,
    frame: str | None,
    previous=None,
) -> tuple:
    """Posterior of the log-residual model (see `gpdepth3d.gp.model`).

    Returns:
        mean, variance, the `PointFit`, the fitted config, the rejected mask, the warnings, the
        global scale as an alignment, the timings, the engine's `SolveInfo` and the MDE's slope. ``previous`` (a `PointFit`) starts the fit's
        search from a previous frame's values.
    """
    from ..gp.local_calibration import local_variance_factor
    from ..gp.points import PointFit, screen_points
    from ..gp.slope import fit_mde_slope
    from ..gp.sublattice import sublattice_kriging

    t0 = time.perf_counter()
    h, w = mde.shape
    base = fill_nearest(mde, valid) if valid.any() else np.full((h, w), float(np.median(grid_sparse.depth)))
    rows = grid_sparse.v.astype(np.int64)
    cols = grid_sparse.u.astype(np.int64)
    z = grid_sparse.depth
    sig = grid_sparse.sigma
    unit = 1.0 if config.units == "metres" else z
    noise = np.where(np.isfinite(sig), sig / z, config.sigma_meas * unit / z) ** 2
    stated = np.where(np.isfinite(sig), sig / z, 0.0) ** 2  # the part the points' own sigmas state
    log_raw = np.log(base)
    # the MDE's log-depth range around each point (3 x 3): the edge term of the slope fit and the screen
    edge_raw = _edge_range_at(log_raw, rows, cols) if config.edge_sigma > 0 else None
    # the MDE's log-depth coefficient of this frame (gp.slope): the MDE is re-sloped about the
    # points' median log depth before anything else looks at it, and once more without the
    # points the screen rejects (one point at a tenth of its depth can still tilt a robust fit)
    slope = None
    fit_slope = config.mde_slope_sigma is not None and len(z) >= 3
    if fit_slope:
        slope_noise = noise
        if config.edge_sigma > 0:
            slope_noise = noise + (config.edge_sigma * edge_raw) ** 2
        slope_kernel = Kernel(config.nu, config.lengthscale, config.outputscale)

        def fitted_slope(use):
            with _single_threaded_blas():
                return fit_mde_slope(
                    rows[use], cols[use], np.log(z[use]), log_raw[rows[use], cols[use]], slope_noise[use],
                    slope_kernel, config.nugget, prior_sigma=config.mde_slope_sigma,
                )

        slope = fitted_slope(np.ones(len(z), dtype=bool))
    log_base = slope.apply(log_raw) if slope is not None else log_raw  # the (re-sloped) log MDE
    resid = np.log(z) - log_base[rows, cols]
    start = None
    if not config.fit:
        s2 = config.outputscale**2
        b = float(np.median(resid)) if len(z) else 0.0
        start = PointFit(config.lengthscale, config.outputscale, config.nugget, b, s2 / max(len(z), 1), len(z))
    if len(z) >= 3 or start is not None:
        around = (previous.lengthscale, previous.eta) if previous is not None else None
        # a point at an MDE depth edge is judged with the edge's uncertainty (the same term the
        # posterior's variance gets): there its neighbours may rightly disagree with it
        screen_noise = noise
        if config.edge_sigma > 0:
            edge = abs(slope.slope) * edge_raw if slope is not None else edge_raw  # the re-sloped MDE's range
            screen_noise = noise + (config.edge_sigma * edge) ** 2
        with _single_threaded_blas():  # small dense matrices: threads only contend (25-50x slower on 2 busy cores)
            fit, rejected, zscores, shares = screen_points(
                rows, cols, resid, screen_noise, threshold=config.outlier_threshold, nu=config.nu, start=start,
                around=around, raise_outputscale=start is not None and config.raise_outputscale, stated=stated,
            )
    else:  # fewer than 3 points: the configured scales, the points' median as the global scale
        b = float(np.median(resid)) if len(z) else 0.0
        fit = PointFit(config.lengthscale, config.outputscale, config.nugget, b, config.outputscale**2, len(z))
        rejected = np.zeros(len(z), dtype=bool)
        zscores = shares = np.zeros(len(z))
    if fit_slope and rejected.any() and np.count_nonzero(~rejected) >= 3:
        before = resid
        slope = fitted_slope(~rejected)
        log_base = slope.apply(log_raw)
        resid = np.log(z) - log_base[rows, cols]
        # the global scale follows: the same statistic as above (fixed: all points' median; fitted:
        # moved by the kept points' median change)
        b = float(np.median(resid)) if not config.fit else fit.log_scale + float(np.median((resid - before)[~rejected]))
        fit = replace(fit, log_scale=b)
    a = slope.slope if slope is not None else 1.0
    t1 = time.perf_counter()

    keep = ~rejected
    r, c = rows[keep], cols[keep]
    # the GP's lattice: every pixel, 2nd or 4th (see `lattice_stride`);
    # a point enters at its lattice node with the field's variance between its pixel and the node
    # added to its noise, points sharing a node by their precision-weighted mean (exact for them)
    k = lattice_stride(config, h, w, len(r), fit.lengthscale, out_shape)
    hl, wl = -(-h // k), -(-w // k)
    off_r, off_c = r - (k * (r // k) + (k - 1) / 2), c - (k * (c // k) + (k - 1) / 2)
    between = 2 * fit.outputscale**2 * (1 - separable_correlation(off_r, off_c, fit.lengthscale, config.nu)) if k > 1 else 0.0
    pp = 1.0 / (fit.nugget**2 + noise[keep] + between)
    cell = (r // k) * wl + c // k
    precision = np.bincount(cell, pp, hl * wl).astype(np.float64, copy=False).reshape(hl, wl)  # (int when empty)

    def on_lattice(v):  # per-point values -> the precision-weighted mean at each lattice node
        out = np.bincount(cell, pp * v, hl * wl).astype(np.float64, copy=False).reshape(hl, wl)
        np.divide(out, precision, out=out, where=precision > 0)
        return out

    obs = on_lattice(resid[keep] - fit.log_scale)
    out_rows = (output_coordinates(h, out_shape[0]) - (k - 1) / 2) / k
    out_cols = (output_coordinates(w, out_shape[1]) - (k - 1) / 2) / k
    kernel = Kernel(config.nu, fit.lengthscale / k, fit.outputscale)
    zeros_in, zeros_out = np.zeros((hl, wl)), np.zeros(out_shape)
    problem = GridProblem(zeros_in, obs, precision, out_rows, out_cols, zeros_out, kernel)
    same_grid = tuple(out_shape) == (h, w)
    base_out = np.exp(log_base) if slope is not None else base
    if not same_grid:
        base_out = resize_map(base_out, out_shape)
    log_out = log_base if same_grid else np.log(base_out)
    lz = config.depth_lengthscale
    depth_aware = lz is not None and len(r) > 0
    # the scale term below needs k(x)' (K + N)^-1 1 unless Var[b] is small; the depth-aware
    # correlation needs it and the kriging-weighted log MDE depth: further right-hand sides of
    # the one engine call, sharing its factorisation
    scale_term = variance and fit.log_scale_var > SCALE_VAR_SHARE * fit.nugget**2
    slope_term = variance and slope is not None and len(r) > 0
    extra = ()
    if depth_aware or scale_term or slope_term:
        extra = (np.where(precision > 0, 1.0, 0.0),)
    if depth_aware or slope_term:
        # the kriging-weighted (centred, not re-sloped) log MDE depth of the points: the
        # depth-aware correlation's zbar and the slope's variance term
        x_pts = log_raw[r, c]
        centre = slope.centre if slope is not None else float(np.median(x_pts))
        extra += (on_lattice(x_pts - centre),)
        if slope is None:
            x_out = log_out - centre
        else:
            x_out = (log_raw if same_grid else np.log(resize_map(base, out_shape))) - centre
    solution = engine.solve(problem, variance=variance, extra_obs=extra)
    g_mean, g_var = solution.mean, solution.variance
    w1 = solution.extra_means[0] if extra else None  # kriging weights' sum at each output pixel, k(x)' (K + N)^-1 1
    wx = solution.extra_means[1] if len(extra) > 1 else None  # k(x)' (K + N)^-1 (x - c) at each output pixel
    if k > 1 and config.nu == 0.5 and len(r) and out_shape[0] >= h and out_shape[1] >= w:
        # the field's detail below the lattice, kriged from the points' residuals against it
        # (gp.sublattice), for the mean, the variance and the extra right-hand sides alike; only for
        # outputs at least as fine as the GP grid, from which the lattice's values at the points are read
        targets = [resid[keep] - fit.log_scale]
        fields = [g_mean]
        if extra:
            targets.append(np.ones(len(r)))
            fields.append(w1)
        if len(extra) > 1:
            targets.append(x_pts - centre)
            fields.append(wx)
        at = _at_points(np.stack(fields), r, c, (h, w))
        # kriged at the GP grid's pixels, where the points are, and bilinear to a finer output: the
        # output pixels between grid pixels hold no point of their own (kitti_tiny, GP at 1/3, full
        # resolution: RMSE equal to or up to 0.4 % below kriging at every output pixel, +-2 sigma up to
        # 0.3 points lower; all of the LiDAR at stride 4: 195 -> 129 ms)
        corr, vred = sublattice_kriging(
            np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), r, c,
            np.stack(targets, 1) - at.T, fit.nugget**2 + noise[keep], (h, w), stride=k,
            lengthscale=fit.lengthscale, outputscale=fit.outputscale,
        )
        if not same_grid:
            corr = np.stack([resize_map(f, out_shape) for f in corr])
            vred = resize_map(vred, out_shape)
        g_mean = g_mean + corr[0]
        if variance:
            g_var = np.maximum(g_var - vred, 0.0)
        if extra:
            w1 = w1 + corr[1]
        if len(extra) > 1:
            wx = wx + corr[2]
    # per pixel, in one compiled pass (completion._assemble): the depth-aware correlation rho(x) =
    # exp(-a |x - c - wx / w1| / l_z) (gp.model: zbar(x) the kriging-weighted log MDE depth of the
    # points that inform x; rho = 1 where their weights sum below WEIGHT_FLOOR: there g's posterior is
    # its prior whatever rho is) scales E[g] and pulls Var[g] back to the prior; the global scale b
    # (flat prior) adds Var[b] (1 - rho k(x)' (K + N)^-1 1)^2 - bounded by Var[b] when Var[b] is at most
    # 5 % of the nugget variance (thousands of points: variance high by <= 5 %); the slope a adds
    # Var[a] (x(x) - c - rho k(x)' (K + N)^-1 (x - c))^2; the depth is log-normal
    mean, var = assemble(
        log_out, g_mean, g_var, w1, wx, x_out if (depth_aware or slope_term) else None,
        b=fit.log_scale, s2=fit.outputscale**2, tau2=fit.nugget**2, var_b=fit.log_scale_var,
        var_a=slope.slope_var if slope_term else 0.0, a=a, lz=lz if depth_aware else None, floor=WEIGHT_FLOOR,
        scale_term=scale_term, slope_term=slope_term, variance=variance,
    )
    if variance and config.edge_sigma > 0:
        factor = max(out_shape[0] / h, out_shape[1] / w)
        window = 2 * int(np.ceil(factor)) + 1
        var += (config.edge_sigma * np.exp(fit.log_scale) * _edge_range(base_out, window)) ** 2
    if variance and config.local_calibration is not None and len(r) >= FEW_POINTS:
        # the variance moved to where the points disagree with their neighbours (gp.local_calibration);
        # the screen's z-scores are those of the residuals before a refit of the slope without the
        # rejected points (the refit moves them little: it removes what the screen rejected)
        if config.outlier_threshold is None:  # no screen: the z-scores computed here
            from ..gp.points import loo_zscores

            with _single_threaded_blas():
                zscores, shares = loo_zscores(rows, cols, resid, screen_noise, fit, nu=config.nu, stated=stated)
        local = local_variance_factor((h, w), r, c, zscores[keep], reach=config.local_calibration,
                                      noise_share=shares[keep])
        var *= local if same_grid else resize_map(local, out_shape)
    t2 = time.perf_counter()

    fitted = config.replace(lengthscale=fit.lengthscale, outputscale=fit.outputscale, nugget=fit.nugget)
    name = f"frame {frame}: " if frame is not None else ""
    messages = []
    scale = float(np.exp(fit.log_scale))
    n_kept = int(np.count_nonzero(~rejected))
    if len(z) and not 1.0 / SCALE_WARN_FACTOR <= scale <= SCALE_WARN_FACTOR:
        messages.append(_scale_message(name, scale, float(np.median(base))))
    if n_kept < FEW_POINTS:
        messages.append(
            f"{name}only {n_kept} usable points: the posterior is the MDE with the prior's variance "
            f"(s = {fit.outputscale:.2f} in log depth) away from them"
        )
    elif n_kept:
        from scipy.ndimage import distance_transform_cdt

        seen = np.ones((h, w), dtype=bool)
        seen[r, c] = False
        reach = max(h, w) / COVERAGE_REACH
        far = float(np.mean(distance_transform_cdt(seen, metric="taxicab") > reach))
        if far > COVERAGE_WARN:
            messages.append(
                f"{name}the points cover little of the image: {far:.0%} of it is farther than "
                f"{reach:.0f} px from any point (the variance grows there)"
            )
    if slope is not None and slope.slope < SLOPE_WARN:
        messages.append(
            f"{name}the points follow the MDE's depth differences only weakly (slope {slope.slope:.2f} in log "
            f"depth; 1 = fully): its shape is barely used, check that it is depth (not disparity) of this image"
        )
    if not config.fit and fit.outputscale > OUTPUTSCALE_WARN * config.outputscale:
        messages.append(
            f"{name}the MDE's log-depth error at the points has s = {fit.outputscale:.2f}, above the configured "
            f"{config.outputscale:.2f}: the variance is widened to match (is the MDE out of its range here?)"
        )
    if len(z) and rejected.mean() > REJECTED_WARN:
        messages.append(f"{name}{int(rejected.sum())} of {len(z)} points ({rejected.mean():.0%}) rejected as outliers")
    alignment = AlignmentResult(scale, 0.0, n_kept)
    times = {"fit": t1 - t0, "solve": t2 - t1}
    return mean, var, fit, fitted, rejected, tuple(messages), alignment, times, solution.info, a


def _scale_message(name: str, factor: float, median_mde: float) -> str:
    """The warning for an MDE whose scale disagrees with the points by more than SCALE_WARN_FACTOR."""
    return (
        f"{name}the MDE's scale disagrees with the points by a factor of {factor:.2f} "
        f"(median MDE depth {median_mde:.2f} m): check the MDE's units or model"
    )


def _gaussian_warnings(
    mean: np.ndarray, mde: np.ndarray, valid: np.ndarray, grid_sparse: SparseDepth, frame: str | None
) -> tuple[str, ...]:
    """What a posterior of the Gaussian formulations (``balanced``, ``residual``) cannot support.

    These models are Gaussian in metres (the paper's model is kept as the paper states it), so
    nothing keeps their mean positive: a badly scaled MDE or a far point can put pixels at or
    below 0 m. They are not clipped (the mean stays the model's); the warning counts them. The
    MDE's scale against the points is checked as for the default model (a factor of 2).
    """
    name = f"frame {frame}: " if frame is not None else ""
    messages = []
    rows, cols = grid_sparse.v.astype(np.int64), grid_sparse.u.astype(np.int64)
    seen = valid[rows, cols]
    if seen.any():
        ratio = float(np.median(grid_sparse.depth[seen] / mde[rows[seen], cols[seen]]))
        if not 1.0 / SCALE_WARN_FACTOR <= ratio <= SCALE_WARN_FACTOR:
            messages.append(_scale_message(name, ratio, float(np.median(mde[valid]))))
    low = int(np.count_nonzero(~(mean > 0)))
    if low:
        messages.append(
            f"{name}{low} pixels ({low / mean.size:.1%}) have a posterior mean <= 0 m or not finite (a Gaussian model "
            f"in metres; the default log_residual model keeps depths positive): mask them before use"
        )
    return tuple(messages)


class DepthCompleter:
    """Completes depth frame after frame with one configuration.

    The engine (and the per-resolution set-up it caches: the elimination structure, the prior
    precision and the output read-out of the ``fast`` engine) is kept between calls, so the frames
    of a sequence after the first are cheaper. With ``config.fit`` each frame's hyperparameters
    are fitted by maximum marginal likelihood, warm-started from the previous frame's values
    (`fitted`; set it to None to start again from ``config``). ``engine`` (a
    `gpdepth3d.gp.EngineConfig`) sets the engine's options: device, back-end, route, limits.

    Example:
        >>> completer = DepthCompleter(DepthGPConfig(engine="exact"))
        >>> posterior = completer(mde_depth, sparse)  # doctest: +SKIP
    """

    def __init__(self, config: DepthGPConfig | None = None, *, engine: EngineConfig | None = None):
        if config is not None and not isinstance(config, DepthGPConfig):
            raise InvalidInputError("config", "a DepthGPConfig (or None for the defaults)", describe(config))
        self.config = config or DepthGPConfig()
        self.engine = make_engine(self.config, engine)
        self.fitted: DepthGPConfig | None = None
        self._fit_engine = None
        self._point_fit = None

    def _frame_config(self, mde_depth: np.ndarray, sparse: SparseDepth) -> DepthGPConfig:
        """The configuration of this frame: ``config``, or fitted to the frame when ``config.fit``."""
        if not self.config.fit:
            return self.config
        from ..gp.fast import FastEngine
        from .fit import fit_hyperparameters

        if self._fit_engine is None:
            self._fit_engine = self.engine if isinstance(self.engine, FastEngine) else FastEngine()
        start = (self.fitted or self.config).replace(fit=False)
        fitted = fit_hyperparameters(mde_depth, sparse, start, engine=self._fit_engine)
        self.fitted = fitted
        return fitted.replace(fit=True)

    def complete(
        self,
        mde_depth: np.ndarray,
        sparse: SparseDepth,
        *,
        output_shape: tuple[int, int] | None = None,
        variance: bool = True,
        frame: str | None = None,
    ) -> DepthPosterior:
        """Posterior depth (mean and variance) given an MDE map and sparse measurements.

        Args:
            mde_depth: (H, W) MDE z-depth in metres (0/NaN/inf = none).
            sparse: Range measurements (any resolution of the same image).
            output_shape: (Ho, Wo) of the result; default (H, W).
            variance: Compute the marginal variance (else it is NaN, and faster).
            frame: Name of the frame, used in the posterior's warnings.
        """
        if self.config.formulation == "log_residual":
            return self._complete_log_residual(mde_depth, sparse, output_shape, variance, frame)
        t0 = time.perf_counter()
        config = self._frame_config(mde_depth, sparse)
        tf = time.perf_counter()
        problem, grid_sparse, scale, alignment = build_problem(mde_depth, sparse, config, output_shape)
        t1 = time.perf_counter()
        solution = self.engine.solve(problem, variance=variance)
        mean, var = solution.mean, solution.variance
        t2 = time.perf_counter()
        if var is None:
            var = np.full(mean.shape, np.nan)
        mde, valid = check_mde_depth(mde_depth)
        mde_out = self._mde_out(mde, valid, problem.out_shape)
        messages = _gaussian_warnings(mean, mde, valid, grid_sparse, frame)
        for message in messages:
            warnings.warn(message, PosteriorWarning, stacklevel=2)
        return DepthPosterior(
            mean=mean,
            variance=var,
            mde=mde_out,
            sparse=grid_sparse,
            config=config,
            depth_scale=scale,
            alignment=alignment,
            timings={"fit": tf - t0, "setup": t1 - tf, "solve": t2 - t1},
            warnings=messages,
            solve=solution.info,
        )

    def _complete_log_residual(self, mde_depth, sparse, output_shape, variance, frame) -> DepthPosterior:
        t0 = time.perf_counter()
        mde, valid, grid_sparse, out_shape = _frame_inputs(mde_depth, sparse, output_shape)
        t1 = time.perf_counter()
        mean, var, fit, fitted, rejected, messages, alignment, times, info, slope = _log_residual_posterior(
            self.engine,
            mde,
            valid,
            grid_sparse,
            out_shape,
            self.config,
            variance=variance,
            frame=frame,
            previous=self._point_fit if self.fitted is not None else None,
        )
        for message in messages:
            warnings.warn(message, PosteriorWarning, stacklevel=3)
        self.fitted, self._point_fit = fitted, fit
        return DepthPosterior(
            mean=mean,
            variance=var,
            mde=self._mde_out(mde, valid, out_shape),
            sparse=grid_sparse,
            config=fitted,
            depth_scale=float(np.median(mde[valid])) if valid.any() else float(np.median(grid_sparse.depth)),
            alignment=alignment,
            timings={"setup": t1 - t0, **times},
            rejected=rejected,
            warnings=messages,
            solve=info,
            mde_slope=slope,
        )

    @staticmethod
    def _mde_out(mde: np.ndarray, valid: np.ndarray, out_shape: tuple[int, int]) -> np.ndarray:
        """The input MDE on the output grid (0 where it had no value)."""
        mde_out = resize_map(mde, out_shape)
        if tuple(out_shape) != mde.shape:
            mde_out = np.where(resize_map(valid.astype(np.float64), out_shape) > 0.999, mde_out, 0.0)
        return mde_out

    __call__ = complete


def complete(
    mde_depth: np.ndarray,
    sparse: SparseDepth,
    *,
    config: DepthGPConfig | None = None,
    output_shape: tuple[int, int] | None = None,
    variance: bool = True,
    frame: str | None = None,
) -> DepthPosterior:
    """Completes one frame: dense posterior depth and variance from an MDE map and sparse depth.

    See `DepthCompleter.complete` for the arguments; the module docstring states the input rules.
    """
    return DepthCompleter(config).complete(
        mde_depth, sparse, output_shape=output_shape, variance=variance, frame=frame
    )
