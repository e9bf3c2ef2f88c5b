"""I/O: the BOP scene layout, the BOP results CSV, meshes, Middlebury .flo flow files."""

from ._bop import CameraView as CameraView
from ._bop import Sequence as Sequence
from ._bop import SequenceError as SequenceError
from ._bop import read_bop_results as read_bop_results
from ._bop import read_camera_view as read_camera_view
from ._bop import read_sequence as read_sequence
from ._bop import write_bop_results as write_bop_results
from ._bop import write_camera_view as write_camera_view
from ._meshes import load_mesh as load_mesh
from ._meshes import load_trimesh as load_trimesh
from ._flo import flow_errors as flow_errors
from ._flo import flow_to_colour as flow_to_colour
from ._flo import known_flow_mask as known_flow_mask
from ._flo import read_flo as read_flo
from ._flo import write_flo as write_flo
