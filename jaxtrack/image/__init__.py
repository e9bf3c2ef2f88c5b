"""Image operations shared by every cue: derivatives, sampling, blur, pyramids, medians, distances.

All functions are pure JAX on (H, W) or (H, W, C) arrays with static shapes (jit/vmap friendly);
shape-defining arguments (σ, window size, pyramid shapes) are static Python values.
"""

from ._derivatives import as_channels as as_channels
from ._derivatives import image_gradients as image_gradients
from ._distance import nearest_seed_distance as nearest_seed_distance
from ._distance import nearest_seed_points as nearest_seed_points
from ._distance import silhouette_sdf as silhouette_sdf
from ._filters import gaussian_blur as gaussian_blur
from ._filters import gaussian_blur_traced as gaussian_blur_traced
from ._filters import gaussian_kernel as gaussian_kernel
from ._median import median_filter as median_filter
from ._median import median_network as median_network
from ._pyramid import downsample as downsample
from ._pyramid import pyramid_shapes as pyramid_shapes
from ._pyramid import resize_bilinear as resize_bilinear
from ._pyramid import upsample_flow as upsample_flow
from ._sampling import sample_bilinear as sample_bilinear
from ._sampling import sample_bilinear_flat as sample_bilinear_flat
from ._sampling import warp_bilinear as warp_bilinear
from ._windows import crop_window as crop_window
from ._windows import full_to_window as full_to_window
from ._windows import paste_window as paste_window
from ._windows import paste_window_scaled as paste_window_scaled
from ._windows import sample_window as sample_window
from ._windows import window_to_full as window_to_full
