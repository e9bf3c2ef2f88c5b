"""JAX rasteriser: silhouette, depth, face id, surface points, visibility, signed distance."""

from ..image import nearest_seed_distance as nearest_seed_distance  # Φ0 lives with the image ops
from ..image import silhouette_sdf as silhouette_sdf
from ._mesh import Mesh as Mesh
from ._mesh import box_mesh as box_mesh
from ._mesh import hides_its_back_faces as hides_its_back_faces
from ._mesh import is_closed as is_closed
from ._mesh import make_mesh as make_mesh
from ._mesh import torus_mesh as torus_mesh
from ._raster import PATCH_SIZES as PATCH_SIZES
from ._raster import TILE_SIZE as TILE_SIZE
from ._raster import RasterPlan as RasterPlan
from ._raster import Renderer as Renderer
from ._raster import RenderOutput as RenderOutput
from ._raster import dense_is_cheaper as dense_is_cheaper
from ._raster import face_extents as face_extents
from ._raster import merge_plans as merge_plans
from ._raster import plan_raster as plan_raster
from ._raster import render as render
from ._raster import replan as replan
from ._raster import tile_demand as tile_demand
