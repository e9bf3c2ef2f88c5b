"""Model-based occlusion detection with an appearance model on the surface (Section III-C, eq. 9-10).

The appearance model f(X) is a grey texture over the mesh (`TextureAtlas`). At frame t, with the pose
χ_t known, the model is rendered into each camera (the model image M(x) = f(X(x))); for every object
pixel x the grey histograms of M and of the image I over a window around x are compared,
d = ½ Σ_b |p_M,b − p_I,b| ∈ [0, 1] (eq. 9), and x is occluded when d > 1/4. The flow cue gets
r(x) = 0 there and 1 elsewhere; the SIFT cue drops keypoints there. The model is then updated where
not occluded, f_t = (1 − 1/8) f_{t−1} + 1/8 I (eq. 10); texels seen for the first time take I.
Texels never seen are unknown: they neither vote in the histograms nor count as occluded.

Both histograms see the image through the same surface sampling: the image is read at the texel
centres (`observe_texels`) and shown at the pixels through the same texel lookup as the model, so an
unchanged surface gives d = 0 exactly and only appearance changes (an occluder, lighting) raise d.

Everything here is pure JAX on static shapes; thresholds and rates are arrays (`OcclusionParams`),
so sweeping or differentiating them does not recompile. Cameras sit on a leading axis.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._device import to_device
from ...geometry import Camera, KinematicModel, part_point_columns, part_transforms, rigid_model
from ...image import gaussian_blur, sample_bilinear_flat
from ...render import RenderOutput
from ._atlas import TextureAtlas, texel_index
from ._histogram import box_sum, local_gain, patch_histogram_distance, to_gray


class OcclusionParams(eqx.Module):
    """Thresholds and rates of eq. 9-10 as arrays (vmappable, differentiable, no recompilation).

    Attributes:
        threshold: occluded when d > threshold (paper: 1/4).
        rate: appearance update rate (paper: 1/8).
        min_known: least fraction of a window's pixels with a known model appearance for a decision.
        min_cos: least |cos| of the angle between the surface normal and the viewing ray for an
            observation to update the model: texels seen only at grazing angles (a face turning
            into view) stay unknown instead of being filled with smeared values.
        max_gain: bound of the local brightness gain between model and image (≥ 1; 1 switches the
            compensation off). Shading changes as the surface turns against the light, and texels
            hidden for a while miss the updates that would have followed it; a gain within
            [1/max_gain, max_gain] absorbs that but not the difference to most occluders.
    """

    threshold: jax.Array
    rate: jax.Array
    min_known: jax.Array
    min_cos: jax.Array
    max_gain: jax.Array


def occlusion_params(
    threshold=0.25, rate=0.125, min_known=0.25, min_cos=0.3, max_gain=1.25, dtype=jnp.float32
) -> OcclusionParams:
    """`OcclusionParams` with the paper's values by default.

    Raises:
        ValueError: naming a parameter outside its domain.
    """
    bounded = (("threshold", threshold), ("rate", rate), ("min_known", min_known), ("min_cos", min_cos))
    for name, value, lo, hi in ((n, v, 0.0, 1.0) for n, v in bounded):
        if not lo <= float(value) <= hi:
            raise ValueError(f"occlusion_params: {name} must lie in [{lo}, {hi}], got {value}")
    if not float(max_gain) >= 1.0:
        raise ValueError(f"occlusion_params: max_gain must be ≥ 1, got {max_gain}")
    return OcclusionParams(*(to_device(x, dtype) for x in (threshold, rate, min_known, min_cos, max_gain)))


class OcclusionConfig(eqx.Module):
    """Static settings (they shape the compiled program).

    Attributes:
        bins: grey histogram bins.
        window: odd side of the square patch (pixels).
        depth_tolerance: relative depth slack of the texel visibility test in the update.
        edge_margin: observations closer than this (pixels) to the silhouette edge do not update the
            model (the blurred image mixes in the background there).
        init_margin: pixels around detected occlusions where unseen texels wait to be initialised.
        gain_window: odd side of the window of the local gain estimate (pixels).
        blur_sigma: Gaussian σ (pixels) applied to the image before it is read at the texels; it
            removes aliasing and pixel noise that the averaging model (eq. 10) does not have, which
            would otherwise widen the image's histograms against the model's.
    """

    bins: int = eqx.field(static=True, default=8)
    window: int = eqx.field(static=True, default=9)
    depth_tolerance: float = eqx.field(static=True, default=5e-3)
    edge_margin: int = eqx.field(static=True, default=2)
    init_margin: int = eqx.field(static=True, default=16)
    gain_window: int = eqx.field(static=True, default=31)
    blur_sigma: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        if self.bins < 2:
            raise ValueError(f"OcclusionConfig.bins must be ≥ 2, got {self.bins}")
        for name in ("window", "gain_window"):
            value = getattr(self, name)
            if value < 1 or value % 2 == 0:
                raise ValueError(f"OcclusionConfig.{name} must be a positive odd number, got {value}")


class AppearanceModel(eqx.Module):
    """The appearance model f(X) (state carried from frame to frame).

    Attributes:
        texture: (T,) grey value per texel (0-255).
        seen: (T,) bool texel has been observed (unknown otherwise).
    """

    texture: jax.Array
    seen: jax.Array


def init_appearance(atlas: TextureAtlas, dtype=jnp.float32) -> AppearanceModel:
    """An empty model: every texel unknown. The first `update_appearance` (at the known initial pose)
    fills what it sees."""
    return AppearanceModel(jnp.zeros((atlas.num_texels,), dtype), jnp.zeros((atlas.num_texels,), bool))


class OcclusionMap(eqx.Module):
    """Per-pixel result for one camera (a leading C axis for a rig).

    Attributes:
        distance: (H, W) histogram distance d (eq. 9), 0 off the object.
        occluded: (H, W) bool object pixel with d > threshold and enough known model pixels around it.
        data_weight: (H, W) r(x): 0 where occluded, 1 elsewhere (the flow cue's `data_weight`).
        model_image: (H, W) the model's grey appearance M(x) (0 where unknown or off the object).
        known: (H, W) bool object pixel whose texel has been seen.
        visible: (H, W) bool non-occluded object pixels (the SIFT cue's detection mask).
        near_occlusion: (H, W) bool within `init_margin` pixels of an occluded pixel: unseen texels
            are not initialised there (a face turning into view behind an occluder would otherwise
            learn the occluder as its appearance; it still counts as unknown, not occluded).
    """

    distance: jax.Array
    occluded: jax.Array
    data_weight: jax.Array
    model_image: jax.Array
    known: jax.Array
    visible: jax.Array
    near_occlusion: jax.Array


class TexelObservation(eqx.Module):
    """The image read at every texel centre of the mesh at the current pose (one camera; a leading C
    axis for a rig).

    Attributes:
        value: (T,) grey value (bilinear) at the texel's projection.
        visible: (T,) bool texel in front of the depth buffer, inside the image and inside its triangle.
        reliable: (T,) bool visible, not at a grazing angle and away from the silhouette edge: may
            update the model.
        pixel: (T,) int32 flat index (row · W + column) of the pixel nearest the projection.
    """

    value: jax.Array
    visible: jax.Array
    reliable: jax.Array
    pixel: jax.Array


def _observe_one(atlas, image, depth, camera, T_world_parts, params, config):
    T_cam_parts = camera.T_cam_world @ T_world_parts  # (P, 4, 4)
    p, n = atlas.texel_p_model, atlas.texel_normal
    # Per coordinate columns: XLA:CPU reduces over a minor axis of 3 with a slow strided loop.
    p_cam = part_point_columns(T_cam_parts, atlas.texel_part, p[:, 0], p[:, 1], p[:, 2])
    zero = jnp.zeros((), p.dtype)  # a direction: the rotation alone
    T_rot = T_cam_parts.at[:, :3, 3].set(zero)
    n_cam = part_point_columns(T_rot, atlas.texel_part, n[:, 0], n[:, 1], n[:, 2])
    z = p_cam[2]
    safe_z = jnp.where(z > 1e-6, z, 1e-6)
    K = camera.K
    x, y = p_cam[0] / safe_z, p_cam[1] / safe_z
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    h, w = depth.shape
    ui = jnp.clip(jnp.round(u).astype(jnp.int32), 0, w - 1)
    vi = jnp.clip(jnp.round(v).astype(jnp.int32), 0, h - 1)
    pixel = vi * w + ui
    gray = gaussian_blur(to_gray(image).astype(z.dtype)[..., None], config.blur_sigma)[..., 0]
    # Reads of the (H, W) maps at the texels through flat indices (`sample_bilinear_flat`, `take`): XLA:CPU's
    # two-index gathers with these computed indices ran several times slower (README, "Per-part transforms gathered
    # by entry, texels read through flat indices").
    value, inside = sample_bilinear_flat(gray, u, v)
    depth_at = jnp.take(depth.reshape(-1), pixel, mode="clip")  # +inf off the object: such texels are hidden behind the silhouette edge
    visible = inside & (z > 1e-6) & jnp.isfinite(depth_at) & (z <= depth_at * (1 + config.depth_tolerance) + 1e-3)
    visible = visible & atlas.texel_live
    # |cos| of the viewing angle (two-sided: open meshes show their inside too).
    distance = jnp.sqrt(p_cam[0] ** 2 + p_cam[1] ** 2 + p_cam[2] ** 2)
    cos = jnp.abs(n_cam[0] * p_cam[0] + n_cam[1] * p_cam[1] + n_cam[2] * p_cam[2]) / jnp.maximum(distance, 1e-9)
    side = 2 * config.edge_margin + 1
    interior = box_sum(jnp.isfinite(depth).astype(z.dtype)[..., None], config.edge_margin)[..., 0] >= side * side - 0.5
    reliable = visible & (cos >= params.min_cos) & jnp.take(interior.reshape(-1), pixel, mode="clip")
    return TexelObservation(value, visible, reliable, pixel)


def observe_texels(
    atlas: TextureAtlas,
    images,
    depth,
    cameras: Camera,
    T_world_root,
    params: OcclusionParams,
    theta=None,
    model: KinematicModel | None = None,
    config: OcclusionConfig | None = None,
) -> TexelObservation:
    """Read frames t at the texel centres projected with the pose χ_t, per camera. Jittable.

    Args:
        atlas: texture layout of the mesh.
        images: (C, H, W) grey or (C, H, W, 3) RGB frames (0-255).
        depth: (C, H, W) rendered depth at χ_t (+inf off the object), for the visibility test.
        cameras: stacked rig (C on the leading axis).
        T_world_root: (4, 4) root pose; theta: (J,) joint angles; model: kinematic tree (rigid if None).
        params: `min_cos` decides which observations are reliable enough to update the model.

    Returns:
        `TexelObservation` with a leading C axis.
    """
    config = OcclusionConfig() if config is None else config
    dtype = atlas.texel_p_model.dtype
    model = rigid_model(dtype) if model is None else model
    T_world_root = jnp.asarray(T_world_root, dtype)
    theta = jnp.zeros((model.num_joints,), dtype) if theta is None else jnp.asarray(theta, dtype)
    T_world_parts = part_transforms(model, T_world_root, theta)
    return jax.vmap(lambda img, dep, cam: _observe_one(atlas, img, dep, cam, T_world_parts, params, config))(
        images, depth, cameras
    )


def model_image(atlas: TextureAtlas, appearance: AppearanceModel, rendered: RenderOutput):
    """M(x) = f(X(x)) for one camera: (H, W) grey values and (H, W) bool known."""
    covered = rendered.face_id >= 0
    idx = texel_index(atlas, rendered.face_id, rendered.p_model)
    known = covered & appearance.seen[idx]
    return jnp.where(known, appearance.texture[idx], 0.0), known


class _DetectionInputs(eqx.Module):
    """One camera's inputs to the histogram test (all (H, W)): M(x), the image through the same texel lookup, and
    where a decision can be made."""

    covered: jax.Array
    known: jax.Array
    model: jax.Array
    image: jax.Array
    valid: jax.Array
    groups: jax.Array


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces (eqx.debug.get_num_traces); never fails
def _detection_inputs(atlas, appearance, observation, rendered) -> _DetectionInputs:
    covered = rendered.face_id >= 0
    idx = texel_index(atlas, rendered.face_id, rendered.p_model)
    known = covered & appearance.seen[idx]
    model = jnp.where(known, appearance.texture[idx], 0.0)
    # The image seen through the same texel lookup as the model (see the module docstring).
    seen_now = covered & observation.visible[idx]
    image = jnp.where(seen_now, observation.value[idx], 0.0).astype(model.dtype)
    # Gains per group of similar surface normals (6 groups: the dominant signed model-frame axis).
    normal = atlas.texel_normal[idx]
    axis = jnp.argmax(jnp.abs(normal), -1)
    negative = jnp.take_along_axis(normal, axis[..., None], -1)[..., 0] < 0
    groups = (2 * axis + negative).astype(jnp.int32)
    return _DetectionInputs(covered, known, model, image, known & seen_now, groups)


def _decide_one(inputs: _DetectionInputs, gain_mask, params, config):
    """(H, W) histogram distance d (eq. 9) with the gains fitted on `gain_mask`, and (H, W) bool occluded."""
    gain = local_gain(inputs.model, inputs.image, gain_mask, config.gain_window, params.max_gain, inputs.groups, 6)
    d, count = patch_histogram_distance(inputs.model * gain, inputs.image, inputs.valid, config.bins, config.window)
    enough = count >= params.min_known * config.window**2
    return d, inputs.covered & enough & (d > params.threshold)


def detect_occlusion(
    atlas: TextureAtlas,
    appearance: AppearanceModel,
    observation: TexelObservation,
    rendered: RenderOutput,
    params: OcclusionParams,
    config: OcclusionConfig | None = None,
) -> OcclusionMap:
    """Occlusion maps of C cameras at the current pose (eq. 9). Jittable (inline it in a tracker step).

    Two passes: the gains of the second ignore the pixels the first found occluded. Where the first finds
    nothing in any camera, the second would repeat it exactly; it is skipped (`lax.cond` over all cameras,
    outside the per-camera vmap: under an outer vmap, e.g. a weight sweep, both branches run and the result
    is the same).

    Args:
        atlas: texture layout of the mesh.
        appearance: the model f_{t−1}.
        observation: `observe_texels` of frames t at χ_t (leading C axis).
        rendered: the mesh rendered at χ_t in each camera, stacked on a leading C axis.
        params, config: thresholds/rate (arrays) and static settings (default `OcclusionConfig()`).

    Returns:
        `OcclusionMap` with a leading C axis.
    """
    config = OcclusionConfig() if config is None else config
    inputs = jax.vmap(lambda obs, ren: _detection_inputs(atlas, appearance, obs, ren))(observation, rendered)
    decide = jax.vmap(lambda x, mask: _decide_one(x, mask, params, config))
    first_d, first = decide(inputs, inputs.valid)
    d, occluded = jax.lax.cond(jnp.any(first), lambda: decide(inputs, inputs.valid & ~first), lambda: (first_d, first))
    dtype = inputs.model.dtype
    return OcclusionMap(
        distance=jnp.where(inputs.covered, d, 0.0),
        occluded=occluded,
        data_weight=jnp.where(occluded, 0.0, 1.0).astype(dtype),
        model_image=inputs.model,
        known=inputs.known,
        visible=inputs.covered & ~occluded,
        near_occlusion=jax.vmap(lambda o: box_sum(o.astype(dtype)[..., None], config.init_margin)[..., 0] > 0.5)(occluded),
    )


def update_appearance(
    appearance: AppearanceModel, observation: TexelObservation, occluded, params: OcclusionParams, hold_new=None
) -> AppearanceModel:
    """f_t = (1 − rate) f_{t−1} + rate · I where visible and not occluded (eq. 10); untouched elsewhere.

    Texels seen for the first time take I. With several cameras a texel takes the mean of the
    cameras that see it unoccluded. Jittable.

    Args:
        appearance: the model f_{t−1}.
        observation: `observe_texels` of frames t at χ_t (leading C axis).
        occluded: (C, H, W) bool from `detect_occlusion` (all False for the initialising frame).
        params: `rate` is used.
        hold_new: optional (C, H, W) bool where unseen texels are not initialised yet
            (`OcclusionMap.near_occlusion`).
    """

    def at_texels(image_map):
        return jnp.take_along_axis(image_map.reshape(image_map.shape[0], -1), observation.pixel, axis=1)

    usable = observation.reliable & ~at_texels(occluded)
    if hold_new is not None:
        usable = usable & (appearance.seen[None, :] | ~at_texels(hold_new))
    n = jnp.sum(usable, 0)
    observed = n > 0
    mean = jnp.sum(jnp.where(usable, observation.value, 0.0), 0) / jnp.maximum(n, 1)
    dtype = appearance.texture.dtype
    blended = jnp.where(appearance.seen, (1 - params.rate) * appearance.texture + params.rate * mean, mean)
    return AppearanceModel(
        texture=jnp.where(observed, blended, appearance.texture).astype(dtype), seen=appearance.seen | observed
    )
