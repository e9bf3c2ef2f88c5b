"""Synthetic data with exact ground truth."""

from ._pose_scenes import PoseScene as PoseScene
from ._pose_scenes import camera_ring as camera_ring
from ._pose_scenes import demo_chain as demo_chain
from ._pose_scenes import look_at as look_at
from ._pose_scenes import perturb_pose as perturb_pose
from ._pose_scenes import project_model_points as project_model_points
from ._pose_scenes import random_pose_scene as random_pose_scene
from ._pose_scenes import random_rotation as random_rotation
from ._raycast import RayCaster as RayCaster
from ._sequences import PRESETS as PRESETS
from ._sequences import SynthConfig as SynthConfig
from ._sequences import render_sequence as render_sequence
from ._sequences import write_sequence as write_sequence
