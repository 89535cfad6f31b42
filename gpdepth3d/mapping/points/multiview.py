"""Multi-view triangulation of feature tracks: inverse depth along the reference ray, robust Gauss-Newton, honest sigma.

See `triangulate_tracks`; the held-pose path (the default) runs compiled per-track loops (numba), the
bundle adjustment (``refine_poses``, the default) a Levenberg-Marquardt on the Schur complement of the depths.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba as nb
import numpy as np
from scipy import sparse

from ...camera import PinholeCamera, check_pose
from ...completion.threads import single_threaded_blas
from ...errors import InvalidInputError, ShapeError, describe
from ...measurements import SparseDepth
from .triangulation_config import TriangulationConfig


# ---------------------------------------------------------------------- multi-view tracks
@dataclass(frozen=True)
class MultiViewPoints:
    """Points triangulated from tracks over several views by `triangulate_tracks`.

    Attributes:
        index: (N,) int64 row of each point in the tracks given.
        uv: (N, 2) pixel positions in the reference view.
        depth: (N,) z-depth in the reference camera, metres.
        sigma: (N,) standard deviation of that depth, metres: pixel noise (scaled by the
            residuals actually seen) and pose uncertainty propagated through the refinement,
            plus the relative floor ``depth_sigma_floor``.
        points_world: (N, 3) positions in the world frame (the reference pose as given), metres.
        n_views: (N,) views that support the point, the reference included (>= 2).
        reprojection_error: (N,) RMS reprojection error over the supporting views, pixels.
        parallax_deg: (N,) largest angle between the reference ray and another view's ray, degrees.
        poses: (V, 4, 4) ``T_world_camera`` of every view after refinement (the reference is
            kept as given; views without enough tracks keep their given pose).
        pixel_sigma: Reprojection noise estimated from the residuals (pixels, >= the configured
            ``pixel_sigma``); used in ``sigma``.
        agreeing: Tracks the poses agree with: in front of their views and seen within
            ``max_reprojection_error`` in ``min_views`` of them, whether or not they pass the parallax,
            depth and sigma checks (a pose that does not belong to its image leaves few).
        pose_displacement: Median distance, pixels, between where the neighbours see the triangulated
            tracks and where the poses as given put them, beyond what ``pixel_sigma`` keypoint noise gives
            (subtracted in quadrature; 0 without any): how far the relative poses' error moves a point
            carried from one of these frames into another across the image (the refinement of poorer poses
            takes that error out of the frame's own points, not out of points carried between frames).
    """

    index: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    sigma: np.ndarray
    points_world: np.ndarray
    n_views: np.ndarray
    reprojection_error: np.ndarray
    parallax_deg: np.ndarray
    poses: np.ndarray
    pixel_sigma: float
    agreeing: int = 0
    pose_displacement: float = 0.0

    def __len__(self) -> int:
        return int(self.depth.shape[0])

    def to_sparse(self, image_size: tuple[int, int]) -> SparseDepth:
        """The points as `SparseDepth` of the reference image with their sigma."""
        return SparseDepth.from_arrays(self.uv[:, 0], self.uv[:, 1], self.depth, image_size, self.sigma)


def _skew(a: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(a.shape[:-1])
    return np.stack(
        [
            np.stack([z, -a[..., 2], a[..., 1]], -1),
            np.stack([a[..., 2], z, -a[..., 0]], -1),
            np.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    W = _skew(w)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    return np.eye(3) + a * W + b * (W @ W)


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) left Jacobians of SO(3): exp(w + d) ~ exp(J_l(w) d) exp(w)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    W = _skew(w)
    small = theta < 1e-5
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0, (th - np.sin(th)) / th**3)
    return np.eye(3) + a * W + b * (W @ W)


class _Problem:
    """Inverse-depth bundle adjustment of one reference view against its neighbours.

    Unknowns x = (rho, xi): the inverse depth rho_i of every track along its reference ray (the
    reference keypoint is taken as exact) and a 6-D correction xi_j = (w_j, d_j) of every
    neighbour's pose relative to the reference, R_j = exp(w_j) R0_j, t_j = t0_j + d_j, with a
    Gaussian prior xi_j ~ N(0, diag(1 / prior)) around the given pose.
    A point in neighbour j: p = R_j xbar_i + rho_i t_j (homogeneous), pixel = pi(K p).
    """

    def __init__(self, xbar, uv, mask, R0, t0, camera, pixel_sigma, rot_sigma, trans_sigma):
        self.xbar = xbar  # (N, 3) normalised reference rays (z = 1)
        self.uv = uv  # (N, J, 2) observations in the neighbours
        self.mask = mask  # (N, J) observed
        self.R0, self.t0 = R0, t0  # (J, 3, 3), (J, 3): given reference -> neighbour transforms
        self.R, self.t = R0.copy(), t0.copy()
        self.xi = np.zeros((R0.shape[0], 6))  # pose corrections behind R, t
        self.f = np.array([camera.fx, camera.fy])
        self.c = np.array([camera.cx, camera.cy])
        self.pixel_sigma = float(pixel_sigma)
        self.prior = np.r_[np.full(3, 1.0 / rot_sigma**2), np.full(3, 1.0 / trans_sigma**2)]

    def rotated_rays(self, R=None):
        """(N, J, 3) reference rays rotated into every neighbour (cached for the current R)."""
        R = self.R if R is None else R
        cached = getattr(self, "_rx", None)
        if cached is not None and cached[0] is R:
            return cached[1]
        Rx = np.matmul(self.xbar[None], np.swapaxes(R, 1, 2)).transpose(1, 0, 2)  # einsum("jab,nb->nja")
        self._rx = (R, Rx)
        return Rx

    def project(self, rho, R=None, t=None):
        R = self.R if R is None else R
        t = self.t if t is None else t
        p = self.rotated_rays(R) + rho[:, None, None] * t[None]
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = p[..., :2] / z[..., None] * self.f + self.c
        return p, z, uv

    def residuals(self, rho, R=None, t=None):
        p, z, uv = self.project(rho, R, t)
        r = (uv - self.uv) / self.pixel_sigma
        valid = self.mask & (z > 1e-9) & np.all(np.isfinite(r), axis=-1)
        return p, z, np.where(valid[..., None], r, 0.0), valid

    # ---- the problem as one stacked least-squares system, x = (rho (N), xi (J * 6)): the reference the
    # normal equations (`_normal_equations`) are checked against
    @property
    def n_data(self) -> int:
        """Reprojection residuals (2 per observation in ``mask``); the 6 J prior residuals follow them."""
        return 2 * int(np.count_nonzero(self.mask))

    def pack(self, rho: np.ndarray) -> np.ndarray:
        return np.concatenate([rho, self.xi.reshape(-1)])

    def unpack(self, x: np.ndarray) -> np.ndarray:
        """Sets the poses from x's corrections; returns its inverse depths."""
        n = self.xbar.shape[0]
        xi = x[n:].reshape(-1, 6)
        if not np.array_equal(xi, self.xi):
            self.xi = xi.copy()
            self.R = _rodrigues(xi[:, :3]) @ self.R0
            self.t = self.t0 + xi[:, 3:]
        return x[:n]

    def stacked_residuals(self, x: np.ndarray) -> np.ndarray:
        """(n_data + 6 J,) residuals: the observations' reprojection errors / pixel_sigma, then xi / prior sigma.

        One (u, v) pair for every observation in ``mask``, in its row-major order; 0 where not valid.
        """
        rho = self.unpack(x)
        r = self.residuals(rho)[2]
        return np.concatenate([r[self.mask].reshape(-1), (self.xi * np.sqrt(self.prior)).reshape(-1)])

    def derivatives(self, rho):
        """Residuals and their derivatives at the current poses, zero where not valid.

        Returns:
            r (N, J, 2), valid (N, J), d r / d rho_i (N, J, 2), d r / d xi_j (N, J, 2, 6).
        """
        p, z, r, valid = self.residuals(rho)
        fz = self.f / self.pixel_sigma
        iz = np.where(valid, 1.0 / np.where(valid, z, 1.0), 0.0)
        # d(residual)/dp: (N, J, 2, 3)
        Jp = np.zeros(p.shape[:2] + (2, 3))
        Jp[..., 0, 0] = fz[0] * iz
        Jp[..., 1, 1] = fz[1] * iz
        Jp[..., 0, 2] = -fz[0] * p[..., 0] * iz**2
        Jp[..., 1, 2] = -fz[1] * p[..., 1] * iz**2
        J_rho = np.matmul(Jp, self.t[None, :, :, None])[..., 0]
        # d(exp(w) R0 xbar)/dw = -[R xbar]_x J_l(w)
        J_w = -np.matmul(np.matmul(Jp, _skew(self.rotated_rays())), _left_jacobian(self.xi[:, :3])[None])
        J_d = Jp * rho[:, None, None, None]
        return r, valid, J_rho, np.concatenate([J_w, J_d], axis=-1)

    def jacobian(self, x: np.ndarray) -> sparse.csr_array:
        """(n_data + 6 J, N + 6 J) sparse Jacobian of `stacked_residuals`: 7 entries a reprojection row, 1 a prior row."""
        rho = self.unpack(x)
        n, nj = self.mask.shape
        _, _, J_rho, J_xi = self.derivatives(rho)
        track, view = np.nonzero(self.mask)
        cols = np.empty((track.size, 2, 7), np.int64)
        cols[..., 0] = track[:, None]
        cols[..., 1:] = n + 6 * view[:, None, None] + np.arange(6)
        blocks = np.concatenate([J_rho[..., None], J_xi], axis=-1)[self.mask]  # (K, 2, 7)
        data = np.concatenate([blocks.reshape(-1), np.tile(np.sqrt(self.prior), nj)])
        indices = np.concatenate([cols.reshape(-1), n + np.arange(6 * nj)])
        indptr = np.concatenate([np.arange(0, 7 * self.n_data, 7), 7 * self.n_data + np.arange(6 * nj + 1)])
        return sparse.csr_array((data, indices, indptr), shape=(self.n_data + 6 * nj, n + 6 * nj))


def _normal_equations(prob: _Problem, rho: np.ndarray, w: np.ndarray):
    """Weighted Gauss-Newton normal equations of the inverse depths (diagonal block) and poses (k = 6 a neighbour).

    Args:
        prob: The problem at its current poses.
        rho: (N,) inverse depths.
        w: (N, J) weight of each observation (0: not used).

    Returns:
        h (N,) the depth block's diagonal, g_r (N,) its gradient, B (N, k J) the depth-pose block,
        H_xx (k J, k J) the pose block with the prior, g_x (k J,) its gradient (prior included), and
        the robust cost's data residuals r (N, J, 2) and valid (N, J).
    """
    r, valid, J_rho, J_xi = prob.derivatives(rho)
    prior, k = prob.prior, 6
    n, nj = valid.shape
    w = np.where(valid, w, 0.0)
    wj = w[..., None] * J_rho  # (N, J, 2)
    h = np.einsum("njc,njc->n", wj, J_rho)
    g_r = np.einsum("njc,njc->n", wj, r)
    B = np.einsum("njc,njck->njk", wj, J_xi).reshape(n, k * nj)
    wx = w[..., None, None] * J_xi  # (N, J, 2, k)
    blocks = np.einsum("njck,njcl->jkl", wx, J_xi)
    H_xx = np.zeros((k * nj, k * nj))
    for j in range(nj):
        H_xx[k * j : k * j + k, k * j : k * j + k] = blocks[j] + np.diag(prior)
    g_x = (np.einsum("njck,njc->jk", wx, r) + prob.xi * prior).reshape(-1)
    return h, g_r, B, H_xx, g_x, r, valid


def _robust_cost(prob: _Problem, rho: np.ndarray, scale: float, R=None, t=None, xi=None) -> float:
    """Cauchy cost of the observations in ``mask`` (units of pixel_sigma) plus the Gaussian pose prior."""
    _, _, r, valid = prob.residuals(rho, R, t)
    s = np.where(valid & prob.mask, np.sum(r * r, axis=-1), 0.0)
    xi = prob.xi if xi is None else xi
    return float(scale**2 * np.sum(np.log1p(s / scale**2)) + np.sum(xi * xi * prob.prior))


def _schur_solve(h, g_r, B, H_xx, g_x, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt step (d rho, d xi): the depths eliminated by their Schur complement (6 J unknowns left)."""
    hd = h * (1.0 + damping)
    inv = np.where(hd > 0, 1.0 / np.where(hd > 0, hd, 1.0), 0.0)
    Bi = B * inv[:, None]
    S = H_xx + damping * np.diag(np.diag(H_xx)) - B.T @ Bi
    rhs = -g_x + Bi.T @ g_r
    try:
        dx = np.linalg.solve(S, rhs)
    except np.linalg.LinAlgError:
        dx = np.linalg.lstsq(S, rhs, rcond=None)[0]
    return -(g_r + B @ dx) * inv, dx


_GN_STEPS = 12
"""Most Levenberg-Marquardt steps of one bundle adjustment (`_bundle_adjusted`)."""
_FTOL = 1e-3
"""A bundle adjustment stops when a step lowers the cost by less than this fraction of it."""


def _bundle_adjusted(prob: _Problem, rho: np.ndarray, scale: float) -> np.ndarray:
    """Inverse depths and poses (left in ``prob``) minimising the robust cost at Cauchy ``scale`` (units of pixel_sigma).

    Iteratively reweighted Levenberg-Marquardt: each step weights every observation by its Cauchy
    weight 1 / (1 + |r|^2 / scale^2) and solves the normal equations with the inverse depths
    eliminated (Schur complement: a 6 J system, J neighbours), the bundle adjustment's usual
    structure (Triggs et al., https://doi.org/10.1007/3-540-44480-7_21). A step that does not
    lower the cost is retried with more damping; it stops when a step gains less than `_FTOL`.
    """
    with single_threaded_blas():  # small products: BLAS threads only contend
        return _levenberg_marquardt(prob, rho, scale)


def _levenberg_marquardt(prob: _Problem, rho: np.ndarray, scale: float) -> np.ndarray:
    """`_bundle_adjusted`'s iterations."""
    damping = 1e-3
    cost = _robust_cost(prob, rho, scale)
    for _ in range(_GN_STEPS):
        _, _, r, valid = prob.residuals(rho)
        w = 1.0 / (1.0 + np.sum(r * r, axis=-1) / scale**2)
        h, g_r, B, H_xx, g_x, _, _ = _normal_equations(prob, rho, np.where(prob.mask, w, 0.0))
        improved = False
        for _ in range(4):
            d_rho, dx = _schur_solve(h, g_r, B, H_xx, g_x, damping)
            xi = prob.xi + dx.reshape(-1, 6)
            R, t = _rodrigues(xi[:, :3]) @ prob.R0, prob.t0 + xi[:, 3:]
            rho_new = np.where(rho + d_rho > 0.1 * rho, rho + d_rho, 0.5 * rho)
            new_cost = _robust_cost(prob, rho_new, scale, R, t, xi)
            if new_cost < cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break
        gain = (cost - new_cost) / max(cost, 1e-300)
        prob.xi, prob.R, prob.t = xi, R, t
        rho, cost, damping = rho_new, new_cost, max(damping / 10.0, 1e-7)
        if gain < _FTOL:
            break
    return rho


def _refined_depths(prob, rho, mask, xbar, obs, config: TriangulationConfig):
    """Robust refinement of the inverse depths: (rho, residuals, valid observations).

    A wide Cauchy scale first (the given poses can be several pixels off), then the final one;
    observations beyond ``max_reprojection_error`` are then dropped and the problem solved again.
    """
    final_scale = 2.0
    if config.refine_poses:
        for scale in (8.0, final_scale):
            rho = _bundle_adjusted(prob, rho, scale)
        _, _, r, valid = prob.residuals(rho)
        err_px = np.linalg.norm(r, axis=-1) * prob.pixel_sigma
        prob.mask = mask & valid & (err_px <= config.max_reprojection_error)
        rho = _bundle_adjusted(prob, rho, final_scale)
        _, _, r, valid = prob.residuals(rho)
        return rho, r, valid
    # poses held: independent 1-D problems, one compiled loop over the tracks
    return _held_pose_depths(
        xbar,
        obs,
        mask,
        prob.R,
        prob.t,
        prob.f,
        prob.c,
        prob.pixel_sigma,
        rho,
        final_scale,
        float(config.max_reprojection_error),
    )


def _pixel_noise(
    r: np.ndarray, valid: np.ndarray, unit: float, n_others: int, config: TriangulationConfig
) -> tuple[float, float]:
    """(noise seen in the residuals, pixel sigma used) in pixels: the Rayleigh median of the 2-D
    residual norms (``r`` in units of ``unit`` pixels), dof-corrected, and at least ``config.pixel_sigma``."""
    n_obs = int(valid.sum())
    n_par = int(valid.any(axis=1).sum()) + 6 * n_others
    if n_obs * 2 > n_par + 2:
        med = np.median(np.linalg.norm(r[valid], axis=-1)) * unit / np.sqrt(2 * np.log(2))
        seen = float(med * np.sqrt(2 * n_obs / (2 * n_obs - n_par)))
    else:
        seen = float(config.pixel_sigma)
    return seen, max(float(config.pixel_sigma), seen)


def _inverse_depth_variance(
    prob, rho, valid, xbar, sigma_px: float, seen: float, config: TriangulationConfig
) -> np.ndarray:
    """(N,) variance of each track's inverse depth: pixel noise and the poses' uncertainty."""
    if config.refine_poses:
        var_rho = _joint_inverse_depth_variance(prob, rho, valid, sigma_px)
    else:
        # poses held at their given values: their whole prior uncertainty reaches the depth
        # through d rho / d xi = -H_rho_rho^-1 H_rho_xi
        var_rho = _held_pose_variance(xbar, rho, valid, prob.R, prob.t, prob.f / sigma_px, 1.0 / prob.prior)
    if config.variance_factor:
        # a posteriori variance factor: residuals larger than the pixel noise say the poses
        # (or the tracks) are worse than assumed, in the directions the images cannot see too
        var_rho = var_rho * max(1.0, seen / float(config.pixel_sigma)) ** 2
    return var_rho


def _joint_inverse_depth_variance(prob: _Problem, rho: np.ndarray, valid: np.ndarray, sigma_px: float) -> np.ndarray:
    """(N,) marginal variance of each inverse depth from the Gauss-Newton information J^T J at the solution.

    Unit weights on the valid observations and ``sigma_px`` pixel noise; the poses are eliminated by
    their Schur complement, so the uncertainty all points share (the prior's) reaches each depth:
    var = 1 / h + b^T S^-1 b / h^2.
    """
    prob.mask, prob.pixel_sigma = valid, sigma_px
    with single_threaded_blas():
        return _schur_variance(prob, rho, valid)


def _schur_variance(prob: _Problem, rho: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`_joint_inverse_depth_variance`'s algebra."""
    h, _, B, H_xx, _, _, _ = _normal_equations(prob, rho, valid.astype(np.float64))
    inv = np.where(h > 0, 1.0 / np.where(h > 0, h, 1.0), 0.0)
    Bi = B * inv[:, None]
    S = H_xx - B.T @ Bi
    try:
        S_inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        S_inv = np.linalg.pinv(S)
    return inv + np.einsum("nk,kl,nl->n", Bi, S_inv, Bi)


def triangulate_tracks(
    tracks: np.ndarray,
    poses: Sequence[np.ndarray] | np.ndarray,
    camera: PinholeCamera,
    *,
    reference: int = 0,
    config: TriangulationConfig | None = None,
    _checked: bool = False,
) -> MultiViewPoints:
    """Triangulates feature tracks from all their views, with the neighbours' poses held or refined.

    Every track starts at a keypoint of the reference view. Steps: (1) a linear multi-view
    triangulation of each track's inverse depth along its reference ray (the multi-view DLT
    in inverse-depth form, iteratively reweighted); (2) a robust (Cauchy) Gauss-Newton of
    each inverse depth with the poses held (the default: independent 1-D problems, compiled
    loops), or with ``refine_poses`` a bundle adjustment of all inverse depths jointly with a
    correction of every neighbour's pose relative to the reference, with a Gaussian prior of
    ``rotation_sigma_deg`` / ``translation_sigma`` around the given relative pose (the
    translations' prior fixes the metric scale), solved by an iteratively reweighted (Cauchy)
    Levenberg-Marquardt with the depths eliminated by their Schur complement (`_bundle_adjusted`);
    (3) observations off by more than ``max_reprojection_error`` pixels are dropped and the
    problem solved again; (4) the depth sigma is the marginal standard deviation of the
    inverse depth from the inverse of the Gauss-Newton information J^T J (poses held: their
    prior uncertainty propagated; refined: the Schur complement of the poses, so pixel noise
    *and* the pose uncertainty that all points share), with the pixel noise taken as the
    larger of ``pixel_sigma`` and the one the residuals show, plus a relative floor
    ``depth_sigma_floor * depth`` in quadrature (keypoint-on-edge and residual model errors;
    calibrated on 7-Scenes).

    Args:
        tracks: (N, V, 2) pixel positions (u, v) of N tracks in V views; NaN where a track is
            not seen. Every track must be seen in the reference view.
        poses: V 4x4 ``T_world_camera`` poses.
        camera: Intrinsics shared by all views.
        reference: Index of the reference view.
        config: Options (pixel_sigma, rotation_sigma_deg, translation_sigma, refine_poses,
            variance_factor, min_views, max_reprojection_error, min_parallax_deg, min_depth,
            max_depth, max_relative_sigma, depth_sigma_floor).

    Returns:
        `MultiViewPoints` of the tracks that pass: seen in >= ``min_views`` views after
        outlier removal, in front of every supporting camera, depth in [min_depth,
        max_depth], parallax >= ``min_parallax_deg``, sigma <= ``max_relative_sigma * depth``.

    Raises:
        ShapeError: tracks not (N, V, 2) or poses not V 4x4 matrices.
        InvalidInputError: reference out of range, a track missing in the reference view.
        CalibrationError: a pose that is not rigid.
    """
    config = config or TriangulationConfig()
    tracks, Ts, ref = _checked_tracks(tracks, poses, reference, _checked)
    others = [k for k in range(tracks.shape[1]) if k != ref]
    mask = np.all(np.isfinite(tracks[:, others]), axis=-1)
    keep = np.nonzero(mask.sum(axis=1) >= config.min_views - 1)[0]
    if keep.size == 0:
        return _no_points(Ts, config)
    uv_ref = tracks[keep, ref]
    obs = tracks[keep][:, others]
    mask = mask[keep]
    obs = np.where(mask[..., None], obs, 0.0)
    T_jr = np.linalg.inv(Ts[others]) @ Ts[ref]  # reference camera -> neighbour camera
    xbar = np.column_stack(
        [(uv_ref[:, 0] - camera.cx) / camera.fx, (uv_ref[:, 1] - camera.cy) / camera.fy, np.ones(len(keep))]
    )
    held = replace(config, refine_poses=False)
    prob, rho, r, valid = _solved(xbar, obs, mask, T_jr, camera, held)
    seen, sigma_px = _pixel_noise(r, valid, prob.pixel_sigma, len(others), held)
    held_agreeing = int(np.sum(valid.sum(axis=1) >= config.min_views - 1))
    contradicted = False
    if config.refine_poses and valid.sum() < config.refine_below * max(1, mask.sum()):
        # the tracks contradict the given poses: refine them (a bundle adjustment with the looser prior);
        # the noise the residuals showed against the given poses (``seen``) still widens sigma
        # (``variance_factor``): the refined poses fit the tracks, not necessarily the scene's depth
        prob, rho, r, valid, sigma_px, contradicted = _refined(xbar, obs, mask, T_jr, camera, config, len(others))
    else:
        config = held
    var_rho = _inverse_depth_variance(prob, rho, valid, xbar, sigma_px, seen, config)
    out = _accepted(prob, rho, r, valid, xbar, var_rho, sigma_px, keep, uv_ref, Ts, ref, others, config)
    out = replace(out, pose_displacement=_given_pose_displacement(prob, rho, valid, config.pixel_sigma))
    return replace(out, agreeing=held_agreeing) if contradicted else out


def _given_pose_displacement(prob: _Problem, rho: np.ndarray, valid: np.ndarray, pixel_sigma: float) -> float:
    """Median distance (pixels) between the valid observations and the tracks' points projected by the given poses,
    beyond what keypoint noise of ``pixel_sigma`` in both images gives alone (subtracted in quadrature)."""
    use = valid & (rho > 0)[:, None]
    if not use.any():
        return 0.0
    _, z, uv = prob.project(rho, prob.R0, prob.t0)
    dist = np.linalg.norm(uv - prob.uv, axis=-1)[use & (z > 1e-9)]
    dist = dist[np.isfinite(dist)]
    if not dist.size:
        return 0.0
    noise = np.sqrt(2.0 * np.log(2.0)) * np.sqrt(2.0) * pixel_sigma  # median norm of 2-D noise, both keypoints
    return float(np.sqrt(max(0.0, float(np.median(dist)) ** 2 - noise**2)))


def _checked_tracks(
    tracks: np.ndarray, poses: Sequence[np.ndarray] | np.ndarray, reference: int, checked: bool
) -> tuple[np.ndarray, np.ndarray, int]:
    """Checks `triangulate_tracks`'s tracks, poses and reference: (tracks, stacked poses, reference index)."""
    tracks = np.asarray(tracks, dtype=np.float64)
    if tracks.ndim != 3 or tracks.shape[2] != 2:
        raise ShapeError("tracks", "an (N, V, 2) array of pixel positions", describe(tracks))
    n, V = tracks.shape[:2]
    poses = list(poses)
    if len(poses) != V or V < 2:
        raise ShapeError("poses", f"{V} 4x4 poses, one per view of tracks (>= 2 views)", len(poses))
    Ts = np.stack([T if checked else check_pose(T, f"poses[{k}]") for k, T in enumerate(poses)])
    if not -V <= reference < V:
        raise InvalidInputError("reference", f"an index into {V} views", reference)
    ref = reference % V
    if n and not np.all(np.isfinite(tracks[:, ref])):
        raise InvalidInputError(
            "tracks", "every track seen (finite) in the reference view", "NaN in the reference view"
        )
    return tracks, Ts, ref


def _no_points(Ts: np.ndarray, config: TriangulationConfig) -> MultiViewPoints:
    """The `MultiViewPoints` without any point (the poses as given)."""
    return MultiViewPoints(
        np.zeros(0, np.int64),
        np.zeros((0, 2)),
        np.zeros(0),
        np.zeros(0),
        np.zeros((0, 3)),
        np.zeros(0, np.int64),
        np.zeros(0),
        np.zeros(0),
        Ts.copy(),
        float(config.pixel_sigma),
    )


def _refined(
    xbar: np.ndarray,
    obs: np.ndarray,
    mask: np.ndarray,
    T_jr: np.ndarray,
    camera: PinholeCamera,
    config: TriangulationConfig,
    n_others: int,
) -> tuple:
    """Solves again with the poses refined: (problem, rho, residuals, valid, pixel sigma, poses contradicted)."""
    prob, rho, r, valid = _solved(xbar, obs, mask, T_jr, camera, config)
    sigma_px = _pixel_noise(r, valid, prob.pixel_sigma, n_others, config)[1]
    # corrections far beyond the prior: the given poses do not belong to these images
    z = np.sqrt(np.mean(prob.xi**2 * prob.prior, axis=1))
    contradicted = bool(z.size and np.max(z) > _CONTRADICTED)
    return prob, rho, r, valid, sigma_px, contradicted


_CONTRADICTED = 4.0
"""A neighbour's pose correction whose RMS over its 6 components exceeds this many prior sigmas says the given
poses do not belong to the images (inverted, another frame's): the tracks then count as agreeing only as far
as they do with the poses held (`MultiViewPoints.agreeing`)."""


def _solved(xbar, obs, mask, T_jr, camera, config: TriangulationConfig):
    """The inverse depths from the linear start and the robust refinement: (problem, rho, residuals, valid).

    With ``refine_poses`` the neighbours' poses are refined under the prior ``refine_rotation_sigma_deg`` /
    ``refine_translation_sigma``; else they are held, with the prior ``rotation_sigma_deg`` / ``translation_sigma``.
    """
    refine = config.refine_poses
    prob = _Problem(
        xbar,
        obs,
        mask.copy(),
        T_jr[:, :3, :3],
        T_jr[:, :3, 3],
        camera,
        config.pixel_sigma,
        np.radians(config.refine_rotation_sigma_deg if refine else config.rotation_sigma_deg),
        config.refine_translation_sigma if refine else config.translation_sigma,
    )
    mask = mask.copy()
    rho = _linear_inverse_depth(xbar, obs, mask, prob.R, prob.t, prob.f, prob.c)
    rho_ok = np.isfinite(rho) & (rho > 0)
    if refine and rho_ok.any():
        # poses off by a few degrees put many linear depths behind a view; the bundle adjustment corrects
        # the poses, so such tracks start from the others' median depth rather than being dropped
        rho = np.where(rho_ok, rho, np.median(rho[rho_ok]))
    else:
        rho = np.where(rho_ok, rho, 1.0 / np.sqrt(config.min_depth * config.max_depth))
        mask &= rho_ok[:, None]
    prob.mask = mask
    rho, r, valid = _refined_depths(prob, rho, mask, xbar, obs, config)
    return prob, rho, r, valid


def _accepted(prob, rho, r, valid, xbar, var_rho, sigma_px, keep, uv_ref, Ts, ref, others, config) -> MultiViewPoints:
    """Depth and sigma of each track, the geometry checks, and the `MultiViewPoints` of those that pass."""
    depth = np.where(rho > 0, 1.0 / np.where(rho > 0, rho, 1.0), np.nan)
    with np.errstate(invalid="ignore"):
        sigma_geo = np.sqrt(np.maximum(var_rho, 0.0)) * depth**2
    sigma = np.hypot(sigma_geo, config.depth_sigma_floor * depth)
    # geometry checks
    Xr = xbar * depth[:, None]
    n_views, parallax, front, rms = _point_checks(Xr, r, valid, prob.R, prob.t, 0.5 * config.min_depth)
    agree = (n_views >= config.min_views) & np.isfinite(depth) & front
    good = (
        agree
        & (depth >= config.min_depth)
        & (depth <= config.max_depth)
        & front
        & (parallax >= config.min_parallax_deg)
        & np.isfinite(sigma)
        & (sigma > 0)
        & (sigma <= config.max_relative_sigma * depth)
    )
    refined = Ts.copy()
    T_new = np.tile(np.eye(4), (len(others), 1, 1))
    T_new[:, :3, :3], T_new[:, :3, 3] = prob.R, prob.t
    refined[others] = Ts[ref] @ np.linalg.inv(T_new)
    sel = np.nonzero(good)[0]
    Xw = Xr[sel] @ Ts[ref][:3, :3].T + Ts[ref][:3, 3]
    return MultiViewPoints(
        index=keep[sel].astype(np.int64),
        uv=uv_ref[sel],
        depth=depth[sel],
        sigma=sigma[sel],
        points_world=Xw,
        n_views=n_views[sel].astype(np.int64),
        reprojection_error=rms[sel] * sigma_px,
        parallax_deg=parallax[sel],
        poses=refined,
        pixel_sigma=sigma_px,
        agreeing=int(agree.sum()),
    )


# ---------------------------------------------------------------------- compiled kernels (poses held)
@nb.njit(cache=True, nogil=True, error_model="numpy")
def _residual(Rx0, Rx1, Rx2, rho, t, obs0, obs1, f, c, pixel_sigma):  # pragma: no cover - compiled
    """A point on its reference ray at inverse depth rho in one neighbour: (p, residual / pixel_sigma, valid)."""
    p0 = Rx0 + rho * t[0]
    p1 = Rx1 + rho * t[1]
    p2 = Rx2 + rho * t[2]
    r0 = (p0 / p2 * f[0] + c[0] - obs0) / pixel_sigma
    r1 = (p1 / p2 * f[1] + c[1] - obs1) / pixel_sigma
    ok = p2 > 1e-9 and np.isfinite(r0) and np.isfinite(r1)
    return p0, p1, p2, r0, r1, ok


@nb.njit(cache=True, nogil=True)
def _rotated_rays(xbar, R, Rx):  # pragma: no cover - compiled
    """Rx[j] = R[j] @ xbar for every neighbour j (into ``Rx``, (J, 3))."""
    for j in range(R.shape[0]):
        for a in range(3):
            Rx[j, a] = R[j, a, 0] * xbar[0] + R[j, a, 1] * xbar[1] + R[j, a, 2] * xbar[2]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _linear_inverse_depth(xbar, obs, mask, R, t, f, c):  # pragma: no cover - compiled
    """Multi-view DLT of each track's inverse depth along its reference ray (closed form).

    For an observation (x, y) (normalised) in neighbour j: x (r3.xbar + rho t3) = r1.xbar + rho t1
    and the same in y; each row is linear in rho and scaled by the focal length over the
    point's depth proxy, so that the least-squares residual is in pixels. Two passes, the
    second weighting each observation by a Cauchy weight of its first-pass residual (4 px).
    Returns (N,) inverse depths (NaN or <= 0 where the views do not determine one).
    """
    n, nj = mask.shape
    rho = np.full(n, np.nan)
    Rx = np.empty((nj, 3))
    a = np.empty((nj, 2))
    b = np.empty((nj, 2))
    w = np.empty(nj)
    for i in range(n):
        _rotated_rays(xbar[i], R, Rx)
        for j in range(nj):
            sw = 1.0 / max(Rx[j, 2], 1e-6)
            for q in range(2):
                xy = (obs[i, j, q] - c[q]) / f[q]
                a[j, q] = (xy * t[j, 2] - t[j, q]) * (sw * f[q])
                b[j, q] = (Rx[j, q] - xy * Rx[j, 2]) * (sw * f[q])
            w[j] = 1.0 if mask[i, j] else 0.0
        r = np.nan
        for _ in range(2):
            num = 0.0
            den = 0.0
            for j in range(nj):
                num += w[j] * (a[j, 0] * b[j, 0] + a[j, 1] * b[j, 1])
                den += w[j] * (a[j, 0] * a[j, 0] + a[j, 1] * a[j, 1])
            r = num / den
            for j in range(nj):
                e0 = a[j, 0] * r - b[j, 0]
                e1 = a[j, 1] * r - b[j, 1]
                res = np.sqrt(e0 * e0 + e1 * e1)
                if np.isnan(res):
                    res = 1e6
                elif np.isinf(res):
                    res = 1.7976931348623157e308
                w[j] = (1.0 if mask[i, j] else 0.0) / (1.0 + (res / 4.0) ** 2)
        rho[i] = r
    return rho


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _held_pose_depths(xbar, obs, mask, R, t, f, c, pixel_sigma, rho0, scale, max_error):  # pragma: no cover - compiled
    """Robust (Cauchy) Gauss-Newton of each track's inverse depth with the poses held.

    Per track (independent 1-D problems): 3 Gauss-Newton steps from ``rho0``, observations off
    by more than ``max_error`` pixels dropped, one more step. A step that would bring the
    inverse depth below a tenth of its value halves it instead.

    Returns:
        rho (N,), the residuals (N, J, 2) in units of ``pixel_sigma`` (0 where not valid) and
        valid (N, J): observed, kept, in front of the neighbour, finite.
    """
    n, nj = mask.shape
    rho = rho0.copy()
    r_out = np.zeros((n, nj, 2))
    valid = np.zeros((n, nj), np.bool_)
    Rx = np.empty((nj, 3))
    m = np.empty(nj, np.bool_)
    fs0 = f[0] / pixel_sigma
    fs1 = f[1] / pixel_sigma
    s2 = scale * scale
    for i in range(n):
        _rotated_rays(xbar[i], R, Rx)
        for j in range(nj):
            m[j] = mask[i, j]
        x = rho[i]
        for it in range(5):
            if it == 3:  # drop the outliers of the first 3 steps
                for j in range(nj):
                    if m[j]:
                        _, _, _, r0, r1, ok = _residual(
                            Rx[j, 0], Rx[j, 1], Rx[j, 2], x, t[j], obs[i, j, 0], obs[i, j, 1], f, c, pixel_sigma
                        )
                        m[j] = ok and np.sqrt(r0 * r0 + r1 * r1) * pixel_sigma <= max_error
                continue
            h = 0.0
            g = 0.0
            for j in range(nj):
                if not m[j]:
                    continue
                p0, p1, p2, r0, r1, ok = _residual(
                    Rx[j, 0], Rx[j, 1], Rx[j, 2], x, t[j], obs[i, j, 0], obs[i, j, 1], f, c, pixel_sigma
                )
                if not ok:
                    continue
                iz2 = 1.0 / p2**2
                J0 = fs0 * (t[j, 0] * p2 - p0 * t[j, 2]) * iz2
                J1 = fs1 * (t[j, 1] * p2 - p1 * t[j, 2]) * iz2
                wc = 1.0 / (1.0 + (r0 * r0 + r1 * r1) / s2)
                h += wc * (J0 * J0 + J1 * J1)
                g += wc * (J0 * r0 + J1 * r1)
            step = -g / h if h > 0 else 0.0
            x_new = x + step
            x = x_new if x_new > 0.1 * x else 0.5 * x
        rho[i] = x
        for j in range(nj):
            if m[j]:
                _, _, _, r0, r1, ok = _residual(
                    Rx[j, 0], Rx[j, 1], Rx[j, 2], x, t[j], obs[i, j, 0], obs[i, j, 1], f, c, pixel_sigma
                )
                if ok:
                    valid[i, j] = True
                    r_out[i, j, 0] = r0
                    r_out[i, j, 1] = r1
    return rho, r_out, valid


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _held_pose_variance(xbar, rho, valid, R, t, fs, prior_var):  # pragma: no cover - compiled
    """(N,) variance of each inverse depth with the poses held at their given values.

    Pixel noise through the Gauss-Newton information h = sum J_rho^2 (``fs`` = focal length
    over the pixel sigma) plus every neighbour's pose prior (``prior_var``: 6 variances,
    rotation vector then translation) through d rho / d xi = -h^-1 H_rho_xi:
    var = 1/h + sum_j,k (H_rho_xi[j, k] / h)^2 prior_var[k].
    """
    n, nj = valid.shape
    out = np.zeros(n)
    Rx = np.empty((nj, 3))
    H = np.zeros((nj, 6))
    for i in range(n):
        _rotated_rays(xbar[i], R, Rx)
        x = rho[i]
        h = 0.0
        for j in range(nj):
            for k in range(6):
                H[j, k] = 0.0
            if not valid[i, j]:
                continue
            p0 = Rx[j, 0] + x * t[j, 0]
            p1 = Rx[j, 1] + x * t[j, 1]
            p2 = Rx[j, 2] + x * t[j, 2]
            iz = 1.0 / p2
            # d(residual)/dp rows: (a, 0, -a p0 iz) and (0, b, -b p1 iz)
            a0 = fs[0] * iz
            a2 = -fs[0] * p0 * iz * iz
            b1 = fs[1] * iz
            b2 = -fs[1] * p1 * iz * iz
            j_rho0 = a0 * t[j, 0] + a2 * t[j, 2]
            j_rho1 = b1 * t[j, 1] + b2 * t[j, 2]
            h += j_rho0 * j_rho0 + j_rho1 * j_rho1
            # rotation: -Jp @ skew(Rx); translation: Jp * rho
            H[j, 0] = j_rho0 * a2 * Rx[j, 1] + j_rho1 * (b2 * Rx[j, 1] - b1 * Rx[j, 2])
            H[j, 1] = j_rho0 * (a0 * Rx[j, 2] - a2 * Rx[j, 0]) - j_rho1 * b2 * Rx[j, 0]
            H[j, 2] = j_rho1 * b1 * Rx[j, 0] - j_rho0 * a0 * Rx[j, 1]
            H[j, 3] = j_rho0 * a0 * x
            H[j, 4] = j_rho1 * b1 * x
            H[j, 5] = (j_rho0 * a2 + j_rho1 * b2) * x
        inv = 1.0 / h if h > 0 else 0.0
        v = inv
        for j in range(nj):
            for k in range(6):
                e = H[j, k] * inv
                v += e * e * prior_var[k]
        out[i] = v
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _point_checks(Xr, r, valid, R, t, min_front):  # pragma: no cover - compiled
    """Per point (Xr: (N, 3) in the reference camera): views, parallax, in front, RMS residual.

    Returns:
        n_views (N,) (the reference included), the largest angle (degrees) between the
        reference ray and a supporting neighbour's ray (NaN for a NaN point), whether the point
        lies deeper than ``min_front`` in every supporting neighbour, and the RMS of the
        residuals ``r`` over the supporting views.
    """
    n, nj = valid.shape
    n_views = np.ones(n, np.int64)
    parallax = np.zeros(n)
    front = np.ones(n, np.bool_)
    rms = np.zeros(n)
    centre = np.empty((nj, 3))  # neighbour centres in the reference frame: -R^T t
    for j in range(nj):
        for a in range(3):
            centre[j, a] = -(R[j, 0, a] * t[j, 0] + R[j, 1, a] * t[j, 1] + R[j, 2, a] * t[j, 2])
    for i in range(n):
        x0, x1, x2 = Xr[i, 0], Xr[i, 1], Xr[i, 2]
        nx = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        best = 0.0
        ss = 0.0
        count = 0
        for j in range(nj):
            if not valid[i, j]:
                continue
            count += 1
            ss += r[i, j, 0] * r[i, j, 0] + r[i, j, 1] * r[i, j, 1]
            zj = R[j, 2, 0] * x0 + R[j, 2, 1] * x1 + R[j, 2, 2] * x2 + t[j, 2]
            if not zj > min_front:
                front[i] = False
            o0, o1, o2 = x0 - centre[j, 0], x1 - centre[j, 1], x2 - centre[j, 2]
            cosang = (x0 * o0 + x1 * o1 + x2 * o2) / (nx * np.sqrt(o0 * o0 + o1 * o1 + o2 * o2))
            ang = np.degrees(np.arccos(min(max(cosang, -1.0), 1.0)))
            if np.isnan(ang) or np.isnan(best):
                best = np.nan
            elif ang > best:
                best = ang
        n_views[i] = 1 + count
        parallax[i] = best
        rms[i] = np.sqrt(ss / max(count, 1))
    return n_views, parallax, front, rms
