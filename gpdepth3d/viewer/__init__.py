"""The browser viewer (viser): `scene_data` (frames, options, point layers), `colors` (colour maps),
`app` (the `Viewer`: scene and GUI; `show`), `serving` (hosts, ports), `files` (any file the library
writes, read for the scene), `launch` (`gpdepth3d view`'s work) and `live_map` (a map growing while
``gpdepth3d map`` runs)."""

from .app import Viewer as Viewer
from .app import show as show
from .colors import COLORMAPS as COLORMAPS
from .colors import MISSING_COLOR as MISSING_COLOR
from .colors import colorbar_image as colorbar_image
from .scene_data import COLOR_MODES as COLOR_MODES
from .scene_data import LAYOUTS as LAYOUTS
from .scene_data import ColorBy as ColorBy
from .scene_data import Layout as Layout
from .scene_data import ViewerConfig as ViewerConfig
from .scene_data import ViewerFrame as ViewerFrame
from .scene_data import default_camera as default_camera
from .scene_data import load_mesh as load_mesh
from .serving import check_host as check_host
from .serving import port_taken as port_taken
