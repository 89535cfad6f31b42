"""What a user runs: the product's runners, as functions that return data and write outputs.

Modules: `mapping_run` (map a posed sequence: `map_sequence`, `open_posed_sequence`, `write_map`,
`fuse_sequence`), `batch` (dataset-scale completion on Dask, `run_batch`), `previews` (PNG previews
and the six-panel frame figure), `demo` (the simulated-scene demo), `sfm` (a metric map from an image folder alone, by pycolmap), `frames` (one frame's inputs on a
GP grid: `mde_to_grid`, `holdout_lidar`) and `scoring` (`metric_row`, the one metric row).
Synthetic scenes, which the demo and the batch's simulated MDE use, are a data source:
`gpdepth3d.datasets.synthetic`. The paper's protocols stand above this layer (`gpdepth3d.evaluation`);
nothing here imports them.
"""
