"""Synthetic data with exact ground truth.

The 2D-3D pose scenes (`random_pose_scene`, `demo_chain`, ...) are pure JAX/numpy and load eagerly;
the rendered sequences (`render_sequence`, `PRESETS`, `RayCaster`, ...) need OpenCV, trimesh, embree and
scikit-image and load on first use (PEP 562).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports
from ._pose_scenes import PoseScene as PoseScene
from ._pose_scenes import camera_ring as camera_ring
from ._pose_scenes import demo_chain as demo_chain
from ._pose_scenes import look_at as look_at
from ._pose_scenes import perturb_pose as perturb_pose
from ._pose_scenes import project_model_points as project_model_points
from ._pose_scenes import random_pose_scene as random_pose_scene
from ._pose_scenes import random_rotation as random_rotation

# public name -> private module defining it (loaded on first access)
_LAZY = {
    "ArticulatedSynthConfig": "_articulated",
    "mocap_motion": "_articulated",
    "random_joint_trajectory": "_articulated",
    "render_articulated_sequence": "_articulated",
    "upright_urdf_pose": "_articulated",
    "write_articulated_sequence": "_articulated",
    "CrossingConfig": "_crossing",
    "render_crossing": "_crossing",
    "write_crossing_sequence": "_crossing",
    "RayCaster": "_raycast",
    "SYNTH_RBOT_VARIANTS": "_rbot_layout",
    "RbotSynthConfig": "_rbot_layout",
    "write_rbot_dataset": "_rbot_layout",
    "PRESETS": "_sequences",
    "SynthConfig": "_sequences",
    "render_sequence": "_sequences",
    "write_sequence": "_sequences",
}


__getattr__, __dir__ = lazy_exports(__name__, globals(), _LAZY)


if TYPE_CHECKING:  # static analysers and IDEs see the real definitions
    from ._articulated import ArticulatedSynthConfig as ArticulatedSynthConfig
    from ._articulated import mocap_motion as mocap_motion
    from ._articulated import random_joint_trajectory as random_joint_trajectory
    from ._articulated import render_articulated_sequence as render_articulated_sequence
    from ._articulated import upright_urdf_pose as upright_urdf_pose
    from ._articulated import write_articulated_sequence as write_articulated_sequence
    from ._crossing import CrossingConfig as CrossingConfig
    from ._crossing import render_crossing as render_crossing
    from ._crossing import write_crossing_sequence as write_crossing_sequence
    from ._raycast import RayCaster as RayCaster
    from ._rbot_layout import SYNTH_RBOT_VARIANTS as SYNTH_RBOT_VARIANTS
    from ._rbot_layout import RbotSynthConfig as RbotSynthConfig
    from ._rbot_layout import write_rbot_dataset as write_rbot_dataset
    from ._sequences import PRESETS as PRESETS
    from ._sequences import SynthConfig as SynthConfig
    from ._sequences import render_sequence as render_sequence
    from ._sequences import write_sequence as write_sequence
