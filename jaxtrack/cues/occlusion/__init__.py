"""Model-based occlusion detection (Section III-C, eq. 9-10): appearance model, r(x) map, update."""

from ._appearance import AppearanceModel as AppearanceModel
from ._appearance import OcclusionConfig as OcclusionConfig
from ._appearance import OcclusionMap as OcclusionMap
from ._appearance import OcclusionParams as OcclusionParams
from ._appearance import TexelObservation as TexelObservation
from ._appearance import detect_occlusion as detect_occlusion
from ._appearance import init_appearance as init_appearance
from ._appearance import model_image as model_image
from ._appearance import observe_texels as observe_texels
from ._appearance import occlusion_params as occlusion_params
from ._appearance import update_appearance as update_appearance
from ._atlas import TextureAtlas as TextureAtlas
from ._atlas import make_texture_atlas as make_texture_atlas
from ._atlas import texel_index as texel_index
from ._histogram import patch_histogram_distance as patch_histogram_distance
from ._histogram import to_gray as to_gray
