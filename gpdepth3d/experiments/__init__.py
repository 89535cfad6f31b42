"""The paper's protocols and the library's own experiments, as functions that return data.

Modules: `evaluation` (methods x protocols x densities on a dataset, `run_evaluation`),
`kitti_protocol` (the paper's KITTI tables), `batch` (dataset-scale runs on Dask),
`baselines` (IP-Basic), `synthetic` (ray-cast scenes with simulated LiDAR and MDE; `simulate_mde`,
the one MDE stand-in), `frames` (one frame's inputs on a GP grid: `mde_to_grid`, `holdout_lidar`),
`scoring` (`metric_row`, the one metric row) and `demo`.
Nothing below this layer imports it.
"""
