"""The sparse region modality: the region energy on correspondence lines (PWP3D / RBOT / SRT3D / M3T).

- `_viewmodel`: contour points of the model, precomputed from 10 · 4^s + 2 directions (`SparseViewModel`,
  `build_view_model`, `load_or_build_view_model`, `nearest_view`) or taken from a render per frame
  (`contour_points_from_render`, for articulated objects);
- `_histograms`: global RGB colour histograms of object and background (`ColourHistograms`);
- `_lines`: lines along the projected contour normals, segment posteriors, the contour distribution and
  its moments, and one edge row per line for `jaxtrack.solve.solve_pose` (`line_rows`,
  `refine_pose_lines`).

See ../shared/DESIGN.md, "The region energy on correspondence lines".
"""

from ._histograms import ColourHistograms as ColourHistograms
from ._histograms import LogOddsTable as LogOddsTable
from ._histograms import colour_index as colour_index
from ._histograms import histogram_from_colours as histogram_from_colours
from ._histograms import image_colours as image_colours
from ._histograms import learn_histograms as learn_histograms
from ._histograms import log_odds_image as log_odds_image
from ._histograms import log_odds_of_cells as log_odds_of_cells
from ._histograms import log_odds_table as log_odds_table
from ._histograms import pixel_posteriors as pixel_posteriors
from ._histograms import posterior_image as posterior_image
from ._histograms import posterior_of_cells as posterior_of_cells
from ._histograms import uniform_histograms as uniform_histograms
from ._histograms import update_histograms as update_histograms
from ._lines import LineConfig as LineConfig
from ._lines import LineMeasurements as LineMeasurements
from ._lines import LineParams as LineParams
from ._lines import LineRefinement as LineRefinement
from ._lines import LineSamples as LineSamples
from ._lines import ProjectedPoints as ProjectedPoints
from ._lines import contour_distribution as contour_distribution
from ._lines import distribution_moments as distribution_moments
from ._lines import learn_line_histograms as learn_line_histograms
from ._lines import line_learning_pixels as line_learning_pixels
from ._lines import line_params as line_params
from ._lines import line_rows as line_rows
from ._lines import measure_lines as measure_lines
from ._lines import min_expected_variance as min_expected_variance
from ._lines import project_contour as project_contour
from ._lines import refine_pose_lines as refine_pose_lines
from ._lines import rows_from_measurements as rows_from_measurements
from ._lines import sample_lines as sample_lines
from ._lines import schedule as schedule
from ._lines import segment_log_odds as segment_log_odds
from ._lines import smoothed_step as smoothed_step
from ._lines import unoccluded as unoccluded
from ._modality import LineRegion as LineRegion
from ._modality import LineState as LineState
from ._viewmodel import ContourPoints as ContourPoints
from ._viewmodel import SparseViewModel as SparseViewModel
from ._viewmodel import build_view_model as build_view_model
from ._viewmodel import camera_direction as camera_direction
from ._viewmodel import contour_points_from_render as contour_points_from_render
from ._viewmodel import default_cache_dir as default_cache_dir
from ._viewmodel import icosphere as icosphere
from ._viewmodel import load_or_build_view_model as load_or_build_view_model
from ._viewmodel import load_view_model as load_view_model
from ._viewmodel import nearest_view as nearest_view
from ._viewmodel import points_for_pose as points_for_pose
from ._viewmodel import save_view_model as save_view_model
from ._viewmodel import view_model_build_progress as view_model_build_progress
from ._viewmodel import view_model_path as view_model_path
from ._viewmodel import view_points as view_points
