"""The tracker: adaptive cue fusion (Section V), the per-frame step and the sequence loop; evaluation."""

from ..solve import CueWeights as CueWeights  # fusion acts on correspondence sets: it lives in solve
from ..solve import fuse_cue_weights as fuse_cue_weights
from ._evaluate import add_error as add_error
from ._evaluate import adds_error as adds_error
from ._evaluate import model_diameter as model_diameter
from ._evaluate import pose_errors as pose_errors
from ._evaluate import precision_recall as precision_recall
from ._evaluate import success_mask as success_mask
