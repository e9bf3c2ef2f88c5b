"""Dense variational optical flow (Brox et al. 2004) restricted to the object region (eq. 6-8)."""

from ._api import ROI_SIZES as ROI_SIZES
from ._api import BidirectionalFlow as BidirectionalFlow
from ._api import compute_flow_bidirectional as compute_flow_bidirectional
from ._api import compute_flow_roi as compute_flow_roi
from ._api import roi_crop as roi_crop
from ._consistency import forward_backward_consistency as forward_backward_consistency
from ._correspondences import flow_correspondences as flow_correspondences
from ._energy import FlowEnergyParams as FlowEnergyParams
from ._energy import articulated_params as articulated_params
from ._energy import flow_confidence as flow_confidence
from ._energy import flow_energy as flow_energy
from ._energy import local_flow_energy as local_flow_energy
from ._energy import middlebury_params as middlebury_params
from ._energy import rigid_params as rigid_params
from ._solver import FlowConfig as FlowConfig
from ._solver import FlowResult as FlowResult
from ._solver import MotionTensor as MotionTensor
from ._solver import compute_flow as compute_flow
from ._solver import flow_level_energies as flow_level_energies
from ._solver import linearised_flow_energy as linearised_flow_energy
from ._solver import median_filter_flow as median_filter_flow
from ._solver import middlebury_config as middlebury_config
from ._solver import motion_tensor as motion_tensor
from ._solver import prepare_image as prepare_image
from ._solver import refine_flow as refine_flow
