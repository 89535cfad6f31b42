"""The paper's protocols, as functions that return data.

Modules: `evaluation` (methods x protocols x densities on a dataset, `run_evaluation`),
`kitti_protocol` (the paper's KITTI tables) and `baselines` (IP-Basic). They stand on the product
(`gpdepth3d.pipelines`: frames on a GP grid, the metric row, the figures) and on the synthetic scenes
of `gpdepth3d.datasets.synthetic`; of the package's commands only `gpdepth3d eval` imports them.
"""
