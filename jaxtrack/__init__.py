"""jaxtrack: differentiable model-based 3D tracking of rigid and articulated objects in JAX.

An implementation of Brox, Rosenhahn, Gall and Cremers, "Combined Region- and Motion-based 3D
Tracking of Rigid and Articulated Objects" (TPAMI 2010).
"""

from . import cues as cues
from . import image as image
from . import geometry as geometry
from . import io as io
from . import render as render
from . import solve as solve
from . import synth as synth
from ._status import Status as Status
from ._status import StatusError as StatusError
from ._status import check_status as check_status
from ._status import first_failure as first_failure
from ._status import is_usable as is_usable
from .geometry import Camera as Camera
from .geometry import KinematicModel as KinematicModel
from .geometry import chain_model as chain_model
from .geometry import make_camera as make_camera
from .geometry import part_transforms as part_transforms
from .geometry import rigid_model as rigid_model
from .geometry import se3_exp as se3_exp
from .geometry import se3_log as se3_log
from .solve import Correspondences as Correspondences
from .solve import Cue as Cue
from .solve import PoseSolution as PoseSolution
from .solve import PoseStatus as PoseStatus
from .solve import SolverConfig as SolverConfig
from .solve import estimate_pose as estimate_pose
from .solve import make_correspondences as make_correspondences
from .solve import solve_pose as solve_pose

__version__ = "0.1.0"
