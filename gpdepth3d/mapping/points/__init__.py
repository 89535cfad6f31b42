"""The point front-end: the sparse points a frame is refined with, from images, earlier frames or a given map.

Modules: `triangulation_config` (`TriangulationConfig`), `features` (detection and matching),
`tracks` (feature tracks over frames), `two_view` and `multiview` (triangulation with sigma),
`triangulation` (`triangulate_frames`, re-exporting the pieces), `refinding` (points re-found after
large camera motion), `local_map` (the earlier frames' points), `map_points` (SLAM map points as
sparse depth) and `colmap_points` (pycolmap's points). Nothing here knows the `Mapper` or the volume.
"""
