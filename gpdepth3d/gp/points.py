"""Statistics of the sparse points under the log-residual model: per-frame fit and outlier rejection.

The default model (`DepthGPConfig.formulation == "log_residual"`, see `gpdepth3d.gp.model`) is a
GP on the log ratio of true to MDE depth. Its observations are the measured points only, so its
hyperparameters and its outliers can be judged from the points alone, cheaply:

* `fit_log_residual`: maximum marginal likelihood of (length scale l, nugget share eta, output
  scale s, global log scale b) on a subset of the points. For each (l, eta) on a small grid the
  scale s^2 and the constant b are profiled out in closed form (b by generalised least squares
  with a flat prior, i.e. the REML-style criterion), so a fit costs a few dozen Cholesky
  factorisations of at most ``max_points`` x ``max_points``.
* `loo_zscores`: leave-one-out predictive z-scores of every point given its nearest
  neighbours (local simple kriging with the fitted kernel), vectorised over points.
* `screen_points`: the robust loop that alternates the two: a point whose LOO z-score exceeds
  the threshold contradicts the MDE and its neighbours beyond what the model allows and is
  rejected; the fit is repeated without the rejected points.

Everything works in the GP grid's pixel units and in log-depth (dimensionless) units. This
module needs nothing above `gpdepth3d.errors`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from ..errors import InvalidInputError
from .model import separable_correlation

#: Neighbours of each point in `screen_points`' leave-one-out z-scores.
_NEIGHBOURS = 12
#: Length scales (GP-grid pixels) and nugget shares searched by `fit_log_residual`.
LENGTHSCALES = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)
NUGGETS = (0.01, 0.03, 0.1, 0.3, 1.0)


@dataclass(frozen=True)
class PointFit:
    """Hyperparameters of the log-residual GP fitted to one frame's points.

    Attributes:
        lengthscale: l, GP-grid pixels.
        outputscale: s, standard deviation of the correlated log-ratio field (dimensionless).
        nugget: tau = s * sqrt(eta), standard deviation of the white part of the MDE's log error.
        log_scale: b, the generalised-least-squares constant of the log ratio (exp(b) is the
            global scale that maps the MDE onto the points).
        log_scale_var: Variance of b (flat prior), from the fitted subset.
        n_used: Points the fit used.
    """

    lengthscale: float
    outputscale: float
    nugget: float
    log_scale: float
    log_scale_var: float
    n_used: int

    @property
    def eta(self) -> float:
        """Nugget share (tau / s)^2."""
        return (self.nugget / self.outputscale) ** 2 if self.outputscale > 0 else 0.0


def _profile(resid: np.ndarray, corr: np.ndarray, noise: np.ndarray, eta: float, s2_prev: float):
    """Profiled restricted likelihood for one (l, eta); returns (criterion, s2, b, var_b) or None."""
    n = resid.size
    # noise (measurement variance) is absolute; fold it in relative to the current s^2 estimate
    C = corr.copy()
    C[np.diag_indices(n)] += eta + noise / s2_prev
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return None
    from scipy.linalg import solve_triangular

    a1 = solve_triangular(L, np.ones(n), lower=True, check_finite=False)
    ar = solve_triangular(L, resid, lower=True, check_finite=False)
    q = float(a1 @ a1)
    b = float(a1 @ ar) / q
    a = ar - b * a1
    s2 = max(float(a @ a) / max(n - 1, 1), 1e-12)
    crit = 0.5 * (n - 1) * np.log(s2) + float(np.log(np.diag(L)).sum()) + 0.5 * np.log(q)
    return crit, s2, b, s2 / q


def _fit_subset(rows: np.ndarray, cols: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of a subset for the fit: random seed points, each with its nearest neighbour.

    A purely random subset of dense points (full LiDAR) has no close pairs, so the likelihood
    cannot see the short-range correlation and calls it nugget; pairing every seed with its
    nearest point keeps the points' own spacing in the subset.
    """
    from scipy.spatial import cKDTree

    n = rows.size
    seeds = rng.choice(n, size=size // 2, replace=False)
    xy = np.column_stack([rows, cols])
    _, nn = cKDTree(xy).query(xy[seeds], k=2, p=1)
    pick = np.unique(np.concatenate([seeds, nn[:, 1]]))
    if pick.size < size:  # duplicates: fill up with random other points
        rest = np.setdiff1d(np.arange(n), pick)
        pick = np.union1d(pick, rng.choice(rest, size=min(size - pick.size, rest.size), replace=False))
    return pick


def fit_log_residual(
    rows: np.ndarray,
    cols: np.ndarray,
    resid: np.ndarray,
    noise: np.ndarray,
    *,
    nu: float = 0.5,
    max_points: int = 150,
    lengthscales: tuple[float, ...] = LENGTHSCALES,
    nuggets: tuple[float, ...] = NUGGETS,
    rng: np.random.Generator | None = None,
    around: tuple[float, float] | None = None,
) -> PointFit:
    """Fits (l, s, tau, b) of the log-residual GP to the points by profiled marginal likelihood.

    Args:
        rows, cols: (N,) pixel coordinates of the points on the GP grid.
        resid: (N,) log(measured depth / MDE depth).
        noise: (N,) measurement variance in log units ((sigma / depth)^2).
        nu: Matern smoothness.
        max_points: Fit on a subset of at most this many points (cost max_points^3 per grid
            cell): half random seeds, half their nearest neighbours.
        lengthscales, nuggets: The grid searched (pixels; shares of s^2).
        rng: Generator of the subset (default seeded 0: the same frame gives the same fit).
        around: (l, eta) of a previous fit (the frame before in a sequence): instead of the
            whole grid, a pattern search starts at the grid cell nearest to it and moves to the
            best neighbouring cell until none is better (a few cells instead of all).

    Returns:
        The fit. With fewer than 3 points the length scale and nugget are the grid's middle
        values, s the spread of the residuals (at least 0.1) and b their median.
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    resid = np.asarray(resid, dtype=np.float64)
    noise = np.asarray(noise, dtype=np.float64)
    n = resid.size
    if not (rows.shape == cols.shape == resid.shape == noise.shape) or resid.ndim != 1:
        raise InvalidInputError("rows, cols, resid, noise", "four (N,) arrays", (rows.shape, cols.shape, resid.shape, noise.shape))
    if n < 3:
        b = float(np.median(resid)) if n else 0.0
        s = max(float(np.std(resid)) if n > 1 else 0.0, 0.1)
        return PointFit(lengthscales[len(lengthscales) // 2], s, s * np.sqrt(nuggets[0]), b, s * s, n)
    if n > max_points:
        pick = _fit_subset(rows, cols, max_points, rng if rng is not None else np.random.default_rng(0))
        rows, cols, resid, noise = rows[pick], cols[pick], resid[pick], noise[pick]
        n = pick.size
    spread = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    s2_guess = max(spread * spread, float(np.median(noise)), 1e-6)
    corr_cache: dict[int, np.ndarray] = {}
    scores: dict[tuple[int, int], tuple | None] = {}

    def score(i: int, j: int):
        if (i, j) not in scores:
            if i not in corr_cache:
                corr_cache[i] = separable_correlation(
                    np.subtract.outer(rows, rows), np.subtract.outer(cols, cols), lengthscales[i], nu
                )
            scores[(i, j)] = _profile(resid, corr_cache[i], noise, nuggets[j], s2_guess)
        return scores[(i, j)]

    if around is None:
        cells = [(i, j) for i in range(len(lengthscales)) for j in range(len(nuggets))]
        for cell in cells:
            score(*cell)
    else:  # pattern search from the previous fit
        i = int(np.argmin(np.abs(np.log(np.asarray(lengthscales) / max(around[0], 1e-9)))))
        j = int(np.argmin(np.abs(np.log(np.asarray(nuggets) / max(around[1], 1e-9)))))
        while True:
            here = score(i, j)
            moves = [
                (a, b)
                for a in (i - 1, i, i + 1)
                for b in (j - 1, j, j + 1)
                if 0 <= a < len(lengthscales) and 0 <= b < len(nuggets) and (a, b) != (i, j)
            ]
            cand = [(score(a, b), (a, b)) for a, b in moves]
            cand = [(c[0], ab) for c, ab in cand if c is not None]
            if not cand or (here is not None and min(cand)[0] >= here[0]):
                break
            i, j = min(cand)[1]
    valid = [(out[0], lengthscales[i], nuggets[j], *out[1:]) for (i, j), out in scores.items() if out is not None]
    best = min(valid) if valid else None
    if best is None:  # every cell failed (duplicate points with no noise): fall back to a white model
        b = float(np.median(resid))
        return PointFit(lengthscales[0], np.sqrt(s2_guess), np.sqrt(s2_guess), b, s2_guess / n, n)
    _, lengthscale, eta, s2, b, var_b = best
    return PointFit(float(lengthscale), float(np.sqrt(s2)), float(np.sqrt(s2 * eta)), b, float(var_b), n)


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
    out, reach, shares = np.zeros(n), np.full(n, np.inf), np.zeros(n)
    extras = ((reach,) if radius else ()) + ((shares,) if stated is not None else ())  # filled in place below
    if n == 0 or k < 1 or targets.size == 0:
        return (out, *extras) if extras else out
    nn, dist = neighbours_of(rows, cols, usable, targets, k)
    from ._loo import loo_predict
    from .multifrontal import numeric_section

    stated_part = np.zeros(n) if stated is None else np.asarray(stated, dtype=np.float64)
    with numeric_section():
        z, share = loo_predict(rows, cols, r, noise, targets, nn, outputscale=fit.outputscale, nugget=fit.nugget,
                               lengthscale=fit.lengthscale, nu=nu, stated=stated_part)
    bad = ~np.isfinite(z)
    if np.any(bad):  # a neighbourhood whose matrix is not numerically positive definite
        z[bad], share[bad] = _loo_lstsq(rows, cols, r, noise, stated_part, targets[bad], nn[bad], fit, nu)
    out[targets] = z
    reach[targets] = dist[:, -1]
    shares[targets] = share
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


def neighbours_of(rows: np.ndarray, cols: np.ndarray, usable: np.ndarray, targets: np.ndarray, k: int):
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

    Returns:
        (nn (T, k) int64, dist (T, k) float64): each row's neighbours in tie order, their distances.
    """
    from ._loo import grid_neighbours

    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.int64)
    if _on_pixel_grid(rows, cols):
        return grid_neighbours(rows, cols, usable, targets, k)
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


def _distance_to(rows: np.ndarray, cols: np.ndarray, sources: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(N,) L1 distance of every point to the nearest of the points ``sources`` (inf beyond max(reach)).

    Many points on integer pixels: an exact city-block distance transform of the box around them
    (O(box)); few points in a large box, or points off the pixel grid: a k-d tree of the sources
    (O(N log sources)). Both are exact.
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    if sources.size == 0:
        return np.full(rows.size, np.inf)
    box = (float(np.ptp(rows)) + 1.0) * (float(np.ptp(cols)) + 1.0)
    if _on_pixel_grid(rows, cols) and 8 * rows.size >= box:
        from scipy.ndimage import distance_transform_cdt

        r = (rows - rows.min()).astype(np.int64)
        c = (cols - cols.min()).astype(np.int64)
        free = np.ones((int(r.max()) + 1, int(c.max()) + 1), dtype=bool)
        free[r[sources], c[sources]] = False
        return distance_transform_cdt(free, metric="taxicab")[r, c].astype(np.float64)
    from scipy.spatial import cKDTree

    bound = float(np.max(reach[np.isfinite(reach)], initial=0.0))
    xy = np.column_stack([rows, cols])
    d, _ = cKDTree(xy[sources]).query(xy, k=1, p=1, distance_upper_bound=bound * (1 + 1e-12) + 1e-12)
    return d


def raised_outputscale(
    rows: np.ndarray,
    cols: np.ndarray,
    resid: np.ndarray,
    noise: np.ndarray,
    start: PointFit,
    *,
    nu: float = 0.5,
    max_points: int = 150,
) -> PointFit:
    """``start`` with its s raised to what the points show, never lowered.

    s is profiled by marginal likelihood (`fit_log_residual`, on at most ``max_points`` points
    evenly strided in their order) at ``start``'s length scale and nugget ratio
    eta = (tau / s)^2; when that s is larger than ``start``'s, it replaces it (and Var[b] =
    s^2 / N follows); l, tau and b stay ``start``'s. The configured s is then the least
    MDE error a frame is assumed to have: a network badly out of its range (FastDepth in a 20 m
    hall, iBims sample) gets a wider prior instead of a confident wrong mean.

    Args:
        rows, cols, resid, noise: (N,) as in `fit_log_residual`.
        start: The configured (floor) hyperparameters.
        nu: Matern smoothness.
        max_points: Subset size of the fit.
    """
    n = np.asarray(resid).size
    if n < 3:
        return start
    eta = (start.nugget / start.outputscale) ** 2
    # l is not fitted, so no close pairs are needed: an evenly strided subset in the points' order
    # (as gp.slope's), not `fit_log_residual`'s k-d tree pairing (1 vs 7 ms at 12.6k points, one thread)
    take = np.linspace(0, n - 1, min(n, int(max_points))).round().astype(np.int64)
    fitted = fit_log_residual(np.asarray(rows)[take], np.asarray(cols)[take], np.asarray(resid)[take],
                              np.asarray(noise)[take], nu=nu, max_points=take.size,
                              lengthscales=(start.lengthscale,), nuggets=(eta,))
    if fitted.outputscale <= start.outputscale:
        return start
    s = fitted.outputscale
    return replace(start, outputscale=s, log_scale_var=s * s / n)


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
    max_points: int = 150,
    iterations: int = 3,
    start: PointFit | None = None,
    around: tuple[float, float] | None = None,
    raise_outputscale: bool = False,
    stated: np.ndarray | None = None,
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
        max_points: Subset size of each fit.
        iterations: Maximum fit/reject rounds.
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

    Returns:
        A `Screen`: the fit without the flagged points, the (N,) bool mask of the flagged points,
        the (N,) final leave-one-out z-scores and noise shares (`loo_zscores`; 0 where not computed).
    """
    resid = np.asarray(resid, dtype=np.float64)
    n = resid.size
    rejected = np.zeros(n, dtype=bool)
    if threshold is not None and (not np.isfinite(threshold) or threshold <= 0):
        raise InvalidInputError("threshold", "a z-score > 0 or None", threshold)
    fit, fitted_on, z, reach, share, changed = start, None, None, None, None, None
    k_used = None
    for _ in range(max(1, iterations) if threshold is not None else 1):
        keep = ~rejected
        # refit whenever the kept set changed: one gross outlier among hundreds of points is
        # enough to inflate the fitted nugget and scale
        changed_set = fitted_on is None or not np.array_equal(keep, fitted_on)
        # raised s: refitted while it stays raised (the points a round flags only widened the spread: if
        # all of them show no wider error than configured, the kept ones do not either)
        refit = changed_set and (start is None or (raise_outputscale and (fitted_on is None or fit is not start)))
        if refit and start is None:
            fit = fit_log_residual(
                rows[keep], cols[keep], resid[keep], noise[keep], nu=nu, max_points=max_points, around=around
            )
            fitted_on, around = keep, (fit.lengthscale, fit.eta)
        elif refit:
            raised = raised_outputscale(rows[keep], cols[keep], resid[keep], noise[keep], start, nu=nu, max_points=max_points)
            fitted_on, refit = keep, raised is not fit  # s unchanged: only the points near a change are recomputed
            fit = raised
        if threshold is None or n < 5:
            break
        only = None
        k_now = min(_NEIGHBOURS, int(np.count_nonzero(keep)) - 1)
        if z is not None and not refit and k_now == k_used:
            # same fit: only points that a newly flagged or cleared point can enter or leave the
            # neighbourhood of (it lies within their neighbourhood radius), and those points, change
            moved = np.flatnonzero(changed)
            only = np.union1d(np.flatnonzero(_distance_to(rows, cols, moved, reach) <= reach), moved)
        k_used = k_now
        z_new, reach_new, share_new = loo_zscores(rows, cols, resid, noise, fit, nu=nu, neighbours=_NEIGHBOURS,
                                                  exclude=rejected, only=only, radius=True,
                                                  stated=np.zeros(n) if stated is None else stated)
        if only is None:
            z, reach, share = z_new, reach_new, share_new
        else:
            z[only], reach[only], share[only] = z_new[only], reach_new[only], share_new[only]
        new = np.abs(z) > threshold
        changed = new != rejected
        if np.array_equal(new, rejected):
            break
        rejected = new
    if z is None or threshold is None:
        z, share = np.zeros(n), np.zeros(n)
    if fit is None:  # pragma: no cover - the loop always runs once
        raise AssertionError("no fit")
    return Screen(fit, rejected, z, share)
