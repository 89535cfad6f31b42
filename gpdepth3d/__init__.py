"""gpdepth3d: Gaussian-process depth completion with posterior variance.

Fuses a dense but inaccurate monocular depth map (MDE) with accurate but sparse range
measurements (LiDAR, SLAM features) following Yoon & Kim, IROS 2020 (KISS-GP), and turns the
result into confidence-weighted point clouds and TSDF maps. Units and frame conventions are
stated once in `gpdepth3d.camera`. Importing the package loads neither torch nor Open3D; the
modules that need them import them when used.

Layers (each folder one layer; imports point down only, checked by tests/test_layers.py):
foundations (`errors`, `camera`, `measurements`, `sampling`, `metrics`, `io`) < `mde`, `datasets`
< `gp` (needs only `errors`) < `completion` < `mapping` < `pipelines` (what a user runs) < `evaluation`
(the paper's protocols) < `cli`, `viewer`. The public API below is re-exported explicitly from the
modules that define it; nothing here comes from `evaluation`.
"""

from ._deprecation import install as _install_moved_modules
from .errors import CalibrationError as CalibrationError
from .errors import ConnectionFailedError as ConnectionFailedError
from .errors import ConvergenceError as ConvergenceError
from .errors import DataFormatError as DataFormatError
from .errors import EmptyInputError as EmptyInputError
from .errors import GPDepthError as GPDepthError
from .errors import InvalidDepthError as InvalidDepthError
from .errors import InvalidInputError as InvalidInputError
from .errors import OutputError as OutputError
from .errors import ProblemTooLargeError as ProblemTooLargeError
from .errors import ShapeError as ShapeError
from .camera import check_pose as check_pose
from .camera import PinholeCamera as PinholeCamera
from .measurements import downsample_depth as downsample_depth
from .measurements import LidarCalibration as LidarCalibration
from .measurements import load_velodyne as load_velodyne
from .measurements import project_points as project_points
from .measurements import SparseDepth as SparseDepth
from .sampling import holdout_split as holdout_split
from .sampling import sample_band as sample_band
from .sampling import sample_scanlines as sample_scanlines
from .sampling import sample_uniform as sample_uniform
from .metrics import calibration_metrics as calibration_metrics
from .metrics import depth_metrics as depth_metrics
from .mde import align_depth as align_depth
from .mde import ArrayMDE as ArrayMDE
from .mde import load_frontend as load_frontend
from .mde import ONNXDepthModel as ONNXDepthModel
from .mde import RTMonoDepthONNX as RTMonoDepthONNX
from .datasets import Frame as Frame
from .datasets import open_dataset as open_dataset
from .datasets.posed import PosedSequence as PosedSequence
from .gp.engine import EngineConfig as EngineConfig
from .gp.model import DepthGPConfig as DepthGPConfig
from .completion.complete import complete as complete
from .completion.complete import DepthCompleter as DepthCompleter
from .completion.complete import DepthPosterior as DepthPosterior
from .completion.complete import PosteriorWarning as PosteriorWarning
from .mapping.cloud import backproject_depth as backproject_depth
from .mapping.cloud import backproject_posterior as backproject_posterior
from .mapping.cloud import ColoredCloud as ColoredCloud
from .mapping.tsdf.fusion import FusionConfig as FusionConfig
from .mapping.tsdf.fusion import save_mesh as save_mesh
from .mapping.tsdf.fusion import TSDFFusion as TSDFFusion
from .mapping.frame_result import FrameResult as FrameResult
from .mapping.mapper import Mapper as Mapper
from .mapping.mapper_config import MapperConfig as MapperConfig
from .mapping.points.map_points import project_map_points as project_map_points
from .mapping.points.map_points import sparse_from_map_points as sparse_from_map_points
from .io.poses import associate_poses as associate_poses
from .io.poses import check_pose_orientation as check_pose_orientation
from .io.poses import invert_pose as invert_pose
from .io.poses import InvertedPoseWarning as InvertedPoseWarning
from .io.poses import pose_from_tq as pose_from_tq
from .io.poses import read_colmap_model as read_colmap_model
from .io.poses import read_flat_poses as read_flat_poses
from .io.poses import read_kitti_poses as read_kitti_poses
from .io.poses import read_pose_files as read_pose_files
from .io.poses import read_trajectory as read_trajectory
from .io.poses import read_tum_trajectory as read_tum_trajectory
from .io.poses import tq_from_pose as tq_from_pose
from .io.poses import Trajectory as Trajectory
from .io.poses import write_tum_trajectory as write_tum_trajectory
from .mapping.points.triangulation import triangulate_frames as triangulate_frames
from .mapping.points.triangulation import TriangulationConfig as TriangulationConfig
from .pipelines.mapping_run import map_sequence as map_sequence
from .pipelines.mapping_run import open_posed_sequence as open_posed_sequence

__version__ = "0.1.0"

_install_moved_modules()  # the old module paths of this release's moves (gpdepth3d._deprecation.MOVED_MODULES)


def __getattr__(name: str):
    """`gpdepth3d.ip_basic`, deprecated for one release: the baseline lives in `gpdepth3d.evaluation.baselines`."""
    if name == "ip_basic":
        from ._deprecation import warn_moved
        from .evaluation.baselines import ip_basic  # the deprecated name's one way in (tests/test_layers.py)

        warn_moved("gpdepth3d.ip_basic", "gpdepth3d.evaluation.baselines.ip_basic", stacklevel=3)
        return ip_basic
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
