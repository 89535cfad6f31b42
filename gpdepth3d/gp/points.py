"""The points' leave-one-out z-scores and the outlier screen of the default model (docs/model.md, "screen").

* `loo_zscores`: each point's log residual predicted by simple kriging from its nearest neighbours and
  divided by the predictive standard deviation (close to the full GP's leave-one-out under the
  exponential kernel's screening effect, at a cost linear in the points).
* `screen_points`: fit the scales (`gpdepth3d.gp.fit`) and reject the points whose z-score exceeds a
  threshold, until the rejected set stops changing.

Coordinates are GP-grid pixels, residuals log depth.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numba
import numpy as np

from ..errors import InvalidInputError
from .fit import PointFit, fit_log_residual, raised_outputscale
from .model import ScreenConfig, separable_correlation

if TYPE_CHECKING:
    from ._loo import NeighbourImage, SharedSearch


def loo_zscores(
    rows: np.ndarray,
    cols: np.ndarray,
    resid: np.ndarray,
    noise: np.ndarray,
    fit: PointFit,
    *,
    nu: float = 0.5,
    neighbours: int = 12,
    exclude: np.ndarray | None = None,
    only: np.ndarray | None = None,
    radius: bool = False,
    stated: np.ndarray | None = None,
    image: NeighbourImage | None = None,
    found: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray | tuple[np.ndarray, ...]:
    """Leave-one-out z-scores of the points, each predicted from its nearest neighbours.

    Point i is predicted by simple kriging (mean b) from its ``neighbours`` nearest points (L1
    pixel distance; ties by a deterministic rule with no preferred direction, `neighbours_of`) that are not excluded; z_i =
    (r_i - prediction) / predictive sd, where the predictive variance includes the nugget and
    point i's own noise. With the exponential kernel's screening effect the nearest neighbours
    carry almost all of the weight, so this is close to the exact leave-one-out of the full GP
    at a cost linear in N. The neighbours come from a ring search over a bucket image of the
    points (`neighbours_of`), the kriging from compiled loops (`gpdepth3d.gp._loo`, one k x k
    Cholesky per point; a neighbourhood whose matrix is not numerically positive definite is
    solved by least squares instead).

    Args:
        rows, cols, resid, noise: (N,) as in `fit_log_residual`.
        fit: The fitted hyperparameters.
        nu: Matern smoothness.
        neighbours: Neighbours per point.
        exclude: (N,) bool, points not to use as neighbours (their own z is still computed).
        only: Indices of the points whose z-score to compute (default all; the others get 0).
        radius: Also return each computed point's L1 distance to its farthest neighbour used.
        stated: (N,) the part of ``noise`` that the points' own sigmas state (0 where the model's
            default noise stands in): with it, also return each point's noise share, the part of its
            predictive variance that this noise makes (its own and its neighbours' through the
            kriging weights), in [0, 1]. With independent errors E[z^2] is at least the share
            whatever the field.
        image: The points' `gpdepth3d.gp._loo.NeighbourImage` (`neighbour_image`, points on integer pixels), for
            calls repeated on the same points (the outlier screen's rounds); None: built here when it is used.
        found: The targets' neighbours and their distances as `neighbours_of` gives them (these exclusions and
            ``neighbours``), found before (`start_screen_search`); None: searched here.

    Returns:
        (N,) z-scores (0 where no neighbour is available or not computed); with ``radius``,
        also the (N,) neighbourhood radii (inf where not computed); with ``stated``, last, the (N,)
        noise shares (0 where not computed).
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    r = np.asarray(resid, dtype=np.float64) - fit.log_scale
    noise = np.asarray(noise, dtype=np.float64)
    n = r.size
    usable = np.ones(n, dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    pool = int(np.count_nonzero(usable))
    k = min(int(neighbours), pool - 1 if pool else 0)
    targets = np.arange(n) if only is None else np.asarray(only, dtype=np.int64)
    if n == 0 or k < 1 or targets.size == 0:
        extras = ((np.full(n, np.inf),) if radius else ()) + ((np.zeros(n),) if stated is not None else ())
        return (np.zeros(n), *extras) if extras else np.zeros(n)
    nn, dist = neighbours_of(rows, cols, usable, targets, k, image) if found is None else found
    from ._loo import image_spans, loo_predict
    from .multifrontal import numeric_section

    stated_part = np.zeros(n) if stated is None else np.asarray(stated, dtype=np.float64)
    with numeric_section():
        z, share = loo_predict(
            rows,
            cols,
            r,
            noise,
            targets,
            nn,
            outputscale=fit.outputscale,
            nugget=fit.nugget,
            lengthscale=fit.lengthscale,
            nu=nu,
            stated=stated_part,
            spans=None if image is None else image_spans(image),
        )
    bad = ~np.isfinite(z)
    if np.any(bad):  # a neighbourhood whose matrix is not numerically positive definite
        z[bad], share[bad] = _loo_lstsq(rows, cols, r, noise, stated_part, targets[bad], nn[bad], fit, nu)
    if only is None:  # every point computed: the kernels' arrays are the results
        out, reach, shares = z, dist[:, -1].copy(), share
    else:
        out, reach, shares = np.zeros(n), np.full(n, np.inf), np.zeros(n)
        out[targets], reach[targets], shares[targets] = z, dist[:, -1], share
    extras = ((reach,) if radius else ()) + ((shares,) if stated is not None else ())
    return (out, *extras) if extras else out


#: Image searches (`neighbours_of`, `_distance_to`) cover the box around the points; they are used
#: for points on integer pixels whose box has at most this many cells per point (plus 2**20).
GRID_CELLS_PER_POINT = 64


def _on_pixel_grid(rows: np.ndarray, cols: np.ndarray) -> bool:
    """True when the points lie on integer pixels in a box small enough for an image search."""
    if rows.size == 0 or not (np.all(rows == np.rint(rows)) and np.all(cols == np.rint(cols))):
        return False
    cells = (float(np.ptp(rows)) + 1.0) * (float(np.ptp(cols)) + 1.0)
    return cells <= GRID_CELLS_PER_POINT * rows.size + 2**20


def neighbours_of(
    rows: np.ndarray,
    cols: np.ndarray,
    usable: np.ndarray,
    targets: np.ndarray,
    k: int,
    image: NeighbourImage | None = None,
):
    """The k nearest usable points of each target in L1 distance, with a deterministic tie rule.

    Points on integer pixels (the GP grid's): `gpdepth3d.gp._loo.grid_neighbours`, ties at equal
    distance by the position on the ring of that radius from a starting pixel that a hash of the
    target fixes (no preferred direction; a function of the pixels alone, so screening rounds that
    recompute only some points agree with a full recompute). Other points (or points spread
    over a box of more than ``GRID_CELLS_PER_POINT`` cells per point): a k-d tree, ties by index.

    Args:
        rows, cols: (N,) pixel coordinates of all points.
        usable: (N,) bool, the points that may be neighbours.
        targets: (T,) indices of the points whose neighbours to find (never their own neighbour).
        k: Neighbours per target, 1 <= k <= the usable points other than any target.
        image: The points' `NeighbourImage` (they lie on integer pixels: the image search is used), for searches
            repeated on the same points; None: one is built when the image search is used.

    Returns:
        (nn (T, k) int64, dist (T, k) float64): each row's neighbours in tie order, their distances.
    """
    from ._loo import grid_neighbours

    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.int64)
    if image is not None or _on_pixel_grid(rows, cols):
        return grid_neighbours(rows, cols, usable, targets, k, image)
    from scipy.spatial import cKDTree

    pool = np.flatnonzero(usable)
    xy = np.column_stack([rows, cols])
    tree = cKDTree(xy[pool])
    far, _ = tree.query(xy[targets], k=k + 1, p=1)  # the k nearest others lie within the (k + 1)-th distance
    near = tree.query_ball_point(xy[targets], r=far[:, -1] * (1 + 1e-9) + 1e-9, p=1)
    nn = np.empty((targets.size, k), dtype=np.int64)
    dist = np.empty((targets.size, k))
    for q, (i, cand) in enumerate(zip(targets, near)):
        cand = pool[np.asarray(cand, dtype=np.int64)]
        cand = cand[cand != i]
        d = np.abs(rows[cand] - rows[i]) + np.abs(cols[cand] - cols[i])
        pick = np.lexsort((cand, d))[:k]
        nn[q], dist[q] = cand[pick], d[pick]
    return nn, dist


def _loo_lstsq(rows, cols, r, noise, stated, targets, nn, fit: PointFit, nu: float) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out z-scores and shares of the ``stated`` noise of ``targets`` from their neighbours ``nn`` by least
    squares (NumPy)."""
    s2, tau2 = fit.outputscale**2, fit.nugget**2
    R, C = rows[nn], cols[nn]
    K = s2 * separable_correlation(R[:, :, None] - R[:, None, :], C[:, :, None] - C[:, None, :], fit.lengthscale, nu)
    diag = np.arange(nn.shape[1])
    K[:, diag, diag] += tau2 + noise[nn]
    kx = s2 * separable_correlation(rows[targets][:, None] - R, cols[targets][:, None] - C, fit.lengthscale, nu)
    w = np.stack([np.linalg.lstsq(Ki, ki, rcond=None)[0] for Ki, ki in zip(K, kx)])
    pred = np.sum(w * r[nn], axis=1)
    var = np.maximum(s2 + tau2 + noise[targets] - np.sum(w * kx, axis=1), 1e-30)
    spread = stated[targets] + np.sum(w * w * stated[nn], axis=1)
    return (r[targets] - pred) / np.sqrt(var), np.minimum(spread / var, 1.0)


#: `_distance_to` transforms the box around the points when it has at most this many cells per point.
DISTANCE_CELLS_PER_POINT = 48

#: `_distance_to` compares every point with every source when there are at most this many pairs (few points in
#: a large box: cheaper than building a k-d tree).
DISTANCE_PAIRS = 1 << 14


def _distance_to(
    rows: np.ndarray, cols: np.ndarray, sources: np.ndarray, reach: np.ndarray, image: NeighbourImage | None = None
) -> np.ndarray:
    """(N,) L1 distance of every point to the nearest of the points ``sources`` (beyond max(reach): that or inf).

    Points on integer pixels in a box of at most ``DISTANCE_CELLS_PER_POINT`` cells per point: an exact
    city-block distance transform of the box around them (`gpdepth3d.gp.distance`, O(box)); at most
    ``DISTANCE_PAIRS`` point-source pairs: every pair (O(N sources)); else a k-d tree of the sources
    (O(N log sources)). All are exact (the same |dr| + |dc| in floating point).
    ``image``: the points' `NeighbourImage` when they have one (its cells are the box's pixels).
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    if sources.size == 0:
        return np.full(rows.size, np.inf)
    if image is not None and DISTANCE_CELLS_PER_POINT * rows.size >= image.start.size - 1:
        from .distance import taxicab_transform

        box = ((image.start.size - 1) // image.width, image.width)
        return taxicab_transform(box, image.r[sources], image.c[sources])[image.r, image.c].astype(np.float64)
    if rows.size * sources.size <= DISTANCE_PAIRS:
        return np.min(np.abs(rows[:, None] - rows[sources]) + np.abs(cols[:, None] - cols[sources]), axis=1)
    box = (float(np.ptp(rows)) + 1.0) * (float(np.ptp(cols)) + 1.0)
    if _on_pixel_grid(rows, cols) and DISTANCE_CELLS_PER_POINT * rows.size >= box:
        from .distance import taxicab_transform

        r = (rows - rows.min()).astype(np.int64)
        c = (cols - cols.min()).astype(np.int64)
        return taxicab_transform((int(r.max()) + 1, int(c.max()) + 1), r[sources], c[sources])[r, c].astype(np.float64)
    from scipy.spatial import cKDTree

    bound = float(np.max(reach[np.isfinite(reach)], initial=0.0))
    xy = np.column_stack([rows, cols])
    d, _ = cKDTree(xy[sources]).query(xy, k=1, p=1, distance_upper_bound=bound * (1 + 1e-12) + 1e-12)
    return d


def _image_of(rows: np.ndarray, cols: np.ndarray) -> NeighbourImage | None:
    """The points' `NeighbourImage` when `neighbours_of` searches them by image, else None (a k-d tree is used)."""
    if not _on_pixel_grid(rows, cols):
        return None
    from ._loo import neighbour_image

    return neighbour_image(rows, cols)


def start_screen_search(rows: np.ndarray, cols: np.ndarray, options: ScreenConfig | None = None) -> SharedSearch | None:
    """The first round's neighbour search of `screen_points` on these points, started on a second thread
    (`gpdepth3d.gp._loo.SharedSearch`) so that it runs while the caller fits what the screen needs (the slope).

    Only the positions and the number of neighbours decide that search (every point is usable in the first round).
    None where `screen_points` would not use it (no threshold, points off the pixel grid) or where it does not pay:
    too few points to split between two threads, or numba limited to one thread.

    Args:
        rows, cols: (N,) the points' pixel coordinates, as `screen_points` will get them.
        options: The screen's settings (`ScreenConfig`; None: its defaults).
    """
    from ._loo import CHUNK, SharedSearch

    options = options or ScreenConfig()
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    if options.outlier_threshold is None or rows.size <= CHUNK or numba.get_num_threads() < 2:
        return None
    image = _image_of(rows, cols)
    return None if image is None else SharedSearch(image, min(options.neighbours, rows.size - 1))


def _rounds_image(
    rows: np.ndarray, cols: np.ndarray, threshold: float | None, options: ScreenConfig, search: SharedSearch | None
) -> NeighbourImage | None:
    """The `NeighbourImage` that `screen_points`' rounds share: ``search``'s when one was started (checked to be
    the first round's search of these points), else one built here; None when no round searches (no threshold,
    fewer than 5 points) or the points are off the pixel grid."""
    n = rows.size
    searched = threshold is not None and n >= 5
    if search is not None:
        if search.nn.shape != (n, min(options.neighbours, n - 1)) or not searched:
            raise InvalidInputError("search", f"the first round's search of these {n} points", search.nn.shape)
        return search.image
    return _image_of(rows, cols) if searched else None


class Screen(NamedTuple):
    """The result of `screen_points`."""

    fit: PointFit
    rejected: np.ndarray
    zscores: np.ndarray
    noise_share: np.ndarray


def screen_points(
    rows: np.ndarray,
    cols: np.ndarray,
    resid: np.ndarray,
    noise: np.ndarray,
    *,
    threshold: float | None = 4.0,
    nu: float = 0.5,
    options: ScreenConfig | None = None,
    start: PointFit | None = None,
    around: tuple[float, float] | None = None,
    raise_outputscale: bool = False,
    stated: np.ndarray | None = None,
    search: SharedSearch | None = None,
) -> Screen:
    """Fits the log-residual GP robustly and flags the points that contradict it.

    Up to ``iterations`` times, the hyperparameters are fitted on the kept points and every
    point's leave-one-out z-score is computed from its kept neighbours; points with |z| >
    ``threshold`` are rejected. The loop stops when the rejected set no longer changes. (No
    global screen comes first: a residual far from the frame's median is often a region where
    the MDE is badly wrong, which the points must correct, not an outlier; only disagreement
    with the neighbours marks a point as bad.)

    Args:
        rows, cols, resid, noise: (N,) as in `fit_log_residual`.
        threshold: |z| above which a point is rejected; None keeps every point (one fit).
        nu: Matern smoothness.
        options: Neighbours, rounds, the fit's subset size and search grid (`ScreenConfig`; None: its defaults).
        start: Hyperparameters to use instead of fitting (e.g. fixed ones); rejection still runs.
        around: (l, eta) to start the fits' pattern search from (see `fit_log_residual`).
        raise_outputscale: With ``start``: its s is a floor, not a fixed value. Each round, s is
            the larger of ``start``'s and the marginal-likelihood s of the kept points at
            ``start``'s length scale and nugget ratio (`raised_outputscale`); the first round
            fits on all points, so a frame whose points show a larger spread is not screened
            with an s too small for it, and the outliers it still flags leave the next fit (a
            round refits only while s stays raised: flagged points only widen the spread).
        stated: (N,) the part of ``noise`` that the points' own sigmas state, for the noise shares
            (`loo_zscores`); None: shares of 0.
        search: The first round's neighbour search, started before (`start_screen_search`); None: searched here.

    Returns:
        A `Screen`: the fit without the flagged points, the (N,) bool mask of the flagged points,
        the (N,) final leave-one-out z-scores and noise shares (`loo_zscores`; 0 where not computed).
    """  # fmt: skip
    rows, cols, resid = (np.asarray(a, dtype=np.float64) for a in (rows, cols, resid))  # converted once, not per round
    n = resid.size
    rejected = np.zeros(n, dtype=bool)
    if threshold is not None and (not np.isfinite(threshold) or threshold <= 0):
        raise InvalidInputError("threshold", "a z-score > 0 or None", threshold)
    fit, fitted_on, z, reach, share, changed, k_used = start, None, None, None, None, None, None
    options = options or ScreenConfig()
    image = _rounds_image(rows, cols, threshold, options, search)
    max_points = options.max_points
    for _ in range(options.iterations if threshold is not None else 1):
        keep = ~rejected
        # refit whenever the kept set changed: one gross outlier among hundreds of points is
        # enough to inflate the fitted nugget and scale
        changed_set = fitted_on is None or not np.array_equal(keep, fitted_on)
        # raised s: refitted while it stays raised (the points a round flags only widened the spread: if
        # all of them show no wider error than configured, the kept ones do not either)
        refit = changed_set and (start is None or (raise_outputscale and (fitted_on is None or fit is not start)))
        if refit and start is None:
            fit = fit_log_residual(
                rows[keep], cols[keep], resid[keep], noise[keep], nu=nu, max_points=max_points, around=around,
                lengthscales=options.fit_lengthscales, nuggets=options.fit_nuggets,
            )  # fmt: skip
            fitted_on, around = keep, (fit.lengthscale, fit.eta)
        elif refit:
            raised = raised_outputscale(rows, cols, resid, noise, start, nu=nu, max_points=max_points, use=keep)
            fitted_on, refit = keep, raised is not fit  # s unchanged: only the points near a change are recomputed
            fit = raised
        if threshold is None or n < 5:
            break
        only = None
        k_now = min(options.neighbours, int(np.count_nonzero(keep)) - 1)
        if z is not None and not refit and k_now == k_used:
            # same fit: only points that a newly flagged or cleared point can enter or leave the
            # neighbourhood of (it lies within their neighbourhood radius), and those points, change
            moved = np.flatnonzero(changed)
            only = np.flatnonzero((_distance_to(rows, cols, moved, reach, image) <= reach) | changed)
        k_used = k_now
        z_new, reach_new, share_new = loo_zscores(rows, cols, resid, noise, fit, nu=nu, neighbours=options.neighbours,
                                                  exclude=rejected, only=only, radius=True,
                                                  stated=np.zeros(n) if stated is None else stated, image=image,
                                                  found=search.result() if search is not None and z is None else None)  # fmt: skip
        if only is None:
            z, reach, share = z_new, reach_new, share_new
        else:
            z[only], reach[only], share[only] = z_new[only], reach_new[only], share_new[only]
        new = np.abs(z) > threshold
        changed = new != rejected
        if not changed.any():
            break
        rejected = new
    if z is None or threshold is None:
        z, share = np.zeros(n), np.zeros(n)
    if fit is None:  # pragma: no cover - the loop always runs once
        raise AssertionError("no fit")
    return Screen(fit, rejected, z, share)
