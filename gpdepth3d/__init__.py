"""gpdepth3d: Gaussian-process depth completion with posterior variance.

Fuses a dense but inaccurate monocular depth map (MDE) with accurate but sparse range
measurements (LiDAR, SLAM features) following Yoon & Kim, IROS 2020 (KISS-GP), and turns the
result into confidence-weighted point clouds and TSDF maps. Units and frame conventions are
stated once in `gpdepth3d.camera`.
"""

from .camera import PinholeCamera as PinholeCamera
from .camera import check_pose as check_pose
from .cloud import ColoredCloud as ColoredCloud
from .cloud import backproject_depth as backproject_depth
from .cloud import backproject_posterior as backproject_posterior
from .fusion import FusionConfig as FusionConfig
from .fusion import TSDFFusion as TSDFFusion
from .fusion import save_mesh as save_mesh
from .mapping import Mapper as Mapper
from .mapping import MapperConfig as MapperConfig
from .mapping import sparse_from_map_points as sparse_from_map_points
from .triangulation import TriangulationConfig as TriangulationConfig
from .triangulation import triangulate_frames as triangulate_frames
from .complete import DepthCompleter as DepthCompleter
from .complete import DepthPosterior as DepthPosterior
from .complete import complete as complete
from .errors import CalibrationError as CalibrationError
from .errors import DataFormatError as DataFormatError
from .errors import EmptyInputError as EmptyInputError
from .errors import GPDepthError as GPDepthError
from .errors import InvalidDepthError as InvalidDepthError
from .errors import InvalidInputError as InvalidInputError
from .errors import ProblemTooLargeError as ProblemTooLargeError
from .errors import ShapeError as ShapeError
from .gp.model import DepthGPConfig as DepthGPConfig
from .measurements import LidarCalibration as LidarCalibration
from .measurements import SparseDepth as SparseDepth
from .measurements import downsample_depth as downsample_depth
from .measurements import load_velodyne as load_velodyne
from .measurements import project_points as project_points
from .metrics import calibration_metrics as calibration_metrics
from .metrics import depth_metrics as depth_metrics

__version__ = "0.1.0"
