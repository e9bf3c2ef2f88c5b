"""Host edge of the region cue: input checks, crop and raster-plan choice, compiled-program reuse."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._exported import persistent_jit
from ...geometry import (
    Camera,
    KinematicModel,
    part_transforms,
    project_points,
    rigid_model,
    stack_cameras,
)
from ...render import Mesh, RasterPlan, replan
from ..flow import ROI_SIZES
from ._energy import RegionParams, region_params
from ._modality import RegionProblem, RegionResult, _refine_jit, densities_at_pose
from ._refine import RegionConfig, RegionState, initial_state

_densities_at_pose_jit = eqx.filter_jit(densities_at_pose)


def _as_rig(cameras: Camera) -> Camera:
    return cameras if cameras.K.ndim == 3 else stack_cameras([cameras])


def _projected_vertices_body(mesh: Mesh, cameras: Camera, model: KinematicModel, T_world_root, theta):
    """(C, V, 2) pixels and (C, V) depths of the posed mesh vertices in each camera (one compiled call:
    op by op this cost 2 s per tracker start and ~0.1 s per frame; kept on disk, `persistent_jit`)."""
    T_parts = part_transforms(model, T_world_root, theta)[mesh.vertex_part]
    p_world = jnp.einsum("vij,vj->vi", T_parts[:, :3, :3], mesh.vertices) + T_parts[:, :3, 3]
    return jax.vmap(lambda cam: project_points(cam, p_world.astype(cam.K.dtype)))(cameras)


_projected_vertices = persistent_jit(_projected_vertices_body)


def projected_boxes(mesh: Mesh, cameras: Camera, T_world_root, theta=None, model: KinematicModel | None = None) -> np.ndarray:
    """(C, 4) pixel boxes (x_min, y_min, x_max, y_max) of the projected mesh vertices per camera
    (NaN where no vertex is in front of the camera)."""
    rig = _as_rig(cameras)
    model = rigid_model(mesh.vertices.dtype) if model is None else model
    dtype = mesh.vertices.dtype
    theta = jnp.zeros((model.num_joints,), dtype) if theta is None else jnp.asarray(theta, dtype)
    px, z = _projected_vertices(mesh, rig, model, jnp.asarray(T_world_root, dtype), theta)
    px, z = np.asarray(px), np.asarray(z)
    boxes = []
    for c in range(px.shape[0]):
        front = px[c][z[c] > 0]
        if len(front) == 0:
            boxes.append([np.nan] * 4)
        else:
            boxes.append([front[:, 0].min(), front[:, 1].min(), front[:, 0].max(), front[:, 1].max()])
    return np.asarray(boxes)


def region_crop(boxes, image_shape: tuple[int, int], margin: int = 24, factor: int = 4, sizes=ROI_SIZES,
                keep: tuple[int, int] | None = None, shrink: float = 0.5, grow: float = 1.0):
    """One static crop size for all cameras and each camera's offset.

    Each box grows by `margin` on every side; the largest need over the cameras is rounded up to the
    next class of `sizes` (the flow cue's `ROI_SIZES`, capped at the image side) on each axis; the
    crop is centred on each box, kept inside the image and aligned to the density grid `factor`.

    `keep`: the crop size used last. It is kept while the need fits in it and is more than `shrink`
    of it on both axes, so an object whose size hovers near a class boundary does not switch
    between two compiled programs (each size class is one compilation of the caller's step). A new
    size is chosen for `grow` times the need, headroom for an object that keeps approaching.

    Returns:
        (offsets (C, 2) int32 (y0, x0), crop_shape (h, w)).

    Raises:
        ValueError: when a box is not finite (the object is behind a camera).
    """
    boxes = np.asarray(boxes, np.float64)
    if not np.all(np.isfinite(boxes)):
        raise ValueError("region_crop: the object is not in front of every camera (non-finite box)")
    H, W = image_shape
    if factor < 1:
        raise ValueError(f"region_crop: factor must be ≥ 1, got {factor}")

    def side(need, n):
        size = next((s for s in sizes if s >= need), int(need))
        return int(min(size, n))

    need_w = np.max(boxes[:, 2] - boxes[:, 0] + 1 + 2 * margin)
    need_h = np.max(boxes[:, 3] - boxes[:, 1] + 1 + 2 * margin)
    cw, ch = side(grow * need_w, W), side(grow * need_h, H)
    if keep is not None:
        kh, kw = keep
        if min(need_h, H) <= kh <= H and min(need_w, W) <= kw <= W and need_h > shrink * kh and need_w > shrink * kw:
            ch, cw = kh, kw
    cw, ch = cw - cw % factor, ch - ch % factor
    offsets = []
    for x0, y0, x1, y1 in boxes:
        sy = int(np.clip((y0 + y1) / 2 - ch / 2, 0, H - ch)) // factor * factor
        sx = int(np.clip((x0 + x1) / 2 - cw / 2, 0, W - cw)) // factor * factor
        offsets.append([sy, sx])
    return np.asarray(offsets, np.int32), (ch, cw)


class RegionRefiner:
    """Region-only pose refinement of one object seen by one or more cameras (host convenience).

    Picks the crop and raster plan from the initial pose, validates inputs, carries the
    `RegionState` from call to call (`self.state`) and re-plans the rasteriser on overflow. Calls with
    the same crop size class and plan share one compiled program.

    Args:
        mesh: the model mesh (parts in `vertex_part`); cameras: one `Camera` or a stacked rig.
        model: kinematic tree (rigid if None). config: `RegionConfig`; params: `RegionParams`
            (default: `region_params` for the first crop's size).
        margin: pixels of context around the projected model.
    """

    def __init__(self, mesh: Mesh, cameras: Camera, model: KinematicModel | None = None, config: RegionConfig | None = None,
                 params: RegionParams | None = None, margin: int = 24, cull_backfaces: bool = False):
        self.mesh, self.cameras = mesh, _as_rig(cameras)
        self.model = rigid_model(mesh.vertices.dtype) if model is None else model
        self.config = RegionConfig() if config is None else config
        self.params, self.margin = params, margin
        self.cull_backfaces = cull_backfaces
        self.plan: RasterPlan | None = None
        self.state: RegionState | None = None

    @property
    def num_cameras(self) -> int:
        return self.cameras.K.shape[0]

    def _replan(self, T, theta):
        self.plan = replan(self.plan, self.mesh, self.cameras, T, theta, self.model, 0, self.cull_backfaces)

    def check_images(self, images) -> np.ndarray:
        images = np.asarray(images)
        if images.ndim in (2, 3) and self.num_cameras == 1 and images.shape[:2] == (self.cameras.height, self.cameras.width):
            images = images[None]
        H, W = self.cameras.height, self.cameras.width
        if images.ndim not in (3, 4) or images.shape[0] != self.num_cameras or images.shape[1:3] != (H, W):
            raise ValueError(
                f"images must have shape ({self.num_cameras}, {H}, {W}[, 3]) for this rig, got {images.shape}"
            )
        if images.ndim == 4 and images.shape[-1] not in (1, 3):
            raise ValueError(f"images must have 1 or 3 channels, got {images.shape[-1]}")
        if not np.all(np.isfinite(images)):
            raise ValueError("images contain non-finite values")
        return images

    def _prepare(self, images, T, theta_init, params, name: str):
        """Checked inputs, the crop around the projected model and the parameters for its size class."""
        images = self.check_images(images)
        dtype = self.cameras.K.dtype
        T = np.asarray(T, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"{name} must be a finite (4, 4) pose, got shape {T.shape}")
        J = self.model.num_joints
        theta = np.zeros(J) if theta_init is None else np.asarray(theta_init, np.float64)
        if theta.shape != (J,) or not np.all(np.isfinite(theta)):
            raise ValueError(f"theta must be ({J},) finite joint angles, got shape {theta.shape}")
        f = self.config.density_factor
        T_j, th_j = jnp.asarray(T, dtype), jnp.asarray(theta, dtype)
        offsets, crop_shape = region_crop(
            projected_boxes(self.mesh, self.cameras, T_j, th_j, self.model), (self.cameras.height, self.cameras.width), self.margin, f
        )
        params = params if params is not None else self.params if self.params is not None else region_params(crop_shape, dtype)
        if self.plan is None:
            self._replan(T_j, th_j)
        if self.state is None:
            channels = (1 if images.ndim == 3 else images.shape[-1]) + int(self.config.texture)
            self.state = initial_state(self.num_cameras, self.cameras.height, self.cameras.width, channels, f, dtype)
        crops = np.stack([images[c, y0 : y0 + crop_shape[0], x0 : x0 + crop_shape[1]] for c, (y0, x0) in enumerate(offsets)])
        return T_j, th_j, offsets, crop_shape, params, jnp.asarray(crops, dtype)

    def learn(self, images, T_world_root, theta=None, params: RegionParams | None = None) -> None:
        """Learn the local densities of both regions at a known pose (`densities_at_pose`), as a tracker does
        on its first frame: the next call's first level-set iterations use them ("the first iterations of
        a new frame use the previous frame's densities", Section IV).

        Raises:
            ValueError: malformed images or pose, or an object behind a camera.
        """
        T_j, th_j, offsets, _, params, crops = self._prepare(images, T_world_root, theta, params, "T_world_root")
        problem = RegionProblem(self.mesh, self.model, self.cameras, self.plan, self.config)
        self.state = _densities_at_pose_jit(problem, crops, jnp.asarray(offsets), self.state, params, T_j, th_j)

    def __call__(self, images, T_init, theta_init=None, params: RegionParams | None = None) -> tuple[RegionResult, tuple]:
        """Refine the pose on one frame. Returns (`RegionResult`, (offsets (C, 2), crop_shape)).

        Raises:
            ValueError: malformed images or pose, or an object behind a camera.
        """
        T_j, th_j, offsets, crop_shape, params, crops = self._prepare(images, T_init, theta_init, params, "T_init")
        for _ in range(3):
            problem = RegionProblem(self.mesh, self.model, self.cameras, self.plan, self.config)
            result = _refine_jit(problem, crops, jnp.asarray(offsets), self.state, params, T_j, th_j)
            if int(result.status) != 7:  # Status.RENDER_OVERFLOW: re-plan from the final pose and redo
                break
            self._replan(result.T_world_root, result.theta)
        self.state = result.state
        return result, (offsets, crop_shape)

    def reset(self):
        """Forget the carried densities (e.g. after a tracking reset)."""
        self.state = None
