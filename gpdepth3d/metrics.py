"""Depth-completion metrics (KITTI and NYU conventions) and calibration of the posterior variance.

All metrics are computed over valid ground-truth pixels only: finite and > 0 (and, where a
prediction is not finite or <= 0, that pixel counts with the prediction clamped to
``min_depth`` so a bad prediction is penalised rather than skipped).

Units: RMSE and MAE in millimetres, iRMSE and iMAE in 1/km (KITTI); REL is the mean absolute
relative error; delta_k is the share of pixels with max(pred/gt, gt/pred) < 1.25^k (NYU).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import EmptyInputError, InvalidInputError, ShapeError, describe

METRIC_NAMES = ("rmse", "mae", "irmse", "imae", "rel", "delta1", "delta2", "delta3")


def _prepare(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None, min_depth: float):
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ShapeError("pred", f"the shape of gt {gt.shape}", describe(pred))
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(gt) & (gt > 0)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != gt.shape:
            raise ShapeError("mask", f"the shape of gt {gt.shape}", describe(mask))
        valid &= mask
    if not valid.any():
        raise EmptyInputError("gt", "at least one valid ground-truth pixel (finite, > 0)", "none")
    p = pred[valid]
    p = np.where(np.isfinite(p), np.maximum(p, min_depth), min_depth)
    return p, gt[valid], valid


def depth_metrics(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None, *, min_depth: float = 1e-3
) -> dict[str, float]:
    """RMSE, MAE (mm), iRMSE, iMAE (1/km), REL, delta1..3 of a depth prediction (metres).

    Args:
        pred: Predicted z-depth, metres.
        gt: Ground-truth z-depth, metres; 0/NaN/inf = no ground truth.
        mask: Optional extra boolean mask of pixels to evaluate.
        min_depth: Predictions are clamped to at least this (metres).

    Returns:
        Dict with the keys of `METRIC_NAMES` plus ``n`` (number of pixels evaluated).
    """
    p, g, _ = _prepare(pred, gt, mask, min_depth)
    err = p - g
    ierr = 1.0 / p - 1.0 / g  # 1/m
    ratio = np.maximum(p / g, g / p)
    return {
        "rmse": float(np.sqrt(np.mean(err**2)) * 1000.0),
        "mae": float(np.mean(np.abs(err)) * 1000.0),
        "irmse": float(np.sqrt(np.mean(ierr**2)) * 1000.0),
        "imae": float(np.mean(np.abs(ierr)) * 1000.0),
        "rel": float(np.mean(np.abs(err) / g)),
        "delta1": float(np.mean(ratio < 1.25)),
        "delta2": float(np.mean(ratio < 1.25**2)),
        "delta3": float(np.mean(ratio < 1.25**3)),
        "n": int(g.size),
    }


def calibration_metrics(
    mean: np.ndarray, variance: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None
) -> dict[str, float]:
    """How well the posterior variance describes the actual error.

    Coverage at one level can be right while the error's distribution is far from the
    posterior's: the shape (``median_abs_z``, the three coverages) and the ranking (``ause``) say
    whether the standard deviation is sharp where the errors are small and wide where they are large.

    Returns:
        ``nll``: mean Gaussian negative log-likelihood of gt (nats per pixel, depth in metres);
        ``coverage_1sigma`` / ``coverage_2sigma`` / ``coverage_3sigma``: share of pixels with
        |error| <= 1 / 2 / 3 std (a calibrated model gives about 0.683 / 0.954 / 0.997);
        ``z_rms``: RMS of error / std (1 when calibrated); ``median_abs_z``: median of |error| /
        std (0.674 when calibrated; below: the std is wider than the typical error);
        ``ause``: area under the sparsification error of the RMSE (`sparsification`: the RMSE of
        the pixels left after removing the largest-std share f, minus the same after removing the
        largest errors, both divided by the RMSE of all pixels, integrated over f in [0, 0.99]; 0
        when the std ranks the errors perfectly, dimensionless); ``n``.
    """
    mean = np.asarray(mean, dtype=np.float64)
    variance = np.asarray(variance, dtype=np.float64)
    if variance.shape != mean.shape:
        raise ShapeError("variance", f"the shape of mean {mean.shape}", describe(variance))
    p, g, valid = _prepare(mean, gt, mask, 0.0)
    var = np.maximum(variance[valid], 1e-12)
    if not np.all(np.isfinite(var)):
        raise ShapeError("variance", "finite variances at the evaluated pixels", "NaN or inf")
    err = p - g
    z = np.abs(err) / np.sqrt(var)
    gap = np.subtract(*sparsification(np.abs(err), var))
    return {
        "nll": float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * err**2 / var)),
        "coverage_1sigma": float(np.mean(z <= 1.0)),
        "coverage_2sigma": float(np.mean(z <= 2.0)),
        "coverage_3sigma": float(np.mean(z <= 3.0)),
        "z_rms": float(np.sqrt(np.mean(z**2))),
        "median_abs_z": float(np.median(z)),
        "ause": float(np.sum((gap[1:] + gap[:-1]) * np.diff(SPARSIFICATION_FRACTIONS)) / 2),  # trapezoid rule
        "n": int(g.size),
    }


SPARSIFICATION_FRACTIONS = np.arange(100) / 100.0
"""Shares of the pixels removed along a sparsification curve (0, 0.01, ..., 0.99)."""


def sparsification(abs_error: np.ndarray, uncertainty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sparsification curves of the RMSE: by the uncertainty, and by the error itself (the oracle).

    For each share f of `SPARSIFICATION_FRACTIONS`, the RMSE of the pixels left after removing the
    share f with the largest ``uncertainty`` (ties: the later pixel first), and after removing the
    share f with the largest error; both divided by the RMSE of all pixels (Ilg et al., ECCV 2018).

    Args:
        abs_error: (N,) absolute errors, N >= 1.
        uncertainty: (N,) any quantity that orders the pixels (a std or variance).

    Returns:
        (by_uncertainty, oracle), each (len(SPARSIFICATION_FRACTIONS),); 1 at f = 0, oracle <= by_uncertainty.
    """
    e2 = np.asarray(abs_error, dtype=np.float64).ravel() ** 2
    u = np.asarray(uncertainty, dtype=np.float64).ravel()
    if e2.size == 0 or u.shape != e2.shape:
        raise ShapeError("abs_error, uncertainty", "two arrays of the same length >= 1", f"{e2.shape}, {u.shape}")
    n = e2.size
    keep = np.maximum(
        n - (np.arange(SPARSIFICATION_FRACTIONS.size) * n) // SPARSIFICATION_FRACTIONS.size, 1
    )  # left (exact)
    total = np.sum(e2)
    if total == 0:
        ones = np.ones(SPARSIFICATION_FRACTIONS.size)
        return ones, ones

    def curve(order):  # order: most trusted first
        kept = np.concatenate([[0.0], np.cumsum(e2[order])])[keep]
        return np.sqrt(kept / keep) / np.sqrt(total / n)

    return curve(np.argsort(u, kind="stable")), curve(np.argsort(e2, kind="stable"))


def mesh_metrics(
    mesh: Any, reference: Any, *, threshold: float = 0.05, samples: int = 50_000, seed: int = 0
) -> dict[str, float]:
    """Accuracy and completeness of a mesh against a reference mesh (both in metres).

    Both surfaces are sampled uniformly (``samples`` points each, seeded, over their triangles in
    a canonical order, `_canonical_soup`: the same surface gives the same samples whatever the
    order of its vertices and faces, so the scores repeat exactly). Accuracy is the mean
    distance from the mesh's samples to the nearest reference sample, completeness the mean
    distance the other way; Chamfer is their mean; precision / recall are the fractions of
    samples within ``threshold`` metres of the other surface; F-score their harmonic mean.

    Returns:
        ``accuracy``, ``completeness``, ``chamfer`` (metres), ``precision``, ``recall``,
        ``fscore`` (0..1), and ``threshold``.
    """
    import trimesh
    from scipy.spatial import cKDTree

    for name, m in (("mesh", mesh), ("reference", reference)):
        if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
            raise EmptyInputError(name, "a trimesh.Trimesh with faces", type(m).__name__)
    if not threshold > 0:
        raise InvalidInputError("threshold", "a distance > 0 (metres)", threshold)
    a, _ = trimesh.sample.sample_surface(_canonical_soup(mesh), samples, seed=seed)
    b, _ = trimesh.sample.sample_surface(_canonical_soup(reference), samples, seed=seed + 1)
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    precision = float(np.mean(d_ab < threshold))
    recall = float(np.mean(d_ba < threshold))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "accuracy": float(d_ab.mean()),
        "completeness": float(d_ba.mean()),
        "chamfer": float((d_ab.mean() + d_ba.mean()) / 2),
        "precision": precision,
        "recall": recall,
        "fscore": float(fscore),
        "threshold": float(threshold),
    }


def _canonical_soup(mesh: Any) -> Any:
    """The triangles of a `trimesh.Trimesh` as a soup in a canonical order: each triangle starts at
    its lexicographically smallest corner (winding kept), triangles sorted by their corners."""
    import trimesh

    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces, dtype=np.int64)] + 0.0  # (m, 3, 3)
    m = tri.shape[0]
    corners = tri.reshape(-1, 3)
    rank = np.empty(3 * m, np.int64)
    rank[np.lexsort(corners.T[::-1])] = np.arange(3 * m)
    first = np.argmin(rank.reshape(m, 3), axis=1)
    tri = tri[np.arange(m)[:, None], (first[:, None] + np.arange(3)[None]) % 3]
    tri = tri[np.lexsort(tri.reshape(m, 9).T[::-1])]
    return trimesh.Trimesh(tri.reshape(-1, 3), np.arange(3 * m).reshape(m, 3), process=False)
