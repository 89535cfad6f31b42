"""The ``fast`` engine: the exact GP posterior by the cheapest of four routes (grid, dense, Woodbury, Neumann).

The grid route factorises the sparse precision P = (Qv (x) Qu) / s^2 + S^T W S of the separable
Matern field's state-space form; the others apply to few points or nu = 0.5 (`gpdepth3d.gp.routes`).
Maths, routes and limits: docs/engines.md.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from contextlib import nullcontext

import numpy as np

from ..errors import ConvergenceError, InvalidInputError, ShapeError, describe
from .engine import Solution, SolveInfo, _is_int, check_device_available, check_extra_obs, device_name
from .exact import check_problem, dense_log_marginal_likelihood, dense_solve
from .markov import chain_precision, state_dim
from .multifrontal import FrontalFactor, FrontTree, PriorFactor
from .model import GridProblem
from .compile_wait import ready as compiled_ahead
from .cost_model import grid_bytes as grid_bytes
from .elimination_tree import EliminationTree, build_tree, front_tree
from .grid_prior import build_batched_prior, build_frontal_prior
from .observed_lattice import LATTICE_QUANTUM as LATTICE_QUANTUM
from .observed_lattice import observed_lattice as observed_lattice
from .readout import Readout, build_readout, frontal_readout, read_mean
from .torch_factor import TorchFactor, torch_threads
from .cost_model import grid_error_estimate as grid_error_estimate
from .cost_model import memory_budget as memory_budget
from .neumann import NEUMANN_MEAN_TOL, NEUMANN_VAR_TOL
from .routes import IllConditionedError as IllConditionedError
from .routes import RouteQuery, choose_route
from .woodbury import WoodburyPosterior


class FastEngine:
    """Exact GP posterior on the pixel grid by the cheapest route that fits (docs/engines.md).

    Caches per resolution and kernel the elimination tree, prior assembly and read-out, so a
    `DepthCompleter` (one engine) pays only the numeric factorisation from its second frame on.

    Args:
        device: torch device of the torch back-end (None = "cpu"; `check_device_available`).
        tile: Target tile size (pixels per side) of the batched part of the elimination.
        leaf_pixels: Largest sub-grid (pixels) eliminated as one dense front inside a tile (default:
            20 for nu = 0.5 on the compiled back-end, 40 / (nu + 1/2)^2 otherwise).
        cache_size: Number of (resolution, kernel) set-ups kept.
        threads: torch back-end: torch's CPU threads during the numeric work (restored after);
            None keeps torch's setting. The compiled back-end runs one subtree group per numba
            thread (``numba.set_num_threads``) with single-threaded BLAS.
        backend: "compiled" (numba + LAPACK, `gpdepth3d.gp.multifrontal`; CPU only), "torch"
            (batched torch kernels, `gpdepth3d.gp.torch_factor`; any device) or "auto"
            (compiled on the CPU, torch elsewhere).
        route: "auto" (the cheapest route that fits, `gpdepth3d.gp.routes.choose_route`), or one
            of "grid", "dense", "woodbury", "neumann" forced. ``Solution.info.route`` says which
            one a call took, `plan` says it beforehand. The log marginal likelihood uses the grid,
            Woodbury or dense route ("neumann" forced: the grid).
        max_dense_points: The dense route takes at most this many observed pixels.
        max_memory_mb: Memory budget of one solve (MiB); None: three quarters of the memory
            available at the call (`memory_budget`; buffers the engine already holds for the
            resolution are not counted). Routes whose estimated memory exceeds it are not taken.
        prior_cache_mb: Compiled back-end: memory allowed for the factor of the prior alone
            (`PriorFactor`), reused by a sequence's frames for every front their observations do
            not reach (built from the second frame of a resolution and kernel); 0 disables it.
        lattice: Grid route: "observed" factorises only the sub-grid spanning the observed
            pixels (`observed_lattice`; the rest is read out exactly), "full" the whole grid.

    Raises:
        InvalidInputError: an option of the wrong type or range, or a device torch does not see.
    """

    name = "fast"

    def __init__(
        self,
        device=None,
        *,
        tile: int | None = None,
        leaf_pixels: int | None = None,
        cache_size: int = 4,
        threads: int | None = 1,
        backend: str = "auto",
        prior_cache_mb: float = 256.0,
        route: str = "auto",
        max_dense_points: int = 6000,
        max_memory_mb: float | None = None,
        lattice: str = "observed",
    ):
        for name, value in (
            ("threads", threads),
            ("tile", tile),
            ("leaf_pixels", leaf_pixels),
            ("cache_size", cache_size),
        ):
            if (value is not None or name == "cache_size") and not _is_int(value, 1):
                raise InvalidInputError(
                    name, ("an" if name == "cache_size" else "None or an") + " integer >= 1", describe(value)
                )
        self.threads = threads
        if backend not in ("auto", "compiled", "torch"):
            raise InvalidInputError("backend", "'auto', 'compiled' or 'torch'", backend)
        on_cpu = device_name(device) in (None, "cpu")
        if backend == "compiled" and not on_cpu:
            raise InvalidInputError("backend", "'torch' or 'auto' on a non-CPU device", backend)
        device = check_device_available(device)
        self.backend = "compiled" if backend == "auto" and on_cpu else ("torch" if backend == "auto" else backend)
        if not isinstance(prior_cache_mb, (int, float, np.integer, np.floating)) or not prior_cache_mb >= 0:
            raise InvalidInputError("prior_cache_mb", "a number >= 0", prior_cache_mb)
        self.prior_cache_mb = float(prior_cache_mb)
        if route not in ("auto", "grid", "woodbury", "neumann", "dense"):
            raise InvalidInputError("route", "'auto', 'grid', 'woodbury', 'neumann' or 'dense'", route)
        self.route = route
        if (
            isinstance(max_dense_points, (bool, np.bool_))
            or not isinstance(max_dense_points, (int, np.integer))
            or max_dense_points < 0
        ):
            raise InvalidInputError("max_dense_points", "an integer >= 0", max_dense_points)
        self.max_dense_points = int(max_dense_points)
        if max_memory_mb is not None and (
            isinstance(max_memory_mb, (bool, np.bool_))
            or not isinstance(max_memory_mb, (int, float, np.integer, np.floating))
            or not max_memory_mb > 0
            or not np.isfinite(max_memory_mb)
        ):
            raise InvalidInputError("max_memory_mb", "None or a finite number > 0", max_memory_mb)
        self.max_memory_mb = None if max_memory_mb is None else float(max_memory_mb)
        if lattice not in ("observed", "full"):
            raise InvalidInputError("lattice", "'observed' or 'full'", lattice)
        self.lattice = lattice
        self._prior_factor: tuple | None = None  # (key, PriorFactor)
        self._kernel_uses: dict = {}
        self._woodbury_buffers: dict = {}  # image buffers of the Woodbury route, per output shape
        self._neumann_buffers: dict = {}  # coefficient buffer of the Neumann route
        self.device = device
        self.tile = tile
        self.leaf_pixels = leaf_pixels
        self.cache_size = int(cache_size)
        self._trees: OrderedDict = OrderedDict()
        self._priors: OrderedDict = OrderedDict()
        self._readouts: OrderedDict = OrderedDict()

    # -- caches
    def _cached(self, store: OrderedDict, key, build):
        if key in store:
            store.move_to_end(key)
            return store[key]
        value = build()
        store[key] = value
        while len(store) > self.cache_size:
            store.popitem(last=False)
        return value

    def _tree_key(self, h: int, w: int, ds: int) -> tuple:
        tile = self.tile or (24 if ds == 1 else 12 if ds == 4 else 8)
        # smaller leaves for nu = 0.5 on the compiled back-end: fewer flops on sparse-point lattices
        leaf = self.leaf_pixels or (20 if ds == 1 and self.backend == "compiled" else max(1, 40 // ds))
        return (h, w, ds, tile, leaf)

    def _tree(self, h: int, w: int, ds: int) -> EliminationTree:
        key = self._tree_key(h, w, ds)
        tile, leaf = key[3], key[4]

        def build():
            tree = build_tree(h, w, ds, tile, leaf)
            tree.__dict__["_key"] = key  # what the prior and read-out caches refer to (ids can be reused)
            return tree

        return self._cached(self._trees, key, build)

    def _prior(self, tree: EliminationTree, nu: float, lengthscale: float):
        key = (tree.__dict__["_key"], float(nu), float(lengthscale), self.backend)
        build = build_frontal_prior if self.backend == "compiled" else build_batched_prior
        return self._cached(self._priors, key, lambda: build(tree, nu, lengthscale))

    def _readout(self, tree: EliminationTree, problem: GridProblem) -> Readout:
        k = problem.kernel
        key = (
            tree.__dict__["_key"],
            problem.out_rows.tobytes(),
            problem.out_cols.tobytes(),
            float(k.nu),
            float(k.lengthscale),
        )
        return self._cached(
            self._readouts, key, lambda: build_readout(tree, problem.out_rows, problem.out_cols, k.nu, k.lengthscale)
        )

    def _reusable_prior(self, tree: EliminationTree, fronts: FrontTree, prior, kernel, prec_var: np.ndarray):
        """The cached `PriorFactor` for this tree and kernel when worth it (see ``prior_cache_mb``)."""
        key = (tree.__dict__["_key"], float(kernel.nu), float(kernel.lengthscale))
        uses = self._kernel_uses[key] = self._kernel_uses.get(key, 0) + 1
        if len(self._kernel_uses) > 64:  # forget kernels of past fits
            self._kernel_uses = {key: uses}
        if self._prior_factor is not None and self._prior_factor[0] == key and self._prior_factor[1].tree is fronts:
            cached = self._prior_factor[1]
        elif uses >= 2 and fronts.prior_bytes <= self.prior_cache_mb * 2**20:
            cached = None
        else:
            return None
        if fronts.touched_share(prec_var) > 0.75:
            return None
        if cached is None:
            self._prior_factor = None  # free the old one first
            cached = PriorFactor(fronts, prior.asm, prior.qvals)
            self._prior_factor = (key, cached)
        return cached

    def _threads(self):
        """torch's thread setting for the torch back-end (the compiled one sets its own)."""
        return torch_threads(self.threads) if self.backend == "torch" else nullcontext()

    def _route(self, problem: GridProblem, variance: bool, *, lml: bool = False, extra: int = 0):
        """(route, its Neumann series or None, the grid route's problem) for ``problem`` (see ``route``).

        The routes judge themselves (`gpdepth3d.gp.routes`); the grid route's problem is the
        sub-grid spanning the observed pixels with ``lattice="observed"``.

        Raises:
            The errors of `gpdepth3d.gp.routes.choose_route`.
        """
        route = self.route
        if route == "neumann" and lml and problem.kernel.exponential:
            route = "grid"  # the series gives no log-determinant
        sub = self._lattice_problem(problem) if route in ("auto", "grid") or lml else problem
        query = RouteQuery(
            problem,
            sub,
            bool(variance),
            int(extra),
            bool(lml),
            route != "auto",
            self.backend,
            self._budget(),
            self.max_dense_points,
            self._grid_buffers_held(*sub.shape, problem.kernel.nu),
            self._neumann_buffers,
        )
        choice = choose_route(query, route)
        return choice.name, choice.payload, sub

    def _grid_buffers_held(self, h: int, w: int, nu: float) -> bool:
        """True when this engine already holds the grid route's buffers for this resolution (an earlier
        frame's, kept for reuse): the route then allocates nothing large, whatever memory is free now."""
        tree = self._trees.get(self._tree_key(h, w, state_dim(nu) ** 2))
        fronts = None if tree is None else tree.__dict__.get("_fronts")
        return bool(fronts is not None and fronts.__dict__.get("_pool"))

    @staticmethod
    def _woodbury(problem: GridProblem, buffers) -> WoodburyPosterior:
        """`WoodburyPosterior` with a failed factorisation mapped to a typed error."""
        try:
            return WoodburyPosterior(problem, buffers)
        except np.linalg.LinAlgError as err:
            k = problem.kernel
            raise ConvergenceError(
                f"fast engine, woodbury route: the observed-pixel covariance of the Matern kernel nu={k.nu}, "
                f"lengthscale={k.lengthscale:g} px, outputscale={k.outputscale:g} m is not numerically positive "
                f"definite (largest observation precision {float(np.max(problem.precision)):.3g} 1/m^2): {err}"
            ) from None

    def _budget(self) -> int:
        return int(self.max_memory_mb * 2**20) if self.max_memory_mb is not None else memory_budget()

    # -- public
    def factorize(self, problem: GridProblem):
        """Factorises the posterior precision of ``problem``.

        Returns:
            (factor, tree, prior, real_vars): the factor, the cached elimination structure and
            prior assembly, and the (H, W) variable index of state 0 of each grid pixel.
        """
        _check_problem(problem)
        return self._factorize(problem)

    def _factorize(self, problem: GridProblem):
        """`factorize` of a checked problem (`solve` checks it once)."""
        h, w = problem.shape
        k = problem.kernel
        d = state_dim(k.nu)
        tree = self._tree(h, w, d * d)
        prior = self._prior(tree, k.nu, k.lengthscale)
        real_vars = tree.pix_var.reshape(tree.padded)[:h, :w]
        prec_var = np.zeros(tree.nvar)
        prec_var[real_vars.ravel()] = np.asarray(problem.precision, dtype=np.float64).ravel()
        inv_s2 = 1.0 / float(k.outputscale) ** 2
        try:
            if self.backend == "compiled":
                fronts = front_tree(tree)
                pf = self._reusable_prior(tree, fronts, prior, k, prec_var)
                factor = FrontalFactor(fronts, prior.asm, prior.qvals, prec_var, scale2=1.0 / inv_s2, prior=pf)
            else:
                with torch_threads(self.threads):
                    factor = TorchFactor(tree, prior, inv_s2, prec_var, self.device)
        except np.linalg.LinAlgError as err:
            raise IllConditionedError(
                f"fast engine, grid route: the posterior precision of the Matern kernel nu={k.nu}, "
                f"lengthscale={k.lengthscale:g} px, outputscale={k.outputscale:g} m on a {h} x {w} grid is not "
                f"numerically positive definite (estimated error {grid_error_estimate(problem):.2g} x outputscale; "
                f"largest observation precision {float(np.max(problem.precision)):.3g} 1/m^2): {err}"
            ) from None
        return factor, tree, prior, real_vars

    def _posterior_states(self, problem: GridProblem, extra: tuple = ()):
        """Factor and posterior state means of ``problem`` and of each further observation array in ``extra``
        (the compiled back-end solves them all in one pass over the factor)."""
        factor, tree, prior, real_vars = self._factorize(problem)
        prec = np.asarray(problem.precision, dtype=np.float64)
        prior_mean = np.asarray(problem.prior_mean, np.float64)
        observed = prec > 0
        resid = np.where(observed, np.asarray(problem.obs, np.float64) - prior_mean, 0.0)
        rhs = np.zeros((1 + len(extra), tree.nvar))  # one right-hand side per row: b = rhs.T, no transposed copy
        rhs[0, real_vars.ravel()] = (prec * resid).ravel()
        for j, e in enumerate(extra):
            rhs[1 + j, real_vars.ravel()] = np.where(observed, prec * (e - prior_mean), 0.0).ravel()
        b = rhs.T
        compiled_ahead("solve")  # a cold cache: the solve's and read-out's kernels come from the second process
        with self._threads():
            if self.backend == "compiled":
                x = factor.solve(b)
                mus = [x[:, j] for j in range(x.shape[1])]
            else:
                mus = [factor.solve(b[:, j]) for j in range(b.shape[1])]
        return factor, tree, prior, real_vars, mus, prec, resid

    def plan(self, problem: GridProblem, *, variance: bool = True, extra: int = 0, lml: bool = False) -> str:
        """The route that `solve` (or, with ``lml``, `log_marginal_likelihood`) takes for ``problem``.

        Args:
            problem: The grid problem.
            variance: Whether the call computes variances.
            extra: Number of further observation vectors (``extra_obs``) of the call.
            lml: The route of `log_marginal_likelihood` instead.

        Raises:
            The errors of `solve` that concern the route (no route, a forced route that does not apply).
        """
        _check_problem(problem)
        route, payload, _ = self._route(problem, variance, lml=lml, extra=int(extra))
        if payload is not None:
            payload.release()
        return route

    def _lattice_problem(self, problem: GridProblem) -> GridProblem:
        """``problem`` on the sub-grid spanning its observed pixels (``lattice="observed"``), else itself."""
        if self.lattice == "full":
            return problem
        box = observed_lattice(problem.precision)
        if box is None:
            return problem
        r0, r1, c0, c1 = box
        win = (slice(r0, r1), slice(c0, c1))
        return GridProblem(
            np.asarray(problem.prior_mean)[win],
            np.asarray(problem.obs)[win],
            np.asarray(problem.precision)[win],
            np.asarray(problem.out_rows, np.float64) - r0,
            np.asarray(problem.out_cols, np.float64) - c0,
            problem.out_prior_mean,
            problem.kernel,
        )

    def solve(self, problem: GridProblem, *, variance: bool = True, extra_obs=()) -> Solution:
        """Posterior mean (Ho, Wo) in metres and marginal variance (Ho, Wo) in m^2 (or None).

        Args:
            problem: The grid problem (either formulation).
            variance: Also compute the marginal variances (selected inversion).
            extra_obs: Further (H, W) observation arrays (the same prior mean, precision and
                kernel); their posterior means reuse this call's factorisation
                (`Solution.extra_means`).

        Returns:
            A `Solution` (unpacks as ``mean, variance``); ``info.route`` says which route
            computed it, ``info.seconds`` the time of its stages ("plan", "factor", "mean",
            "variance", "total"), ``info.details`` the observed pixels and, on the grid route,
            the lattice it factorised ((r0, r1, c0, c1) of the GP grid).

        Raises:
            IllConditionedError: (a `ConvergenceError`) the grid route cannot represent this kernel
                accurately in float64 and no other route applies (or "grid" is forced).
            ProblemTooLargeError: every applicable route exceeds the memory budget (before allocating).
            InvalidInputError: a malformed problem (`gpdepth3d.gp.exact.check_problem`) or a forced
                route that does not apply to it.
            ShapeError: an ``extra_obs`` array of another shape than the grid.
        """
        t0 = time.perf_counter()
        _check_problem(problem)
        extra = check_extra_obs(problem, extra_obs)
        route, post, sub = self._route(problem, variance, extra=len(extra))
        m = int(np.count_nonzero(np.asarray(problem.precision) > 0))
        seconds = {"plan": time.perf_counter() - t0}
        details: dict = {"observed": m}
        if route == "dense":
            mean, var, extras = dense_solve(problem, variance=variance, extra_obs=extra)
        elif route == "woodbury":
            t = time.perf_counter()
            post = self._woodbury(problem, self._woodbury_buffers)
            seconds["factor"] = time.perf_counter() - t
            t = time.perf_counter()
            mean, extras = post.means(extra)
            seconds["mean"] = time.perf_counter() - t
            t = time.perf_counter()
            var = post.variance() if variance else None
            seconds["variance"] = time.perf_counter() - t
        elif route == "neumann":
            try:
                t = time.perf_counter()
                km = post.terms(NEUMANN_MEAN_TOL)
                mean = post.mean(km)
                extras = tuple(post.mean(km, e) for e in extra)
                seconds["mean"] = time.perf_counter() - t
                t = time.perf_counter()
                var = post.variance(post.terms(NEUMANN_VAR_TOL)) if variance else None
                seconds["variance"] = time.perf_counter() - t
            finally:
                post.release()
        else:
            mean, var, extras = self._grid_solve(sub, variance, extra, problem, seconds)
            details["lattice"] = self._lattice_box(problem, sub)
        seconds["total"] = time.perf_counter() - t0
        return Solution(mean, var, SolveInfo("fast", route, seconds, details), extras)

    @staticmethod
    def _lattice_box(problem: GridProblem, sub: GridProblem) -> tuple[int, int, int, int]:
        """(r0, r1, c0, c1) of the GP grid that ``sub`` (the grid route's problem) covers."""
        if sub is problem:
            return (0, problem.shape[0], 0, problem.shape[1])
        r0 = int(round(float(problem.out_rows[0]) - float(sub.out_rows[0])))
        c0 = int(round(float(problem.out_cols[0]) - float(sub.out_cols[0])))
        return (r0, r0 + sub.shape[0], c0, c0 + sub.shape[1])

    def _grid_solve(self, problem: GridProblem, variance: bool, extra: tuple, original: GridProblem, seconds: dict):
        """The grid route on ``problem`` (the lattice of ``original``): (mean, variance, extra means)."""
        t = time.perf_counter()
        if problem is not original:  # the extra observations on the lattice too
            r0, r1, c0, c1 = self._lattice_box(original, problem)
            extra = tuple(e[r0:r1, c0:c1] for e in extra)
        factor, tree, prior, real_vars, mus, prec, _ = self._posterior_states(problem, extra)
        seconds["factor"] = time.perf_counter() - t
        t = time.perf_counter()
        h, w = problem.shape
        k = problem.kernel
        d = state_dim(k.nu)
        s2 = float(k.outputscale) ** 2
        same_grid = problem.output_is_input
        readout = None if same_grid else self._readout(tree, problem)
        out_prior = np.asarray(problem.out_prior_mean, np.float64)
        means = []
        for x in mus:
            if same_grid:
                means.append(out_prior + x[real_vars])  # state (0, 0) of each pixel
            else:
                means.append(read_mean(readout, x, real_vars, d, out_prior))
        seconds["mean"] = time.perf_counter() - t
        if not variance:
            return means[0], None, tuple(means[1:])
        t = time.perf_counter()
        if same_grid:
            with self._threads():
                diag, _ = factor.selected_inverse(None)
            var = diag[real_vars]
        else:
            if self.backend == "compiled":
                ro, (single, var_of, w2) = frontal_readout(factor.tree, readout)
                diag, out = factor.selected_inverse(ro)
                out[single] = w2 * diag[var_of]
            else:
                with self._threads():
                    _, out = factor.selected_inverse(readout)
            var = out.reshape(problem.out_shape) + s2 * readout.resid
        seconds["variance"] = time.perf_counter() - t
        return means[0], np.maximum(var, 0.0), tuple(means[1:])

    def log_marginal_likelihood(self, problem: GridProblem) -> float:
        """Log marginal likelihood log p(y) of the observed pixels of ``problem`` (nats).

        Uses log p(y) = log N(y; f*, W^-1) + log N(f*; m, Q^-1) - log N(f*; f*, P^-1) at the
        posterior mean f* (the latent field on the padded grid, all states), with log det P
        from the Cholesky factor and log det Q from the 1-D chains.
        """
        _check_problem(problem)
        route, _, sub = self._route(problem, False, lml=True)
        if route == "woodbury":
            return self._woodbury(problem, None).log_marginal_likelihood()
        if route == "dense":
            return dense_log_marginal_likelihood(problem)
        problem = sub  # the observed pixels' likelihood on the lattice that spans them
        factor, tree, prior, real_vars, (mu,), prec, resid = self._posterior_states(problem)
        k = problem.kernel
        d = state_dim(k.nu)
        s2 = float(k.outputscale) ** 2
        obs = prec > 0
        f = mu[real_vars]
        data = -0.5 * float(np.sum(prec[obs] * (resid[obs] - f[obs]) ** 2))
        data += 0.5 * float(np.sum(np.log(prec[obs]))) - 0.5 * obs.sum() * np.log(2 * np.pi)
        hp, wp = tree.padded
        Qv, _ = chain_precision(np.arange(hp, dtype=np.float64), k.nu, k.lengthscale)
        Qu, _ = chain_precision(np.arange(wp, dtype=np.float64), k.nu, k.lengthscale)
        X = (
            mu[tree.pix_var[:, None] + np.arange(tree.ds)]
            .reshape(hp, wp, d, d)
            .transpose(0, 2, 1, 3)
            .reshape(hp * d, wp * d)
        )
        quad = float(np.sum(X * (Qv @ (Qu @ X.T).T))) / s2
        logdet_q = prior.logdet - tree.nvar * np.log(s2)
        return data - 0.5 * quad + 0.5 * logdet_q - 0.5 * factor.logdet


def _check_problem(problem: GridProblem) -> None:
    check_problem(problem)
    h, w = problem.shape
    if h < 2 or w < 2:
        raise ShapeError("problem", "a GP grid of at least 2 x 2 pixels", f"{h} x {w}")
