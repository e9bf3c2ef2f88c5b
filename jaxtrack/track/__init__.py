"""The tracker (Section V): adaptive cue fusion, the jitted per-frame step, the sequence loop; evaluation."""

from ..solve import CueWeights as CueWeights  # fusion acts on correspondence sets: it lives in solve
from ..solve import fuse_cue_weights as fuse_cue_weights
from ._evaluate import add_error as add_error
from ._evaluate import adds_error as adds_error
from ._evaluate import failure_episodes as failure_episodes
from ._evaluate import model_diameter as model_diameter
from ._evaluate import pose_errors as pose_errors
from ._evaluate import precision_recall as precision_recall
from ._evaluate import success_mask as success_mask
from ._overlay import OverlayRecorder as OverlayRecorder
from ._overlay import OverlayWriter as OverlayWriter
from ._overlay import overlay_frame as overlay_frame
from ._recovery import RecoveryConfig as RecoveryConfig
from ._recovery import RecoveryResult as RecoveryResult
from ._recovery import recover_pose as recover_pose
from ._sequence import FrameRecord as FrameRecord
from ._sequence import TrackingEvaluation as TrackingEvaluation
from ._sequence import TrackingRun as TrackingRun
from ._sequence import evaluate_tracking as evaluate_tracking
from ._sequence import read_joint_results as read_joint_results
from ._sequence import track_sequence as track_sequence
from ._sequence import write_joint_results as write_joint_results
from ._sequence import write_tracking_results as write_tracking_results
from ._step import FrameResult as FrameResult
from ._step import TrackerConfig as TrackerConfig
from ._step import TrackerParams as TrackerParams
from ._step import TrackerSetup as TrackerSetup
from ._step import TrackerState as TrackerState
from ._step import frame_context as frame_context
from ._step import motion_correspondences as motion_correspondences
from ._step import track_step as track_step
from ._tracker import DEFAULT_POSE_PRIOR as DEFAULT_POSE_PRIOR
from ._tracker import Tracker as Tracker
from ._tracker import default_params as default_params
