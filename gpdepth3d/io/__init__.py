"""Reading and writing: the one home of the package's file formats; every write is atomic.

Modules: `durable` (atomic writes, output sets, the JSON writer), `arrays` (stored ``.npy`` /
``.npz`` arrays and text matrices, checked before they are read), `depth` (depth PNGs and the
depth reader), `points` (sparse point lists), `images` (RGB images) and `poses` (every pose
format: one reader per format, the format table `POSE_FORMATS`, trajectories and COLMAP models).
The names below are re-exported so that ``from gpdepth3d.io import X`` keeps working.
"""

from .durable import TOGETHER_BASE as TOGETHER_BASE
from .durable import atomic_path as atomic_path
from .durable import atomic_write as atomic_write
from .durable import atomic_write_set as atomic_write_set
from .durable import check_output_folder as check_output_folder
from .durable import check_output_path as check_output_path
from .durable import clean_output_folder as clean_output_folder
from .durable import clean_output_set as clean_output_set
from .durable import npz_writer as npz_writer
from .durable import output_set as output_set
from .durable import save_npz as save_npz
from .durable import to_jsonable as to_jsonable
from .durable import write_json as write_json
from .durable import write_problem as write_problem
from .durable import write_together as write_together
from .arrays import check_stored_array as check_stored_array
from .arrays import load_npz_arrays as load_npz_arrays
from .arrays import read_matrix as read_matrix
from .depth import KITTI_PNG_SCALE as KITTI_PNG_SCALE
from .depth import PNGRangeWarning as PNGRangeWarning
from .depth import check_png_scale as check_png_scale
from .depth import depth_png_values as depth_png_values
from .depth import load_depth as load_depth
from .depth import png_writer as png_writer
from .depth import save_depth_png as save_depth_png
from .points import load_sparse as load_sparse
from .images import check_image_header as check_image_header
from .images import load_rgb as load_rgb
from .poses import POSE_FORMATS as POSE_FORMATS
from .poses import detect_pose_format as detect_pose_format
from .poses import load_pose as load_pose
from .poses import load_poses as load_poses
from .poses import read_trajectory as read_trajectory
