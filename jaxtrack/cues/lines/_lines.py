"""Correspondence lines: the region energy of PWP3D/RBOT/SRT3D/M3T on short lines across the contour.

At the current pose every contour point X of the model (from the nearest view of a
`SparseViewModel`, or from a render: `ContourPoints`) projects to a centre c with an outward unit
normal n (the projection of X's 3D contour normal). A line through c along n is read from the image
pixel by pixel, one pixel per step along the line's dominant axis (so every pixel is read once; a step
covers 1/|n_dom| px along n), in `num_segments` = F + D − 1 segments of `scale` pixels, from inside to
outside (M3T: F = 8, D = 12, 19 segments). The line is snapped to the pixel grid along the dominant
axis; `delta_r` is where the grid line's centre lies along n, relative to c.

Per segment the foreground posterior is the product of its pixels' posteriors, normalised against the
background one (M3T), here a sum of per-pixel log-odds log(h_f/h_b) passed through a sigmoid.
Where along the line the contour lies is a discrete distribution over the D segment boundaries in the
middle of the line: for the boundary d, the product over the F segments d..d+F−1 of
p_f · h_f(x_j) + p_b · (1 − h_f(x_j)), with the smoothed step h_f(x) = ½ − α tanh(x / 2s), x_j = j − (F−1)/2
(M3T: amplitude α = 0.43, slope s = 0.5), normalised. Its mean and variance (in segments, the
variance clamped below at M3T's minimal expected variance max(1/(2 atanh(2α)²), s)) give the observed
contour position along the line, in pixels: delta_r + mean · scale / |n_dom|.

One edge row per valid line goes to the pose solver (`jaxtrack.solve`): the observed position as the
pixel, X as the model point, n as the edge normal (the residual is measured across the edge only),
and M3T's weight min_var / (σ² · var) per px² (σ: the round's standard deviation in px), converted to
mm² at the point's depth. With only these rows, Gauss-Newton on them is M3T's "global" optimisation
step (the mean/variance Gaussian approximation of each line's distribution).

Lines are valid when the point is valid and in front of the camera, every pixel of the line lies in
the image, and the line stays on its side of the contour for at least `min_continuous_distance`
segments both ways (M3T's continuous distance, from the view model's foreground/background distances).

Multi-scale: round r uses scales[min(r, len − 1)] and standard_deviations[min(r, len − 1)]
(`schedule`). The number of segments and the buffer length (num_segments · `LineConfig.max_scale`
pixels) are static; the scale itself is a traced integer ≤ max_scale, so one compiled program serves
every round (pixels beyond num_segments · scale are masked out).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._device import to_device
from ...geometry import Camera, KinematicModel, part_transforms, project_points, rigid_model, transform_points
from ...solve import Correspondences, Cue, SolverConfig, correspondences_from_pixels, solve_pose
from ._histograms import ColourHistograms, LogOddsTable, colour_index, learn_histograms, log_odds_of_cells
from ._viewmodel import ContourPoints, SparseViewModel, points_for_pose


class LineConfig(eqx.Module):
    """Static settings: they shape the compiled program.

    Attributes:
        function_length: F, segments of the smoothed step function (M3T: 8; even).
        distribution_length: D, positions of the contour distribution (M3T: 12).
        max_scale: longest segment in pixels any round uses (the line buffer holds
            (F + D − 1) · max_scale pixels; M3T's RBOT setting: 5, its default: 6).
        learn_length: pixels per side and line read for the histograms (M3T: 20 px).
    """

    function_length: int = eqx.field(static=True, default=8)
    distribution_length: int = eqx.field(static=True, default=12)
    max_scale: int = eqx.field(static=True, default=5)
    learn_length: int = eqx.field(static=True, default=20)

    def __check_init__(self):
        if self.function_length < 2 or self.function_length % 2:
            raise ValueError(f"LineConfig.function_length must be even and ≥ 2, got {self.function_length}")
        if self.distribution_length < 2 or self.max_scale < 1 or self.learn_length < 1:
            raise ValueError("LineConfig: distribution_length ≥ 2, max_scale ≥ 1 and learn_length ≥ 1 required")

    @property
    def num_segments(self) -> int:
        return self.function_length + self.distribution_length - 1

    @property
    def max_pixels(self) -> int:
        return self.num_segments * self.max_scale


# Defaults as module-level instances (a call in a signature would run at import anyway).
DEFAULT_LINE_CONFIG = LineConfig()
M3T_SOLVER = SolverConfig(max_steps=2)  # M3T: 2 update iterations per correspondence iteration


class LineParams(eqx.Module):
    """Parameters as arrays (vmappable, differentiable; changing them does not recompile).

    Attributes:
        function_amplitude: α of the smoothed step (M3T: 0.43; < ½).
        function_slope: s of the smoothed step in segments (M3T: 0.5; 0: a hard step).
        min_continuous_distance: segments the line must stay on each side of the contour (M3T: 3).
        posterior_prior: ε added to both histograms in the pixel posteriors.
        weight: factor on every row's weight.
        unconsidered_line_length: px next to the contour left out of the histograms (M3T: 0.5).
        max_considered_line_length: px per side read for the histograms (M3T: 20; ≤ learn_length).
        model_occlusion_threshold: mm: a line is hidden when something else known (another tracked object,
            `occluder_depth` of `measure_lines`) lies nearer than the contour point by more than this (M3T's
            model occlusions: 0.03 m).
    """

    function_amplitude: jax.Array
    function_slope: jax.Array
    min_continuous_distance: jax.Array
    posterior_prior: jax.Array
    weight: jax.Array
    unconsidered_line_length: jax.Array
    max_considered_line_length: jax.Array
    model_occlusion_threshold: jax.Array


def line_params(
    dtype=jnp.float32,
    function_amplitude=0.43,
    function_slope=0.5,
    min_continuous_distance=3.0,
    posterior_prior=1e-7,
    weight=1.0,
    unconsidered_line_length=0.5,
    max_considered_line_length=20.0,
    model_occlusion_threshold=30.0,
) -> LineParams:
    """`LineParams` with M3T's defaults as arrays of `dtype`."""
    a = lambda x: to_device(x, dtype)
    return LineParams(
        a(function_amplitude), a(function_slope), a(min_continuous_distance), a(posterior_prior), a(weight),
        a(unconsidered_line_length), a(max_considered_line_length), a(model_occlusion_threshold),
    )


def unoccluded(center, depth, occluder_depth, threshold):
    """(N,) bool: no known occluder in front of the contour points (M3T's model occlusions). Jittable.

    Args:
        center: (N, 2) pixels (x, y) of the points in the image of `occluder_depth`.
        depth: (N,) the points' camera-frame z (mm).
        occluder_depth: (H, W) depth (mm) of everything else known in the scene (the other tracked objects,
            min-filtered over a few pixels on the host), inf where nothing is.
        threshold: mm a occluder must lie in front of a point to hide it.
    """
    h, w = occluder_depth.shape
    ix = jnp.clip(jnp.floor(center[:, 0] + 0.5), 0, w - 1).astype(jnp.int32)
    iy = jnp.clip(jnp.floor(center[:, 1] + 0.5), 0, h - 1).astype(jnp.int32)
    d = occluder_depth[iy, ix].astype(depth.dtype)
    return ~(d < depth - threshold)


class ProjectedPoints(eqx.Module):
    """Contour points at a pose in one camera.

    Attributes:
        center: (N, 2) projected points (distorted pixels, as in the image).
        normal: (N, 2) unit outward image normal.
        depth: (N,) camera-frame z (mm).
        valid: (N,) bool: a valid point in front of the camera with a defined normal.
    """

    center: jax.Array
    normal: jax.Array
    depth: jax.Array
    valid: jax.Array


class LineSamples(eqx.Module):
    """The pixels of N lines (buffer of M = num_segments · max_scale pixels, inside → outside).

    Attributes:
        pixel: (N, M, 2) int32 (x, y) pixels read.
        colour: (N, M, 3) their colours, in the image's dtype (uint8 for 8-bit frames).
        mask: (N, M) bool, pixel k < num_segments · scale.
        delta_r: (N,) position (px along the normal, relative to the centre) of the line's middle.
        step: (N,) px along the normal per pixel of the line (1/|n_dom|).
        inside: (N,) bool, the whole line lies in the image.
    """

    pixel: jax.Array
    colour: jax.Array
    mask: jax.Array
    delta_r: jax.Array
    step: jax.Array
    inside: jax.Array


class LineMeasurements(eqx.Module):
    """What the lines say about where the contour is.

    Attributes:
        center, normal, depth: (N, 2), (N, 2), (N,) the projected points (`ProjectedPoints`).
        valid: (N,) bool usable lines.
        distribution: (N, D) probability of the contour at each of the D boundaries.
        mean: (N,) contour position along the normal relative to the centre (px).
        variance: (N,) its variance (px²), clamped below (see the module docstring).
        variance_segments: (N,) the variance in segments² (M3T's measured variance).
        p_model: (N, 3), part: (N,) the contour points.
    """

    center: jax.Array
    normal: jax.Array
    depth: jax.Array
    valid: jax.Array
    distribution: jax.Array
    mean: jax.Array
    variance: jax.Array
    variance_segments: jax.Array
    p_model: jax.Array
    part: jax.Array


# ------------------------------------------------------------------------------------------ geometry


def _world_transforms(T_world_root, points: ContourPoints, model: KinematicModel | None, theta):
    """(N, 4, 4) pose of each point's part, or (4, 4) for a rigid object."""
    if model is None or model.num_parts == 1:
        return T_world_root
    theta = jnp.zeros((model.num_joints,), T_world_root.dtype) if theta is None else theta
    return part_transforms(model, T_world_root, theta)[points.part]


def project_contour(
    camera: Camera, T_world_root, points: ContourPoints, model: KinematicModel | None = None, theta=None
) -> ProjectedPoints:
    """Project contour points and their normals at a pose into one camera. Jittable.

    The image normal is the derivative of the projection along the 3D normal (normalised), or the
    points' `normal_image` where no 3D normal is known.

    Args:
        camera: a single camera; T_world_root: (4, 4) root pose (model → world).
        points: N contour points; model, theta: the kinematic tree and (J,) joints (rigid if None).
    """
    dtype = camera.K.dtype
    T = _world_transforms(jnp.asarray(T_world_root, dtype), points, model, theta)
    p_world = transform_points(T, points.p_model.astype(dtype))
    R = T[..., :3, :3]
    n_world = jnp.einsum("...ij,...j->...i", R, points.normal.astype(dtype))
    (px, z), (dpx, _) = jax.jvp(lambda p: project_points(camera, p), (p_world,), (n_world,))
    has3d = jnp.sum(points.normal**2, axis=-1) > 0
    n2 = jnp.where(has3d[:, None], dpx, points.normal_image.astype(dtype))
    length = jnp.linalg.norm(n2, axis=-1)
    ok = length > 1e-9
    n2 = n2 / jnp.where(ok, length, 1.0)[:, None]
    valid = points.valid & (z > 1e-3) & ok & jnp.all(jnp.isfinite(px), axis=-1)
    return ProjectedPoints(center=px, normal=n2, depth=z, valid=valid)


def _scale(scale, config: LineConfig):
    """The segment length as int32, clamped to [1, config.max_scale] (the line buffer's limit)."""
    return jnp.clip(jnp.asarray(scale, jnp.int32), 1, config.max_scale)


def sample_lines(image, center, normal, scale, config: LineConfig = DEFAULT_LINE_CONFIG) -> LineSamples:
    """Read N lines of num_segments · scale pixels through `center` (N, 2) along `normal` (N, 2). Jittable.

    Pixel k (k = 0..M−1) of a line: along its dominant axis (x if |n_y| < |n_x|, else y) at
    u_k = u_0 + sign(n_dom) · k with u_0 = round(c_dom − sign(n_dom) · (L − 1)/2), L = num_segments · scale,
    and on the other axis at round(c_minor + (u_k − c_dom) · n_minor / n_dom) (round: floor(· + ½)).

    Args:
        image: (H, W, 3) colours.
        center, normal: (N, 2) line centres (x, y) and unit normals.
        scale: pixels per segment, int (traced is fine), clamped to [1, config.max_scale].
    """
    h, w = image.shape[:2]
    dtype = center.dtype
    L = (config.num_segments * _scale(scale, config)).astype(dtype)
    x_dom = jnp.abs(normal[:, 1]) < jnp.abs(normal[:, 0])
    n_dom = jnp.where(x_dom, normal[:, 0], normal[:, 1])
    n_min = jnp.where(x_dom, normal[:, 1], normal[:, 0])
    c_dom = jnp.where(x_dom, center[:, 0], center[:, 1])
    c_min = jnp.where(x_dom, center[:, 1], center[:, 0])
    sign = jnp.where(n_dom >= 0, 1.0, -1.0).astype(dtype)
    u0 = jnp.floor(c_dom - sign * (L - 1) / 2 + 0.5)
    k = jnp.arange(config.max_pixels, dtype=dtype)
    u = u0[:, None] + sign[:, None] * k[None, :]
    t = (u - c_dom[:, None]) / n_dom[:, None]
    v = jnp.floor(c_min[:, None] + t * n_min[:, None] + 0.5)
    x = jnp.where(x_dom[:, None], u, v)
    y = jnp.where(x_dom[:, None], v, u)
    mask = jnp.broadcast_to(k[None, :] < L, x.shape)
    in_img = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    last = (L - 1).astype(jnp.int32)
    inside = in_img[:, 0] & jnp.take_along_axis(in_img, jnp.broadcast_to(last, (x.shape[0], 1)), axis=1)[:, 0]
    xi = jnp.clip(x, 0, w - 1).astype(jnp.int32)
    yi = jnp.clip(y, 0, h - 1).astype(jnp.int32)
    colour = image[yi, xi]  # in the image's dtype: 8-bit frames stay 8-bit (`colour_index` bins them as integers)
    delta_r = (u0 + sign * (L - 1) / 2 - c_dom) / n_dom
    return LineSamples(
        pixel=jnp.stack([xi, yi], -1), colour=colour, mask=mask & in_img, delta_r=delta_r,
        step=1.0 / jnp.abs(n_dom), inside=inside,
    )


# ------------------------------------------------------------------------------------- distributions


def segment_log_odds(histograms: ColourHistograms | LogOddsTable, samples: LineSamples, scale, config: LineConfig, prior=1e-7):
    """(N, S) log(P_f / P_b) of each segment: the sum of its pixels' log(h_f / h_b) (S = num_segments).

    `histograms` may be a `LogOddsTable` (then `prior` is the table's own)."""
    cells = colour_index(samples.colour, histograms.bins)
    lo = jnp.where(samples.mask, log_odds_of_cells(histograms, cells, prior), 0.0)
    k = jnp.arange(config.max_pixels)
    seg = k // _scale(scale, config)
    onehot = (seg[:, None] == jnp.arange(config.num_segments)[None, :]).astype(lo.dtype)
    return lo @ onehot


def smoothed_step(amplitude, slope, function_length: int = 8):
    """(F,) foreground probability of the smoothed step at x_j = j − (F−1)/2: ½ − α tanh(x / 2s)
    (a hard step ½ − α sign(x) for s = 0)."""
    amplitude = jnp.asarray(amplitude)
    slope = jnp.asarray(slope, amplitude.dtype)
    x = jnp.arange(function_length, dtype=amplitude.dtype) - (function_length - 1) / 2
    safe = jnp.where(slope > 0, slope, 1.0)
    shape = jnp.where(slope > 0, jnp.tanh(x / (2 * safe)), jnp.sign(x))
    return 0.5 - amplitude * shape


def min_expected_variance(amplitude, slope):
    """M3T's lower bound on a line's variance (segments²): max(1 / (2 atanh(2α)²), s)."""
    amplitude = jnp.asarray(amplitude)
    return jnp.maximum(1.0 / (2.0 * jnp.arctanh(2.0 * amplitude) ** 2), jnp.asarray(slope, amplitude.dtype))


def contour_distribution(log_odds, amplitude, slope, function_length: int = 8):
    """(N, D) distribution of the contour over the D = S − F + 1 inner segment boundaries.

    Args:
        log_odds: (N, S) per-segment log(P_f / P_b) (inside → outside).
        amplitude, slope: the smoothed step (scalars).
    """
    num_seg = log_odds.shape[-1]
    D = num_seg - function_length + 1
    hf = smoothed_step(amplitude, slope, function_length).astype(log_odds.dtype)  # (F,)
    idx = np.arange(D)[:, None] + np.arange(function_length)[None, :]  # (D, F) static
    pf = jax.nn.sigmoid(log_odds)[..., idx]  # (N, D, F)
    log_factor = jnp.log(pf * hf + (1.0 - pf) * (1.0 - hf))
    return jax.nn.softmax(jnp.sum(log_factor, axis=-1), axis=-1)


def distribution_moments(distribution, min_variance):
    """Mean (relative to the middle, in segments) and variance (≥ min_variance) of (N, D) distributions."""
    D = distribution.shape[-1]
    d = jnp.arange(D, dtype=distribution.dtype)
    mean = jnp.sum(d * distribution, axis=-1)
    var = jnp.sum((d - mean[..., None]) ** 2 * distribution, axis=-1)
    return mean - (D - 1) / 2, jnp.maximum(var, min_variance)


def schedule(scales, standard_deviations, round_index):
    """(scale int32, standard deviation) of round r: the r-th entries, the last one beyond. Jittable."""
    scales = jnp.atleast_1d(jnp.asarray(scales, jnp.int32))
    stds = jnp.atleast_1d(jnp.asarray(standard_deviations))
    r = jnp.asarray(round_index, jnp.int32)
    return scales[jnp.minimum(r, scales.shape[0] - 1)], stds[jnp.minimum(r, stds.shape[0] - 1)]


# ---------------------------------------------------------------------------------------------- lines


def _as_points(points, camera: Camera, T_world_root) -> ContourPoints:
    if isinstance(points, SparseViewModel):
        return points_for_pose(points, camera, T_world_root)
    return points


def measure_lines(
    camera: Camera,
    T_world_root,
    points: SparseViewModel | ContourPoints,
    image,
    histograms: ColourHistograms | LogOddsTable,
    params: LineParams,
    scale,
    config: LineConfig = DEFAULT_LINE_CONFIG,
    model: KinematicModel | None = None,
    theta=None,
    occluder_depth=None,
) -> LineMeasurements:
    """Project the contour points, read their lines and compute each contour distribution. Jittable.

    Args:
        camera: a single camera (a crop camera is fine: the image is then the crop).
        T_world_root: (4, 4) pose; points: a view model (its nearest view is used; rigid objects only:
            every point is on part 0) or `ContourPoints`; image: (H, W, 3) colours in [0, 255]; histograms: colour histograms (or their `LogOddsTable`).
        params: `LineParams`; scale: pixels per segment (int, traced is fine; clamped to
            [1, config.max_scale]).
        model, theta: kinematic tree and (J,) joints for `ContourPoints` of several parts.
        occluder_depth: (H, W) depth (mm) of other known objects (inf: none) or None; lines whose point lies
            behind one (`unoccluded`) are not valid, and the pixels of the others' lines that lie behind one count as
            neither foreground nor background (log odds 0).
    """
    dtype = camera.K.dtype
    image = jnp.asarray(image)  # uint8 or float; the samples are cast
    T_world_root = jnp.asarray(T_world_root, dtype)
    scale = _scale(scale, config)
    points = _as_points(points, camera, T_world_root)
    proj = project_contour(camera, T_world_root, points, model, theta)
    samples = sample_lines(image, proj.center, proj.normal, scale, config)
    if occluder_depth is not None:  # pixels of a known occluder say nothing about this contour: log odds 0
        d = occluder_depth[samples.pixel[..., 1], samples.pixel[..., 0]].astype(dtype)
        z_line = jnp.where(proj.valid, proj.depth, 1.0)[:, None]
        samples = eqx.tree_at(lambda m: m.mask, samples, samples.mask & ~(d < z_line - params.model_occlusion_threshold))
    log_odds = segment_log_odds(histograms, samples, scale, config, params.posterior_prior)
    dist = contour_distribution(log_odds, params.function_amplitude, params.function_slope, config.function_length)
    mean_seg, var_seg = distribution_moments(dist, min_expected_variance(params.function_amplitude, params.function_slope))
    seg_px = jnp.asarray(scale, dtype) * samples.step
    z = jnp.where(proj.valid, proj.depth, 1.0)
    continuous = jnp.minimum(points.foreground_distance, points.background_distance) * camera.K[0, 0] / (z * seg_px)
    valid = proj.valid & samples.inside & (continuous >= params.min_continuous_distance)
    if occluder_depth is not None:
        valid = valid & unoccluded(proj.center, z, occluder_depth, params.model_occlusion_threshold)
    return LineMeasurements(
        center=proj.center,
        normal=proj.normal,
        depth=z,
        valid=valid,
        distribution=dist,
        mean=samples.delta_r + mean_seg * seg_px,
        variance=var_seg * seg_px**2,
        variance_segments=var_seg,
        p_model=points.p_model.astype(dtype),
        part=points.part,
    )


def rows_from_measurements(
    camera: Camera,
    lines: LineMeasurements,
    params: LineParams,
    standard_deviation,
    cue=Cue.REGION,
    camera_index=0,
    undistort: bool = True,
) -> Correspondences:
    """One edge row per valid line (zero weight for the others). Jittable.

    Row: pixel = centre + mean · normal (the observed contour), model point = the contour point, edge
    normal = the line's normal (tangent weight 0), weight = params.weight · min_var / (σ² · var) per px²
    (M3T's weight times its Hessian factor), divided by (mm per px across the edge at the point)².

    Args:
        camera: the single camera of the lines; camera_index: the row's camera in the caller's rig.
        standard_deviation: σ (px) of this round; cue: the rows' `Cue` tag.
        undistort: the pixels are distorted image positions (they are when the camera has distortion).
    """
    dtype = lines.mean.dtype
    K = camera.K
    min_var = min_expected_variance(params.function_amplitude, params.function_slope)
    sigma2 = jnp.asarray(standard_deviation, dtype) ** 2
    w_px = params.weight * min_var / (sigma2 * lines.variance_segments)
    mm_per_px2 = lines.depth**2 * ((lines.normal[:, 0] / K[0, 0]) ** 2 + (lines.normal[:, 1] / K[1, 1]) ** 2)
    weight = jnp.where(lines.valid, w_px / mm_per_px2, 0.0)
    pixel = lines.center + lines.mean[:, None] * lines.normal
    pixel = jnp.where(lines.valid[:, None], pixel, jnp.asarray([K[0, 2], K[1, 2]], dtype))
    n = lines.mean.shape[0]
    return correspondences_from_pixels(
        camera,
        pixel,
        jnp.full((n,), camera_index, jnp.int32),
        jnp.where(lines.valid[:, None], lines.p_model, 0.0),
        lines.part,
        weight,
        undistort=undistort,
        cue=cue,
        edge_normal=jnp.where(lines.valid[:, None], lines.normal, 0.0),
        tangent_weight=jnp.zeros((), dtype),
    )


def line_rows(
    camera: Camera,
    T_world_root,
    points: SparseViewModel | ContourPoints,
    image,
    histograms: ColourHistograms | LogOddsTable,
    params: LineParams,
    scale,
    standard_deviation,
    config: LineConfig = DEFAULT_LINE_CONFIG,
    model: KinematicModel | None = None,
    theta=None,
    cue=Cue.REGION,
    camera_index=0,
    undistort: bool = True,
    occluder_depth=None,
) -> Correspondences:
    """Correspondence lines → padded edge rows for `jaxtrack.solve.solve_pose`. Jittable, vmappable.

    `measure_lines` then `rows_from_measurements`; N rows (the view model's points per view, or the
    `ContourPoints`' capacity), zero weight where a line is not valid (or hidden by `occluder_depth`).
    """
    lines = measure_lines(camera, T_world_root, points, image, histograms, params, scale, config, model, theta,
                          occluder_depth)
    return rows_from_measurements(camera, lines, params, standard_deviation, cue, camera_index, undistort)


class LineRefinement(eqx.Module):
    """Result of `refine_pose_lines`.

    Attributes:
        T_world_root: (4, 4) refined pose; theta: (J,) joints.
        status: int32 `jaxtrack.Status` of the last solve.
        num_lines: int32 valid lines of the last round.
    """

    T_world_root: jax.Array
    theta: jax.Array
    status: jax.Array
    num_lines: jax.Array


def refine_pose_lines(
    camera: Camera,
    T_world_root,
    points: SparseViewModel | ContourPoints,
    image,
    histograms: ColourHistograms | LogOddsTable,
    params: LineParams,
    scales,
    standard_deviations,
    num_rounds: int,
    config: LineConfig = DEFAULT_LINE_CONFIG,
    solver: SolverConfig = M3T_SOLVER,
    model: KinematicModel | None = None,
    theta=None,
    undistort: bool = True,
    solve_options: dict | None = None,
) -> LineRefinement:
    """`num_rounds` (static) rounds of {line_rows at the current pose → solve_pose} in a `lax.fori_loop`.

    Round r uses `schedule(scales, standard_deviations, r)`; a view model's nearest view is looked up
    again every round. Jittable, vmappable (e.g. over poses or parameters) and differentiable
    (forward mode through the loop; the solver's implicit derivatives, exact when `solver` runs to
    convergence).

    Args:
        scales, standard_deviations: (R,) per-round values (int px per segment ≤ config.max_scale; px).
        num_rounds: rounds (static). solver: `SolverConfig` of each round's solve (M3T: 2 steps).
        solve_options: extra keyword arguments of `solve_pose` (e.g. a prior), passed to every round.
    """
    dtype = camera.K.dtype
    T0 = jnp.asarray(T_world_root, dtype)
    kin = rigid_model(dtype) if model is None else model
    th0 = jnp.zeros((kin.num_joints,), dtype) if theta is None else jnp.asarray(theta, dtype)

    def body(r, carry):
        T, th, _, _ = carry
        scale, std = schedule(scales, standard_deviations, r)
        corr = line_rows(camera, T, points, image, histograms, params, scale, std, config, model, th,
                         undistort=undistort)
        sol = solve_pose(kin, corr, T, th, solver, cameras=camera, **(solve_options or {}))
        return sol.T_world_root, sol.theta, sol.status, corr.num_effective().astype(jnp.int32)

    init = (T0, th0, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))
    T, th, status, count = jax.lax.fori_loop(0, num_rounds, body, init)
    return LineRefinement(T, th, status, count)


# ------------------------------------------------------------------------------------------ learning


def line_learning_pixels(
    camera: Camera,
    T_world_root,
    points: SparseViewModel | ContourPoints,
    image_shape: tuple[int, int],
    params: LineParams,
    config: LineConfig = DEFAULT_LINE_CONFIG,
    model: KinematicModel | None = None,
    theta=None,
    occluder_depth=None,
):
    """Pixels on the lines inside and outside the projected contour for the histograms. Jittable.

    As M3T: from `unconsidered_line_length` px off the centre, one pixel per step along the dominant
    axis, up to `max_considered_line_length` px (and at most `learn_length` pixels), and short of the
    point's foreground / background distance (less twice the unconsidered length). Lines hidden by
    `occluder_depth` ((H, W) mm of other known objects, `unoccluded`) teach nothing.

    Returns:
        pixels_fg (N · Lf, 2), mask_fg (N · Lf,), pixels_bg, mask_bg, with Lf = config.learn_length.
    """
    h, w = image_shape
    dtype = camera.K.dtype
    T_world_root = jnp.asarray(T_world_root, dtype)
    points = _as_points(points, camera, T_world_root)
    proj = project_contour(camera, T_world_root, points, model, theta)
    c, n = proj.center, proj.normal
    z = jnp.where(proj.valid, proj.depth, 1.0)
    ic = jnp.floor(c + 0.5)
    centre_in = (ic[:, 0] >= 0) & (ic[:, 0] <= w - 1) & (ic[:, 1] >= 0) & (ic[:, 1] <= h - 1)
    ok = proj.valid & centre_in
    if occluder_depth is not None:
        ok = ok & unoccluded(c, z, occluder_depth, params.model_occlusion_threshold)
    skip = params.unconsidered_line_length
    fx = camera.K[0, 0]
    len_f = jnp.minimum(params.max_considered_line_length, points.foreground_distance * fx / z - 2 * skip)
    len_b = jnp.minimum(params.max_considered_line_length, points.background_distance * fx / z - 2 * skip)
    x_dom = jnp.abs(n[:, 1]) < jnp.abs(n[:, 0])
    a_dom = jnp.where(x_dom, jnp.abs(n[:, 0]), jnp.abs(n[:, 1]))
    step = n / a_dom[:, None]  # one pixel along the dominant axis
    i = jnp.arange(config.learn_length, dtype=dtype)

    def side(sign, length):
        count = jnp.floor(length * a_dom + 0.5)
        q = c[:, None, :] + sign * (skip * n[:, None, :] + i[None, :, None] * step[:, None, :])
        q = jnp.floor(q + 0.5)
        in_img = (q[..., 0] >= 0) & (q[..., 0] <= w - 1) & (q[..., 1] >= 0) & (q[..., 1] <= h - 1)
        mask = ok[:, None] & in_img & (i[None, :] < count[:, None])
        return q.reshape(-1, 2), mask.reshape(-1)

    pf, mf = side(-1.0, len_f)
    pb, mb = side(1.0, len_b)
    return pf, mf, pb, mb


def learn_line_histograms(
    camera: Camera,
    T_world_root,
    points: SparseViewModel | ContourPoints,
    image,
    params: LineParams,
    bins: int = 32,
    config: LineConfig = DEFAULT_LINE_CONFIG,
    model: KinematicModel | None = None,
    theta=None,
    occluder_depth=None,
) -> ColourHistograms:
    """Colour histograms of the lines' pixels inside / outside the contour at a pose. Jittable.

    Blend them into the running histograms with `update_histograms` (M3T: rate 1 on the first frame,
    0.2 after). Lines hidden by `occluder_depth` ((H, W) mm, or None) are left out.
    """
    image = jnp.asarray(image, camera.K.dtype)
    pf, mf, pb, mb = line_learning_pixels(camera, T_world_root, points, image.shape[:2], params, config, model, theta,
                                          occluder_depth)
    return learn_histograms(image, pf, mf, pb, mb, bins)
