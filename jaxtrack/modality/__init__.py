"""The modality protocol, its registry and the one refinement loop the tracker runs over modalities."""

from ._loop import RefineResult as RefineResult
from ._loop import RefineSettings as RefineSettings
from ._loop import RoundState as RoundState
from ._loop import cauchy_weights as cauchy_weights
from ._loop import fuse_rows as fuse_rows
from ._loop import live_count as live_count
from ._loop import mean_motion as mean_motion
from ._loop import refine_rounds as refine_rounds
from ._loop import render_crops as render_crops
from ._loop import reprojection_px as reprojection_px
from ._protocol import FrameContext as FrameContext
from ._protocol import FusionCounts as FusionCounts
from ._protocol import Modality as Modality
from ._protocol import Pose as Pose
from ._protocol import StartContext as StartContext
from ._registry import cue_names as cue_names
from ._registry import modality_class as modality_class
from ._registry import modality_names as modality_names
from ._registry import register_modality as register_modality
