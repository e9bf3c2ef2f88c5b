"""The region cue (Section IV, eq. 11-15): level-set segmentation with local Gaussian densities and
a shape prior, shape matching of the contours, and region-only pose refinement."""

from ...geometry import crop_camera as crop_camera  # the crop geometry lives in geometry; kept here for old imports
from ._densities import LocalDensities as LocalDensities
from ._densities import data_term as data_term
from ._densities import local_densities as local_densities
from ._densities import log_likelihoods as log_likelihoods
from ._energy import RegionParams as RegionParams
from ._energy import dirac as dirac
from ._energy import evolve as evolve
from ._energy import heaviside as heaviside
from ._energy import levelset_energy as levelset_energy
from ._energy import levelset_update as levelset_update
from ._energy import region_membership as region_membership
from ._energy import region_memberships as region_memberships
from ._energy import region_params as region_params
from ._energy import time_step as time_step
from ._features import feature_channels as feature_channels
from ._features import smoothed_features as smoothed_features
from ._features import texture_channel as texture_channel
from ._host import RegionRefiner as RegionRefiner
from ._host import projected_boxes as projected_boxes
from ._host import region_crop as region_crop
from ._matching import closest_point_matches as closest_point_matches
from ._matching import closest_point_matches_at as closest_point_matches_at
from ._matching import regularised_matches as regularised_matches
from ._matching import zero_level_points as zero_level_points
from ._modality import LevelSetCarry as LevelSetCarry
from ._modality import LevelSetFrame as LevelSetFrame
from ._modality import LevelSetRegion as LevelSetRegion
from ._modality import RegionProblem as RegionProblem
from ._modality import RegionResult as RegionResult
from ._modality import densities_at_pose as densities_at_pose
from ._modality import refine_pose_region as refine_pose_region
from ._redistance import band_sdf as band_sdf
from ._redistance import contour_pixels as contour_pixels
from ._redistance import nearest_seed_points as nearest_seed_points
from ._redistance import redistance as redistance
from ._refine import RegionConfig as RegionConfig
from ._refine import RegionState as RegionState
from ._refine import contour_matches as contour_matches
from ._refine import initial_state as initial_state
from ._refine import segment as segment
from ._refine import silhouette_contour as silhouette_contour
