"""Padded correspondence sets and the weighted Plücker-line pose solver (eq. 3-5)."""

from ._correspondences import Correspondences as Correspondences
from ._correspondences import Cue as Cue
from ._correspondences import concatenate_correspondences as concatenate_correspondences
from ._correspondences import correspondences_from_pixels as correspondences_from_pixels
from ._correspondences import make_correspondences as make_correspondences
from ._correspondences import pad_rows as pad_rows
from ._fusion import CueWeights as CueWeights
from ._fusion import fuse_cue_weights as fuse_cue_weights
from ._pose_solver import JointPrior as JointPrior
from ._pose_solver import PosePrior as PosePrior
from ._pose_solver import PoseSolution as PoseSolution
from ._pose_solver import PoseStatus as PoseStatus
from ._pose_solver import SolverConfig as SolverConfig
from ._pose_solver import estimate_pose as estimate_pose
from ._pose_solver import fraction_behind_cameras as fraction_behind_cameras
from ._pose_solver import input_status as input_status
from ._pose_solver import model_points_world as model_points_world
from ._pose_solver import plucker_residuals as plucker_residuals
from ._pose_solver import root_conditioning as root_conditioning
from ._pose_solver import solve_pose as solve_pose
from ._pose_solver import weights_per_pixel as weights_per_pixel
