"""I/O: the BOP scene layout and results CSV; your own video or image folder with an OpenCV calibration file and a
first pose from clicked points (`own_sequence`, `read_calibration`, `pose_from_points`); the RBOT dataset's layout
(`read_rbot_sequence`) and BCOT's (`read_bcot_sequence`); meshes, images, Middlebury
.flo flow files, URDF models, mocap skeletons and motions (ASF/AMC, BVH) and human body models built from them.

Names load on first use (PEP 562): OpenCV and trimesh are imported only when a reader or writer that
needs them is touched, so `import jaxtrack` and the .flo functions stay light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

# public name -> private module defining it
_EXPORTS = {
    "CameraView": "_bop",
    "Sequence": "_bop",
    "SequenceError": "_bop",
    "read_bop_results": "_bop",
    "read_camera_view": "_bop",
    "read_sequence": "_bop",
    "write_bop_results": "_bop",
    "frame_step_sequence": "_bop",
    "bop_scenes": "_bop",
    "read_bop_scene": "_bop",
    "bcot_sequences": "_bcot",
    "read_bcot_intrinsics": "_bcot",
    "read_bcot_sequence": "_bcot",
    "rbot_sequences": "_rbot",
    "write_camera_view": "_bop",
    "flow_errors": "_flo",
    "flow_to_colour": "_flo",
    "known_flow_mask": "_flo",
    "read_flo": "_flo",
    "write_flo": "_flo",
    "image_size": "_images",
    "prepare_output_file": "_images",
    "prepare_output_folder": "_images",
    "prepare_image_output": "_images",
    "read_image": "_images",
    "write_image": "_images",
    "load_mesh": "_meshes",
    "load_mesh_arrays": "_meshes",
    "mesh_cache_dir": "_meshes",
    "RBOT_VARIANTS": "_rbot",
    "read_rbot_calibration": "_rbot",
    "read_rbot_poses": "_rbot",
    "read_rbot_sequence": "_rbot",
    "CameraCalibration": "_own_video",
    "PointsPose": "_own_video",
    "VideoView": "_own_video",
    "check_first_pose": "_own_video",
    "is_bop_folder": "_own_video",
    "own_sequence": "_own_video",
    "pose_from_points": "_own_video",
    "read_calibration": "_own_video",
    "read_init_points": "_own_video",
    "write_calibration": "_own_video",
    "load_trimesh": "_meshes",
    "ArticulatedModel": "_urdf",
    "RobotDescription": "_urdf",
    "RobotJoint": "_urdf",
    "RobotLink": "_urdf",
    "articulated_model": "_urdf",
    "read_robot_description": "_urdf",
    "read_urdf": "_urdf",
    "write_urdf": "_urdf",
    "Motion": "_mocap",
    "Skeleton": "_mocap",
    "bone_transforms": "_mocap",
    "joint_positions": "_mocap",
    "read_amc": "_mocap",
    "read_asf": "_mocap",
    "read_bvh": "_mocap",
    "write_bvh": "_mocap",
    "PAPER_DOFS": "_human",
    "human_description": "_human",
    "human_joint_values": "_human",
    "locked_motion": "_human",
    "tapered_capsule": "_human",
}


__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)


if TYPE_CHECKING:  # static analysers and IDEs see the real definitions
    from ._bcot import bcot_sequences as bcot_sequences
    from ._bcot import read_bcot_intrinsics as read_bcot_intrinsics
    from ._bcot import read_bcot_sequence as read_bcot_sequence
    from ._bop import CameraView as CameraView
    from ._bop import Sequence as Sequence
    from ._bop import SequenceError as SequenceError
    from ._bop import bop_scenes as bop_scenes
    from ._bop import frame_step_sequence as frame_step_sequence
    from ._bop import read_bop_results as read_bop_results
    from ._bop import read_bop_scene as read_bop_scene
    from ._bop import read_camera_view as read_camera_view
    from ._bop import read_sequence as read_sequence
    from ._bop import write_bop_results as write_bop_results
    from ._bop import write_camera_view as write_camera_view
    from ._flo import flow_errors as flow_errors
    from ._flo import flow_to_colour as flow_to_colour
    from ._flo import known_flow_mask as known_flow_mask
    from ._flo import read_flo as read_flo
    from ._flo import write_flo as write_flo
    from ._human import PAPER_DOFS as PAPER_DOFS
    from ._human import human_description as human_description
    from ._human import human_joint_values as human_joint_values
    from ._human import locked_motion as locked_motion
    from ._human import tapered_capsule as tapered_capsule
    from ._images import image_size as image_size
    from ._images import prepare_image_output as prepare_image_output
    from ._images import prepare_output_file as prepare_output_file
    from ._images import prepare_output_folder as prepare_output_folder
    from ._images import read_image as read_image
    from ._images import write_image as write_image
    from ._meshes import load_mesh as load_mesh
    from ._meshes import load_mesh_arrays as load_mesh_arrays
    from ._meshes import load_trimesh as load_trimesh
    from ._meshes import mesh_cache_dir as mesh_cache_dir
    from ._mocap import Motion as Motion
    from ._mocap import Skeleton as Skeleton
    from ._mocap import bone_transforms as bone_transforms
    from ._mocap import joint_positions as joint_positions
    from ._mocap import read_amc as read_amc
    from ._mocap import read_asf as read_asf
    from ._mocap import read_bvh as read_bvh
    from ._mocap import write_bvh as write_bvh
    from ._own_video import CameraCalibration as CameraCalibration
    from ._own_video import PointsPose as PointsPose
    from ._own_video import VideoView as VideoView
    from ._own_video import check_first_pose as check_first_pose
    from ._own_video import is_bop_folder as is_bop_folder
    from ._own_video import own_sequence as own_sequence
    from ._own_video import pose_from_points as pose_from_points
    from ._own_video import read_calibration as read_calibration
    from ._own_video import read_init_points as read_init_points
    from ._own_video import write_calibration as write_calibration
    from ._rbot import RBOT_VARIANTS as RBOT_VARIANTS
    from ._rbot import rbot_sequences as rbot_sequences
    from ._rbot import read_rbot_calibration as read_rbot_calibration
    from ._rbot import read_rbot_poses as read_rbot_poses
    from ._rbot import read_rbot_sequence as read_rbot_sequence
    from ._urdf import ArticulatedModel as ArticulatedModel
    from ._urdf import RobotDescription as RobotDescription
    from ._urdf import RobotJoint as RobotJoint
    from ._urdf import RobotLink as RobotLink
    from ._urdf import articulated_model as articulated_model
    from ._urdf import read_robot_description as read_robot_description
    from ._urdf import read_urdf as read_urdf
    from ._urdf import write_urdf as write_urdf
