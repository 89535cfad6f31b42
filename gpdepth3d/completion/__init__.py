"""Depth completion: build a frame's GP problem, solve it, the posterior (layer above `gpdepth3d.gp`).

Modules: `problem` (validated inputs -> `GridProblem`), `complete` (`complete()`,
`DepthCompleter`, `DepthPosterior`), `formulations` (one strategy class per formulation), `marginal_fit` (a
Gaussian formulation's hyperparameters fitted to a frame), and the default model's stages run by
`log_residual` (docs/model.md): `log_frame`, `mde_slope`, `screen`,
`lattice`, `solve`, `detail`, `assemble`, `calibrate`, with `diagnostics` (its warnings). The function
`complete` is re-exported by `gpdepth3d` itself, not here: in this package the name
``complete`` is the module.
"""

from .complete import DepthCompleter as DepthCompleter
from .complete import DepthPosterior as DepthPosterior
from .complete import PosteriorWarning as PosteriorWarning
from .marginal_fit import fit_hyperparameters as fit_hyperparameters
from .marginal_fit import log_marginal_likelihood as log_marginal_likelihood
from .problem import build_problem as build_problem
from .problem import check_mde_depth as check_mde_depth
from .problem import check_output_shape as check_output_shape
