"""The ``kissgp`` engine: the paper's GPyTorch KISS-GP, set up so that it computes the exact model.

Yoon & Kim (IROS 2020) via structured kernel interpolation (Wilson & Nickisch, ICML 2015) and CG;
inducing grid on the pixel centres, so on the input grid only the CG tolerance separates it from
`ExactEngine`. Set-up, GPyTorch pitfalls and variance methods: docs/engines.md#the-kissgp-engine-in-detail.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Literal

import numpy as np
import torch

import gpytorch
import linear_operator
from gpytorch.utils.interpolation import Interpolation
from linear_operator.operators import DenseLinearOperator, KroneckerProductLinearOperator, ToeplitzLinearOperator

from ..errors import ConvergenceError, InvalidInputError, ProblemTooLargeError
from .cost_model import kissgp_bytes, memory_budget
from .engine import Solution, SolveInfo, check_device_available, check_extra_obs
from .model import GridProblem
from .exact import check_problem

VarianceMethod = Literal["auto", "cholesky", "probe", "solve", "love"]

#: Grid axes longer than this use Toeplitz (FFT) Kronecker factors, shorter ones dense factors.
TOEPLITZ_ABOVE = 1000

#: Rounds of refinement of the CG columns whose true residual is above the tolerance (`KissGPEngine._cg`).
REFINE_ROUNDS = 4


class PixelGridInterpolationKernel(gpytorch.kernels.GridInterpolationKernel):
    """GPyTorch ``GridInterpolationKernel`` whose inducing grid is the pixel grid of an image.

    The grid nodes are the integer pixel centres ``-pad .. H - 1 + pad`` (rows) and
    ``-pad .. W - 1 + pad`` (columns); inputs are (row, col) in pixel units. ``K_UU`` is built
    as ``K_rows (x) K_cols`` (Toeplitz factors), the order of GPyTorch's row-major interpolation
    indices (its own ``GridKernel`` reverses it, which is wrong on non-square grids).

    Args:
        base_kernel: A stationary one-dimensional-capable GPyTorch kernel (here a Matern).
        shape: (H, W) of the pixel grid.
        pad: Grid nodes added beyond the image on every side (>= 2 keeps outputs within
            [-0.5, H - 0.5] clear of GPyTorch's interpolation boundary handling).
    """

    def __init__(
        self, base_kernel: gpytorch.kernels.Kernel, shape: tuple[int, int], *, pad: int = 2, toeplitz: bool = False
    ):
        h, w = int(shape[0]), int(shape[1])
        if h < 1 or w < 1:
            raise InvalidInputError("shape", "(H, W) with H, W >= 1", shape)
        if pad < 2:
            raise InvalidInputError("pad", "an integer >= 2", pad)
        bounds = ((-float(pad), float(h - 1 + pad)), (-float(pad), float(w - 1 + pad)))
        super().__init__(base_kernel, grid_size=[h + 2 * pad, w + 2 * pad], grid_bounds=bounds)
        self.pad = pad
        self.toeplitz = bool(toeplitz)
        self.image_shape = (h, w)
        # Integer nodes (create_grid's spacing is (b1 - b0 + 2 d) / (G - 1), not 1).
        nodes = [torch.arange(-pad, size + pad, dtype=torch.float64) for size in (h, w)]
        self.update_grid(nodes)

    def _inducing_forward(self, last_dim_is_batch, **params):
        if last_dim_is_batch:
            return super()._inducing_forward(last_dim_is_batch=last_dim_is_batch, **params)
        factors = []
        for g in self.grid:
            first_col = self.base_kernel(g[:1].unsqueeze(-1), g.unsqueeze(-1), **params).to_dense().squeeze(-2)
            if self.toeplitz:
                factors.append(ToeplitzLinearOperator(first_col))
            else:
                idx = torch.arange(g.shape[-1], device=g.device)
                factors.append(DenseLinearOperator(first_col[(idx[:, None] - idx[None, :]).abs()]))
        return KroneckerProductLinearOperator(*factors)


class _KissGPModel(gpytorch.models.ExactGP):
    """The paper's model: zero mean (data are residuals), ScaleKernel(KISS-GP(Matern))."""

    def __init__(self, train_x, train_y, likelihood, *, nu: float, lengthscale: float, shape, pad: int, toeplitz: bool):
        super().__init__(train_x, train_y, likelihood)
        self.mean_module = gpytorch.means.ZeroMean()
        base = gpytorch.kernels.MaternKernel(nu=nu)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            PixelGridInterpolationKernel(base, shape, pad=pad, toeplitz=toeplitz)
        )
        self.to(dtype=torch.float64)
        # Set after the float64 conversion: a float32 raw parameter would be off by ~1e-7.
        base.lengthscale = lengthscale
        self.covar_module.outputscale = 1.0

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def variance_flops(
    n: int, shape: tuple[int, int], outputs: int, columns: int, iterations: int, *, pad: int = 2, toeplitz: bool = False
) -> dict[str, float]:
    """Floating-point operations of the variance at ``outputs`` pixels from n observed pixels of a grid of
    ``shape``: {"cholesky": the dense route, "cg": CG over ``columns`` right-hand sides ("solve": one per output
    pixel; "probe": one per colour) of ``iterations`` products each}.

    One product with the KISS-GP matrix costs the interpolation (16 weights a point, both sides) and the grid's
    Kronecker product (dense factors: 2 H W (H + W); Toeplitz: FFTs). The Cholesky reads its kernel blocks from
    the grid's factors, factorises (n^3 / 3) and solves a triangle per output pixel (n^2): with the hundreds of
    CG iterations a long length scale takes, it is the cheaper well beyond a few thousand points.
    """
    hp, wp = shape[0] + 2 * pad, shape[1] + 2 * pad
    grid = 10.0 * hp * wp * math.log2(hp * wp) if toeplitz else 2.0 * hp * wp * (hp + wp)
    product = grid + 64.0 * n
    return {"cholesky": n**3 / 3 + float(outputs) * n * n, "cg": float(columns) * (max(iterations, 1) + 2) * product}


def default_device() -> str:
    """ "cuda" when torch sees a GPU, else "cpu"."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def _check_memory(shape: tuple[int, int], out_shape: tuple[int, int], budget: int) -> None:
    """Refuses a solve whose working memory (`cost_model.kissgp_bytes`) would pass ``budget`` (bytes)."""
    need = kissgp_bytes(shape, out_shape)
    if need > budget:
        raise ProblemTooLargeError(
            "kissgp problem",
            f"at most {budget / 2**30:.1f} GiB (three quarters of the device's free memory)",
            f"{shape[0]}x{shape[1]} grid, {out_shape[0]}x{out_shape[1]} outputs: about {need / 2**30:.1f} GiB; "
            "use the fast engine",
        )


class KissGPEngine:
    """GP posterior with GPyTorch KISS-GP (the paper's method), exact on the pixel grid.

    The model, the set-up and its one approximation (upsampled output):
    docs/engines.md#the-kissgp-engine-in-detail. Each `solve` returns, with the posterior, the CG
    iteration counts, the achieved relative residuals and the timings (``Solution.info``).

    Args:
        device: Torch device ("cpu", "cuda", "cuda:1"); default "cuda" if available else "cpu".
        variance_method: "auto" (default: "cholesky" for at most `max_cholesky_size` observed pixels;
            beyond, the CG method, "probe" when at least half the pixels are observed, else "solve", unless
            "cholesky" needs fewer flops than its solves and fits the memory budget, `variance_flops`),
            "cholesky", "probe", "solve" (all exact on the grid, see the module docstring) or "love"
            (GPyTorch LOVE / fast_pred_var, approximate).
        cg_tolerance: Relative residual ||A x - b|| / ||b|| at which CG stops (mean solve).
        variance_cg_tolerance: Relative residual of the batched variance solves (mean over
            the block; every column is checked against 10x this afterwards).
        max_cg_iterations: CG iteration limit; exceeding it raises `ConvergenceError`.
        preconditioner_size: Rank of GPyTorch's pivoted-Cholesky preconditioner, used only
            when all observation noises are equal (0, the default = never: forming it costs
            more than the iterations it saves).
        root_decomposition_size: Lanczos rank of LOVE ("love" only).
        block_entries: Memory bound of the variance solves: right-hand sides per block are
            chosen so that (observed pixels x block) stays below this many entries.
        pad: Inducing-grid nodes beyond the image on every side (>= 2).
        toeplitz: Kronecker factors as Toeplitz (FFT) operators instead of dense matrices;
            default: only for grid axes longer than `TOEPLITZ_ABOVE` nodes.
        max_cholesky_size: "auto" uses the Cholesky route up to this many observed pixels whatever it
            costs (beyond, where it needs fewer flops than the CG solves and its matrices fit the memory budget).
        probe_spacing: Lattice spacing (GP-grid pixels) of the "probe" colouring; the number
            of probe vectors is its square (plus one per output pixel over a hole).
    """

    name = "kissgp"

    def __init__(
        self,
        *,
        device: str | torch.device | None = None,
        variance_method: VarianceMethod = "auto",
        cg_tolerance: float = 1e-8,
        variance_cg_tolerance: float = 1e-10,
        max_cg_iterations: int = 5000,
        preconditioner_size: int = 0,
        root_decomposition_size: int = 1000,
        block_entries: int = 20_000_000,
        pad: int = 2,
        toeplitz: bool | None = None,
        max_cholesky_size: int = 2000,
        probe_spacing: int = 4,
    ):
        if variance_method not in ("auto", "cholesky", "probe", "solve", "love"):
            raise InvalidInputError(
                "variance_method", "'auto', 'cholesky', 'probe', 'solve' or 'love'", variance_method
            )
        for name, value in (("cg_tolerance", cg_tolerance), ("variance_cg_tolerance", variance_cg_tolerance)):
            if (
                isinstance(value, (bool, np.bool_))
                or not isinstance(value, (int, float, np.integer, np.floating))
                or not (math.isfinite(value) and 0 < value < 1)
            ):
                raise InvalidInputError(name, "a value in (0, 1)", value)
        for name, value, low in (
            ("max_cg_iterations", max_cg_iterations, 1),
            ("preconditioner_size", preconditioner_size, 0),
            ("root_decomposition_size", root_decomposition_size, 1),
            ("block_entries", block_entries, 1),
            ("pad", pad, 2),
            ("max_cholesky_size", max_cholesky_size, 0),
            ("probe_spacing", probe_spacing, 1),
        ):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
                raise InvalidInputError(name, f"an integer >= {low}", value)
        self.device = torch.device(default_device() if device is None else check_device_available(device))
        self.variance_method = variance_method
        self.cg_tolerance = float(cg_tolerance)
        self.variance_cg_tolerance = float(variance_cg_tolerance)
        self.max_cg_iterations = int(max_cg_iterations)
        self.preconditioner_size = int(preconditioner_size)
        self.root_decomposition_size = int(root_decomposition_size)
        self.block_entries = int(block_entries)
        self.pad = int(pad)
        self.toeplitz = None if toeplitz is None else bool(toeplitz)
        self.max_cholesky_size = int(max_cholesky_size)
        self.probe_spacing = int(probe_spacing)

    # ------------------------------------------------------------------ helpers
    def _tensor(self, a) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64, device=self.device)

    def _cg(self, op, rhs: torch.Tensor, tolerance: float, preconditioner) -> tuple[torch.Tensor, int, float]:
        """Solves op X = rhs with GPyTorch's CG until every column's true relative residual is at most
        ``tolerance`` (or `max_cg_iterations` are spent); returns X, iterations and the worst residual.

        GPyTorch's CG stops when the *mean* residual of the columns passes its tolerance, which leaves the
        hardest of many columns (a variance block's) well above it: those columns are refined from their true
        residual (X += CG(op, R)) until each passes.
        """
        calls = [0]

        def matmul(x):
            calls[0] += 1
            return op._matmul(x)

        def run(b, tol, iterations):
            with warnings.catch_warnings():
                # Convergence is checked below on the true residual, per column.
                warnings.simplefilter("ignore", linear_operator.utils.warnings.NumericalWarning)
                return linear_operator.utils.linear_cg(
                    matmul,
                    b,
                    tolerance=tol,
                    eps=1e-300,
                    stop_updating_after=tol * 1e-2,
                    max_iter=iterations,
                    max_tridiag_iter=0,
                    preconditioner=preconditioner,
                )

        x = run(rhs, tolerance, self.max_cg_iterations)
        norms = rhs.norm(dim=0).clamp_min(1e-300)
        resid = op._matmul(x) - rhs
        rel = resid.norm(dim=0) / norms
        for _ in range(REFINE_ROUNDS):
            bad = torch.nonzero(rel > tolerance).flatten()
            left = self.max_cg_iterations - calls[0]
            if bad.numel() == 0 or left < 1:
                break
            # each column's residual must fall from rel to tolerance: the hardest ratio is the correction's tolerance
            tol = float(torch.clamp((tolerance / rel[bad]).min(), 1e-14, 0.5))
            x[:, bad] -= run(resid[:, bad], tol, left)
            resid = op._matmul(x) - rhs
            rel = resid.norm(dim=0) / norms
        iterations = max(calls[0] - 1, 0)  # one product computes the initial residual
        return x, iterations, float(rel.max()) if rel.numel() else 0.0

    # ------------------------------------------------------------------ solve
    def solve(self, problem: GridProblem, *, variance: bool = True, extra_obs=()) -> Solution:
        """Posterior mean (Ho, Wo) in metres and marginal variance (Ho, Wo) in m^2 (or None).

        Args:
            problem: The grid problem.
            variance: Also compute the marginal variances.
            extra_obs: Further (H, W) observation arrays; their posterior means come from the
                same CG run (one column each, `Solution.extra_means`).

        Returns:
            A `Solution` (unpacks as ``mean, variance``); route "kissgp", ``info.details`` the CG
            iteration counts, the achieved relative residuals, the variance method and the
            device; ``info.seconds`` "mean", "variance" and "total".

        Raises:
            ConvergenceError: CG did not reach its tolerance within `max_cg_iterations`.
        """
        check_problem(problem)
        extra = check_extra_obs(problem, extra_obs)
        t0 = time.perf_counter()
        k = problem.kernel
        s = float(k.outputscale)
        h, w = problem.shape
        ho, wo = problem.out_shape
        _check_memory((h, w), (ho, wo), self._memory_budget())
        rows, cols = np.nonzero(problem.precision > 0)
        n = rows.shape[0]
        stats: dict = {"observed": int(n), "outputs": int(ho * wo), "device": str(self.device)}
        out_r, out_c = np.meshgrid(problem.out_rows, problem.out_cols, indexing="ij")
        test_x = self._tensor(np.stack([out_r.ravel(), out_c.ravel()], axis=1))
        prior_out = problem.out_prior_mean.astype(np.float64).reshape(ho, wo)

        train_x = self._tensor(np.stack([rows, cols], axis=1).astype(np.float64))
        y = self._tensor((problem.obs[rows, cols] - problem.prior_mean[rows, cols]) / s)
        noise = self._tensor(1.0 / (problem.precision[rows, cols] * s * s))
        likelihood = gpytorch.likelihoods.FixedNoiseGaussianLikelihood(noise=noise, learn_additional_noise=False)
        model = _KissGPModel(
            train_x,
            y,
            likelihood,
            nu=k.nu,
            lengthscale=k.lengthscale,
            shape=(h, w),
            pad=self.pad,
            toeplitz=self.toeplitz if self.toeplitz is not None else max(h, w) + 2 * self.pad > TOEPLITZ_ABOVE,
        ).to(device=self.device, dtype=torch.float64)
        model.eval()
        likelihood.eval()
        covar = model.covar_module

        with torch.no_grad():
            if n == 0:
                prior_var = covar(test_x, diag=True).to_dense().reshape(ho, wo)
                stats.update(cg_iterations_mean=0, cg_iterations_variance=0)
                var = (s * s * prior_var).cpu().numpy() if variance else None
                return Solution(prior_out.copy(), var, self._info(stats, t0), tuple(prior_out.copy() for _ in extra))

            A = covar(train_x).evaluate_kernel().add_diagonal(noise)
            precond = None
            constant_noise = bool(torch.all(noise == noise[0]))
            if constant_noise and self.preconditioner_size > 0 and n > self.preconditioner_size:
                with (
                    linear_operator.settings.max_preconditioner_size(self.preconditioner_size),
                    linear_operator.settings.min_preconditioning_size(0),
                ):
                    precond = A._preconditioner()[0]
            stats["preconditioner"] = "pivoted_cholesky" if precond is not None else "none"
            t1 = time.perf_counter()
            rhs = [y] + [self._tensor((e[rows, cols] - problem.prior_mean[rows, cols]) / s) for e in extra]
            alpha, iters, resid = self._cg(A, torch.stack(rhs, dim=1), self.cg_tolerance, precond)
            stats.update(cg_iterations_mean=iters, cg_residual_mean=resid)
            if not resid <= max(10 * self.cg_tolerance, 1e-12):
                raise ConvergenceError(
                    f"kissgp: CG reached a relative residual of {resid:.3g} after {iters} iterations "
                    f"(tolerance {self.cg_tolerance:g}); raise max_cg_iterations or check the noise levels"
                )
            cross = covar(test_x, train_x).evaluate_kernel()
            means = cross._matmul(alpha).cpu().numpy()  # (Ho Wo, 1 + extras)
            mean_np = prior_out + s * means[:, 0].reshape(ho, wo)
            extra_means = tuple(prior_out + s * means[:, j].reshape(ho, wo) for j in range(1, means.shape[1]))
            t2 = time.perf_counter()
            stats["time_mean"] = t2 - t1
            var_np = None
            if variance:
                method = self._choose_variance_method(problem, n, iters)
                stats["variance_method"] = method
                if method == "cholesky":
                    var = self._variance_cholesky(covar, noise, train_x, problem, stats)
                elif method == "probe":
                    var = self._variance_probe(covar, A, train_x, test_x, problem, precond, stats)
                elif method == "solve":
                    var = self._variance_solve(covar, A, train_x, test_x, precond, stats)
                else:
                    var = self._variance_love(model, test_x, stats)
                var_np = s * s * var.clamp_min(0.0).reshape(ho, wo).cpu().numpy()
            stats["time_variance"] = time.perf_counter() - t2
        return Solution(mean_np, var_np, self._info(stats, t0), extra_means)

    @staticmethod
    def _info(stats: dict, t0: float) -> SolveInfo:
        """The call's `SolveInfo` from its statistics (times "time_*" become ``seconds``)."""
        seconds = {k[5:]: v for k, v in stats.items() if k.startswith("time_")}
        seconds["total"] = time.perf_counter() - t0
        details = {k: v for k, v in stats.items() if not k.startswith("time_")}
        return SolveInfo("kissgp", "kissgp", seconds, details)

    def _check_variance_cg(self, resid: float, iters: int) -> None:
        if not resid <= max(10 * self.variance_cg_tolerance, 1e-12):
            raise ConvergenceError(
                f"kissgp: variance CG reached a relative residual of {resid:.3g} after {iters} iterations "
                f"(tolerance {self.variance_cg_tolerance:g}); raise max_cg_iterations"
            )

    def _memory_budget(self) -> int:
        """Bytes the engine's device may hold: three quarters of a GPU's free memory, or of the host's."""
        if self.device.type == "cuda":
            return torch.cuda.mem_get_info(self.device)[0] * 3 // 4
        return memory_budget()

    def _choose_variance_method(self, problem: GridProblem, n: int, iterations: int) -> str:
        """The "auto" variance method for n observed pixels (see the class docstring); ``iterations``: the mean's
        CG iterations, the estimate of each variance column's."""
        if self.variance_method != "auto":
            return self.variance_method
        if n <= self.max_cholesky_size:
            return "cholesky"
        h, w = problem.shape
        outputs = problem.out_shape[0] * problem.out_shape[1]
        iterative = "probe" if n >= 0.5 * h * w else "solve"
        columns = self._probe_colours(problem)[1] if iterative == "probe" else outputs
        toeplitz = self.toeplitz if self.toeplitz is not None else max(h, w) + 2 * self.pad > TOEPLITZ_ABOVE
        flops = variance_flops(n, (h, w), outputs, columns, iterations, pad=self.pad, toeplitz=toeplitz)
        dense_bytes = 8 * (5 * n * n + 3 * self.block_entries)  # K_oo's gathers and sum, L; a block's
        if flops["cholesky"] < flops["cg"] and dense_bytes <= self._memory_budget():
            return "cholesky"
        return iterative

    def _variance_cholesky(self, covar, noise, train_x, problem: GridProblem, stats) -> torch.Tensor:
        """Cholesky of the (n, n) KISS-GP matrix, var = k** - |L^-1 K_o*|^2, with K_oo and K_o* read from the
        grid's factors (`_kernel_factors`) instead of products with the whole grid."""
        n = train_x.shape[0]
        ho, wo = problem.out_shape
        m = ho * wo
        k_oo, (p_rows, q_rows), (p_cols, q_cols) = self._kernel_factors(
            covar, train_x, problem.out_rows, problem.out_cols
        )
        chol = torch.linalg.cholesky(k_oo + torch.diag(noise))
        out = torch.empty(m, dtype=torch.float64, device=self.device)
        block = int(max(1, min(m, self.block_entries // max(n, 1))))
        for start in range(0, m, block):
            j = torch.arange(start, min(m, start + block), device=self.device)
            half = torch.linalg.solve_triangular(chol, p_rows[:, j // wo] * p_cols[:, j % wo], upper=False)
            out[j] = q_rows[j // wo] * q_cols[j % wo] - (half * half).sum(0)
        stats["cg_iterations_variance"] = 0
        return out

    def _kernel_factors(self, covar, train_x: torch.Tensor, out_rows, out_cols):
        """The KISS-GP kernel ``covar`` between the n observed pixels and the output grid out_rows x out_cols, by
        axis: K_oo (n, n), (P_r (n, Ho), q_r (Ho,)), (P_c (n, Wo), q_c (Wo,)) with K(observed i, output (y, x)) =
        P_r[i, y] P_c[i, x] and the output's prior variance k((y, x), (y, x)) = q_r[y] q_c[x].

        K_UU = K_r (x) K_c and GPyTorch's interpolation weights are products of one cubic per axis, w = w_r (x)
        w_c, so the kernel between grid nodes o (the observed pixels) and an interpolated point is (K_r[r_o] w_r)
        (K_c[c_o] w_c), and its prior variance (w_r' K_r w_r)(w_c' K_c w_c): matrix products per axis for the
        whole output grid, where GPyTorch's operator takes a product with the whole grid per output pixel (the
        same sums in another order).
        """
        grid_kernel = covar.base_kernel
        k_rows, k_cols = (f.to_dense() for f in grid_kernel._inducing_forward(last_dim_is_batch=False).linear_ops)
        nodes = [(train_x[:, axis].round().long() + grid_kernel.pad) for axis in (0, 1)]
        scale = covar.outputscale
        axes = []
        for axis, (k, coords) in enumerate(((k_rows, out_rows), (k_cols, out_cols))):
            x = self._tensor(coords)[:, None]
            index, weight = Interpolation().interpolate([grid_kernel.grid[axis]], x)  # (len, 4) nodes, weights
            interp = torch.zeros(x.shape[0], k.shape[0], dtype=torch.float64, device=self.device)
            interp.scatter_add_(1, index, weight)
            w_k = interp @ k
            axes.append((w_k[:, nodes[axis]].T, (w_k * interp).sum(1)))
        k_oo = scale * k_rows[nodes[0]][:, nodes[0]] * k_cols[nodes[1]][:, nodes[1]]
        (p_rows, q_rows), cols = axes
        return k_oo, (scale * p_rows, scale * q_rows), cols

    def _probe_colours(self, problem: GridProblem) -> tuple[np.ndarray, int, np.ndarray]:
        """(colour of each output pixel, number of colours, the output pixels over holes) of the "probe" method:
        a lattice of spacing `probe_spacing` GP-grid pixels, and a colour of its own for each output pixel whose
        nearest GP pixel is unobserved."""
        ho, wo = problem.out_shape
        h, w = problem.shape
        dr = max(1, int(math.ceil(self.probe_spacing * ho / h - 1e-9)))
        dc = max(1, int(math.ceil(self.probe_spacing * wo / w - 1e-9)))
        rr, cc = np.meshgrid(np.arange(ho), np.arange(wo), indexing="ij")
        colour = ((rr % dr) * dc + (cc % dc)).ravel()
        near_r = np.clip(np.rint(problem.out_rows), 0, h - 1).astype(np.int64)
        near_c = np.clip(np.rint(problem.out_cols), 0, w - 1).astype(np.int64)
        observed = (problem.precision[near_r][:, near_c] > 0).ravel()
        lone = np.flatnonzero(~observed)
        colour[lone] = dr * dc + np.arange(lone.size)
        return colour, dr * dc + lone.size, lone

    def _variance_probe(self, covar, A, train_x, test_x, problem, precond, stats) -> torch.Tensor:
        """Posterior covariance probing: diag(S) from S Z for a colouring Z of the output pixels.

        S = K** - K*o A^-1 Ko* is the posterior covariance of the output pixels. Output pixels
        whose nearest GP pixel is observed are coloured with a lattice of spacing d
        (`probe_spacing` GP-grid pixels); column c of Z is the indicator of colour c, and
        (S Z)_ic = S_ii + the sum of S_ij over the other pixels j of i's colour, all at least d
        pixels away. With dense observations (the balanced formulation) the posterior covariance
        of observed pixels decays within a pixel or two, so this matches the exact engine to the
        bound tests/gp/test_kissgp.py checks. Output pixels over unobserved pixels (holes),
        where the posterior covariance is long-ranged, each get a column of their own (exact).
        """
        colour, count, lone = self._probe_colours(problem)
        m = test_x.shape[0]
        n = train_x.shape[0]
        colour_t = torch.as_tensor(colour, device=self.device)
        cross_o = covar(train_x, test_x).evaluate_kernel()
        cross_t = covar(test_x, train_x).evaluate_kernel()
        prior = covar(test_x).evaluate_kernel()
        out = torch.empty(m, dtype=torch.float64, device=self.device)
        block = int(max(1, min(count, self.block_entries // max(n, m, 1))))
        iters_total, worst, blocks = 0, 0.0, 0
        order = np.argsort(colour, kind="stable")
        bounds = np.searchsorted(colour[order], np.arange(0, count + block, block))
        for b0 in range(0, count, block):
            b1 = min(count, b0 + block)
            rows_b = torch.as_tensor(order[bounds[b0 // block] : bounds[b0 // block + 1]], device=self.device)
            Z = torch.zeros(m, b1 - b0, dtype=torch.float64, device=self.device)
            Z[rows_b, colour_t[rows_b] - b0] = 1.0
            x, iters, resid = self._cg(A, cross_o._matmul(Z), self.variance_cg_tolerance, precond)
            self._check_variance_cg(resid, iters)
            sz = prior._matmul(Z) - cross_t._matmul(x)
            out[rows_b] = sz[rows_b, colour_t[rows_b] - b0]
            iters_total, worst, blocks = iters_total + iters, max(worst, resid), blocks + 1
        stats.update(
            cg_iterations_variance=iters_total / max(blocks, 1),
            cg_residual_variance=worst,
            probe_vectors=int(count),
            probe_unobserved_outputs=int(lone.size),
        )
        return out

    def _variance_solve(self, covar, A, train_x, test_x, precond, stats) -> torch.Tensor:
        """Exact predictive variance k** - k*o A^-1 ko* by batched CG, in blocks of output pixels."""
        n = train_x.shape[0]
        m = test_x.shape[0]
        block = int(max(1, min(m, self.block_entries // max(n, 1))))
        out = torch.empty(m, dtype=torch.float64, device=self.device)
        total_iters, worst, blocks = 0, 0.0, 0
        for start in range(0, m, block):
            xb = test_x[start : start + block]
            b = xb.shape[0]
            eye = torch.eye(b, dtype=torch.float64, device=self.device)
            rhs = covar(train_x, xb).evaluate_kernel()._matmul(eye)  # (n, b) = K_o*
            prior = covar(xb, diag=True).to_dense()
            x, iters, resid = self._cg(A, rhs, self.variance_cg_tolerance, precond)
            self._check_variance_cg(resid, iters)
            out[start : start + b] = prior - (rhs * x).sum(0)
            total_iters += iters
            worst = max(worst, resid)
            blocks += 1
        stats.update(
            cg_iterations_variance=total_iters / max(blocks, 1), cg_residual_variance=worst, variance_blocks=blocks
        )
        return out

    def _variance_love(self, model, test_x, stats) -> torch.Tensor:
        """GPyTorch LOVE (fast_pred_var) predictive variance with a rank-r Lanczos root."""
        with (
            gpytorch.settings.fast_pred_var(True),
            gpytorch.settings.max_root_decomposition_size(self.root_decomposition_size),
            gpytorch.settings.max_cg_iterations(self.max_cg_iterations),
            gpytorch.settings.eval_cg_tolerance(self.cg_tolerance),
            gpytorch.settings.cg_tolerance(self.cg_tolerance),
            linear_operator.settings.max_preconditioner_size(0),
            linear_operator.settings.max_cholesky_size(0),
        ):  # always the Lanczos root, as on large frames
            var = model(test_x).variance
        stats["root_decomposition_size"] = self.root_decomposition_size
        return var
