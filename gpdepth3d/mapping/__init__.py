"""From posteriors to 3D: coloured clouds, the TSDF volume, the point front-end and the `Mapper`.

Sub-packages: `tsdf` (the variance-weighted TSDF volume: `TSDFFusion`, `FusionConfig`, weights,
voxel update, extraction, files) and `points` (the points a frame is refined with: features,
tracks, triangulation, re-finding, the local map, given SLAM or COLMAP map points). Modules here:
`cloud` (coloured clouds with per-point variance, which both stand on) and the incremental
`Mapper` with its parts: `mapper` (the class and its per-frame pipeline), `mapper_config`
(`MapperConfig`), `frame_inputs` (checks of `add_frame`'s arguments), `frame_points` (a frame's
measurements on their way), `own_points` (the points the mapper triangulates, the frames waiting
for them), `map_scale` (a frame's points against the map, `fused_depth`), `frame_result`
(`FrameResult`), `map_store` (`Keyframe`, saved maps) and `loop_closure` (`PoseUpdate`, re-fusing
moved keyframes). The mapper's public names are re-exported here. The old flat module paths of the
public API (`fusion`, `triangulation`, `refinding`, ...) import the moved modules, deprecated.
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
from .points.map_points import MapPointStats as MapPointStats
from .points.map_points import merge_sparse as merge_sparse
from .points.map_points import project_map_points as project_map_points
from .points.map_points import sparse_from_map_points as sparse_from_map_points
from .points.refinding import RefindConfig as RefindConfig
