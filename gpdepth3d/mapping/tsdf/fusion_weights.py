"""Per-pixel TSDF fusion weights from the posterior depth variance (`FusionConfig.weighting`).

* ``"uniform"``: ``w = 1`` for every valid pixel (what Open3D's stock integration does).
* ``"variance"``: ``w = 1 / (1 + variance / sigma_ref^2)`` in (0, 1] from the posterior depth
  variance (m^2). A pixel known to ``sigma << sigma_ref`` counts as one full observation, one
  with ``sigma = sigma_ref`` as half, and one with ``sigma >> sigma_ref`` as
  ``(sigma_ref / sigma)^2``: inverse-variance weighting (the optimal weights for averaging
  independent Gaussian readings of the signed distance, Curless and Levoy,
  https://graphics.stanford.edu/papers/volrange/) saturated at one observation, so that
  ``weight_cap`` and ``weight_threshold`` keep their usual meaning ("number of observations").
  With ``relative_sigma_ref`` (the `Mapper`'s default) the reference is that fraction of the pixel's depth.
  Pixels whose sigma exceeds ``max_relative_sigma`` (default 0.2) times their depth, the pixels no
  point informs, get the frame's fallback weight (`FusionConfig.fallback_for`: a frame without
  points falls back to its MDE depth, one with many leaves them out); `TSDFFusion.weights_for`
  then needs the depth map.
"""

from __future__ import annotations

import numpy as np

from ...errors import InvalidInputError, ShapeError, describe


def weights_from_variance(
    variance: np.ndarray,
    *,
    sigma_ref: float,
    depth: np.ndarray | None = None,
    max_relative_sigma: float | None = None,
    relative_sigma_ref: float | None = None,
    fallback_weight: float = 0.0,
) -> np.ndarray:
    """Per-pixel fusion weights in [0, 1]: ``1 / (1 + variance / s^2)``, s = sigma_ref or relative_sigma_ref * depth.

    Pixels less certain than ``max_relative_sigma`` x depth (no point informs them: the MDE alone)
    get ``fallback_weight`` instead (`FusionConfig.max_relative_sigma`, `FusionConfig.fallback_weight`).

    Args:
        variance: (H, W) depth variance, m^2. Non-finite or negative entries get weight 0.
        sigma_ref: Standard deviation (metres) at which the weight is 0.5 (without ``relative_sigma_ref``).
        depth: (H, W) depth, metres; needed with ``max_relative_sigma`` or ``relative_sigma_ref``.
        max_relative_sigma: sigma / depth above which a pixel counts as uninformed (None: none does).
        relative_sigma_ref: sigma / depth at which the weight is 0.5 (None: ``sigma_ref`` in metres).
        fallback_weight: Weight of the uninformed pixels, in [0, 1].

    Returns:
        (H, W) float64 weights.
    """
    var = np.asarray(variance, dtype=np.float64)
    if not np.isfinite(sigma_ref) or sigma_ref <= 0:
        raise InvalidInputError("sigma_ref", "a finite value > 0 (metres)", sigma_ref)
    for name, value in (("max_relative_sigma", max_relative_sigma), ("relative_sigma_ref", relative_sigma_ref)):
        if value is not None and (not np.isfinite(value) or value <= 0):
            raise InvalidInputError(name, "a finite value > 0 (or None)", value)
    if not (np.isfinite(fallback_weight) and 0 <= fallback_weight <= 1):
        raise InvalidInputError("fallback_weight", "a weight in [0, 1]", fallback_weight)
    ok = np.isfinite(var) & (var >= 0)
    var = np.where(ok, var, 0.0)
    if max_relative_sigma is None and relative_sigma_ref is None:
        return np.where(ok, 1.0 / (1.0 + var / sigma_ref**2), 0.0)
    if depth is None:
        raise InvalidInputError("depth", "the (H, W) depth map the variance belongs to (relative sigmas are set)", None)
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != var.shape:
        raise ShapeError("depth", f"the shape of variance {var.shape}", describe(d))
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = np.where(np.isfinite(d) & (d > 0), d * d, np.inf)
        scale2 = sigma_ref**2 if relative_sigma_ref is None else relative_sigma_ref**2 * d2
        w = 1.0 / (1.0 + var / scale2)
        if max_relative_sigma is not None:
            w = np.where(var <= max_relative_sigma**2 * d2, w, fallback_weight)
    return np.where(ok & np.isfinite(w), w, 0.0)
