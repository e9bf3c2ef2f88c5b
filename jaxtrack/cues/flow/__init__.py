"""Dense variational optical flow (Brox et al. 2004) restricted to the object region (eq. 6-8)."""

from ._energy import FlowEnergyParams as FlowEnergyParams
from ._energy import articulated_params as articulated_params
from ._energy import flow_confidence as flow_confidence
from ._energy import flow_energy as flow_energy
from ._energy import image_gradients as image_gradients
from ._energy import local_flow_energy as local_flow_energy
from ._energy import rigid_params as rigid_params
from ._energy import warp_bilinear as warp_bilinear
