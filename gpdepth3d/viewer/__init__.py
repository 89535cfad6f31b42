"""The browser viewer (viser): GP-refined vs MDE-only depth in 3D. See `gpdepth3d.viewer.app`."""

from .app import COLOR_MODES as COLOR_MODES
from .app import COLORMAPS as COLORMAPS
from .app import LAYOUTS as LAYOUTS
from .app import MISSING_COLOR as MISSING_COLOR
from .app import ColorBy as ColorBy
from .app import Layout as Layout
from .app import Viewer as Viewer
from .app import ViewerConfig as ViewerConfig
from .app import ViewerFrame as ViewerFrame
from .app import check_host as check_host
from .app import colorbar_image as colorbar_image
from .app import default_camera as default_camera
from .app import load_mesh as load_mesh
from .app import port_taken as port_taken
from .app import show as show
