"""From posteriors to 3D: coloured clouds, TSDF fusion, triangulation, the `Mapper`.

Modules: `cloud` (coloured clouds), `fusion` (the TSDF volume) with `fusion_config` (its options),
`fusion_weights` (per-pixel weights), `tsdf_kernels` (voxel update), `tsdf_blocks` (voxel blocks),
`tsdf_extraction` (meshes, surface points) and `tsdf_io` (volume and mesh files), the points a frame is refined with (`triangulation_config`, `features`,
`tracks`, `multiview`, `two_view`, re-exported by `triangulation`; `refinding` for large camera
motion; `local_map` for the earlier frames' points; `colmap_points` for pycolmap's), and the
incremental `Mapper`: `mapper` (the class and its per-frame pipeline), `mapper_config` (`MapperConfig`),
`frame_inputs` (checks of `add_frame`'s arguments), `frame_points` (a frame's measurements on their way),
`own_points` (the points the mapper triangulates, the frames waiting for them), `map_points` (SLAM map
points as sparse depth), `map_scale` (a frame's points against the map, `fused_depth`), `frame_result`
(`FrameResult`), `map_store` (`Keyframe`, saved maps) and `loop_closure` (`PoseUpdate`, re-fusing moved
keyframes). The mapper's public names are re-exported here.
"""

from .frame_result import STAGES as STAGES
from .frame_result import FrameResult as FrameResult
from .loop_closure import PoseUpdate as PoseUpdate
from .map_scale import fused_depth as fused_depth
from .map_scale import map_scale as map_scale
from .map_store import Keyframe as Keyframe
from .mapper import SEVEN_SCENES_RGB_K as SEVEN_SCENES_RGB_K
from .mapper import Mapper as Mapper
from .mapper_config import MapperConfig as MapperConfig
from .map_points import MapPointStats as MapPointStats
from .map_points import merge_sparse as merge_sparse
from .map_points import project_map_points as project_map_points
from .map_points import sparse_from_map_points as sparse_from_map_points
from .refinding import RefindConfig as RefindConfig
