"""jaxtrack: differentiable model-based 3D tracking of rigid and articulated objects in JAX.

An implementation of Brox, Rosenhahn, Gall and Cremers, "Combined Region- and Motion-based 3D
Tracking of Rigid and Articulated Objects" (TPAMI 2010).
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from . import cues as cues
from . import geometry as geometry
from . import image as image
from . import modality as modality
from . import render as render
from . import solve as solve
from . import track as track
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._lazy import lazy_exports as _lazy_exports
from ._status import Status as Status
from ._status import StatusError as StatusError
from ._status import check_status as check_status
from ._status import first_failure as first_failure
from ._status import is_usable as is_usable
from ._tiered import wait_for_optimised_programs as wait_for_optimised_programs
from .geometry import Camera as Camera
from .geometry import KinematicModel as KinematicModel
from .geometry import chain_model as chain_model
from .geometry import make_camera as make_camera
from .geometry import part_transforms as part_transforms
from .geometry import rigid_model as rigid_model
from .geometry import se3_exp as se3_exp
from .geometry import se3_log as se3_log
from .modality import Modality as Modality
from .modality import register_modality as register_modality
from .solve import Correspondences as Correspondences
from .solve import Cue as Cue
from .solve import JointPrior as JointPrior
from .solve import PosePrior as PosePrior
from .solve import PoseSolution as PoseSolution
from .solve import PoseStatus as PoseStatus
from .solve import SolverConfig as SolverConfig
from .solve import estimate_pose as estimate_pose
from .solve import make_correspondences as make_correspondences
from .solve import solve_pose as solve_pose
from .track import JointTracker as JointTracker
from .track import Tracker as Tracker
from .track import TrackerConfig as TrackerConfig
from .track import TrackerParams as TrackerParams
from .track import track_objects as track_objects
from .track import track_sequence as track_sequence

__version__ = "0.1.0"

# Host-side subpackages that pull in OpenCV, trimesh, embree and scikit-image load on first access
# (PEP 562): `jaxtrack.io`, `jaxtrack.synth` and `from jaxtrack.synth import ...` work as before, but a
# plain `import jaxtrack` no longer pays for them.
_LAZY_SUBPACKAGES = ("io", "synth", "bench")
# Top-level names that live in a lazy subpackage.
_LAZY_NAMES = {"read_sequence": "io", "run_bench": "bench"}


__getattr__, __dir__ = _lazy_exports(__name__, globals(), {**{m: m for m in _LAZY_SUBPACKAGES}, **_LAZY_NAMES})


if _TYPE_CHECKING:
    from . import bench as bench
    from . import io as io
    from . import synth as synth
