"""The TSDF volume: a variance-weighted truncated signed distance field on Open3D's voxel blocks.

Modules: `fusion` (`TSDFFusion`, the volume), `fusion_config` (`FusionConfig`, its options),
`fusion_weights` (per-pixel weights from the variance), `kernels` (the projective voxel update),
`blocks` (voxel blocks), `extraction` (meshes, surface points) and `storage` (volume and mesh files).
They stand on `gpdepth3d.mapping.cloud` only; nothing here knows the `Mapper`.
"""
