"""The sparse region modality: the region energy on correspondence lines across the model contour.

Eq. 11 of the paper in the limit of a hard shape prior (Φ = Φ0(χ)), with p1/p2 from global colour
histograms, evaluated only on short lines along the normals of the projected model contour (PWP3D,
RBOT, SRT3D, M3T). Per round: the contour points of the sparse viewpoint model's nearest view (rigid;
for a kinematic chain, of a render at the predicted pose, carried through the rounds) are projected
at the current pose, each line is read at the round's scale, the contour distribution along it gives
an edge row (its mean the observed contour, its variance the weight). In a joint run of several objects,
lines behind another tracked object (`FrameContext.occluder_depth`) are left out (M3T's model occlusions). The lines' rows are the n_C of
Section V. At the end of the frame the histograms learn the lines' pixels at the final pose (rate 0.2,
M3T). No render per round and no crop: one compiled program serves every object size.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp

from ...geometry import part_transforms
from ...modality import FrameContext, FusionCounts, Modality, Pose, StartContext, register_modality
from ...render import render
from ...solve import Correspondences, Cue
from ._histograms import ColourHistograms, log_odds_table, update_histograms
from ._lines import LineConfig, learn_line_histograms, line_rows, measure_lines, schedule
from ._viewmodel import ContourPoints, SparseViewModel, contour_points_from_render, load_or_build_view_model


class LineState(eqx.Module):
    """What the modality carries from frame to frame.

    Attributes:
        histograms: `ColourHistograms` with a leading camera axis (C, B³) (each camera its own).
    """

    histograms: ColourHistograms


def _flatten(corr: Correspondences) -> Correspondences:
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), corr)


@register_modality
class LineRegion(Modality):
    """Correspondence lines across the model contour (M3T's region modality on our solver).

    Attributes:
        config: `LineConfig` (segments, distribution length, the longest segment).
        scales: pixels per segment of rounds 0, 1, ... (the last repeats; M3T's RBOT setting 5, 2, 2, 1).
        standard_deviations: σ (px) of rounds 0, 1, ... (M3T's RBOT setting 20, 7, 3, 1.5).
        rounds: refinement rounds (M3T: 7 correspondence iterations); solver_steps: Gauss-Newton steps per
            round (M3T: 2 update iterations).
        num_points: contour points (lines) per view; subdivisions: of the icosahedron of viewpoints (4: 2562
            views); image_size: side of the renders the view model is made from (px).
        bins: histogram bins per colour channel (M3T: 32).
        inlier_px: a line agrees with the final pose when its contour lies within this many pixels (the
            confidence evidence).
    """

    name = "lines"
    cue = int(Cue.LINES)
    contour = True
    uses_crop = False
    config: LineConfig = eqx.field(static=True, default_factory=LineConfig)
    scales: tuple = eqx.field(static=True, default=(5, 2, 2, 1))
    standard_deviations: tuple = eqx.field(static=True, default=(20.0, 7.0, 3.0, 1.5))
    rounds: int = eqx.field(static=True, default=7)
    solver_steps: int = eqx.field(static=True, default=2)
    num_points: int = eqx.field(static=True, default=200)
    subdivisions: int = eqx.field(static=True, default=4)
    image_size: int = eqx.field(static=True, default=256)
    bins: int = eqx.field(static=True, default=32)
    inlier_px: float = eqx.field(static=True, default=3.0)

    def __check_init__(self):
        if not self.scales or any(int(s) < 1 or int(s) > self.config.max_scale for s in self.scales):
            raise ValueError(f"LineRegion.scales must be in 1..{self.config.max_scale} (LineConfig.max_scale), got {self.scales}")
        if len(self.standard_deviations) == 0 or any(s <= 0 for s in self.standard_deviations):
            raise ValueError(f"LineRegion.standard_deviations must be positive, got {self.standard_deviations}")
        if self.rounds < 1 or self.solver_steps < 1 or self.num_points < 1:
            raise ValueError("LineRegion: rounds, solver_steps and num_points must be ≥ 1")

    @classmethod
    def from_config(cls, config) -> LineRegion:
        """The defaults; `$JAXTRACK_VIEW_SUBDIVISIONS` (e.g. 2: 162 views) coarsens the view model built for a
        new mesh (quick runs and the test suite: a 2562-view model takes about 30 s per mesh)."""
        env = os.environ.get("JAXTRACK_VIEW_SUBDIVISIONS")
        if env is None:
            return cls()
        try:
            sub = int(env)
        except ValueError:
            raise ValueError(f"$JAXTRACK_VIEW_SUBDIVISIONS must be an integer 0..5, got {env!r}") from None
        if not 0 <= sub <= 5:
            raise ValueError(f"$JAXTRACK_VIEW_SUBDIVISIONS must be an integer 0..5, got {env!r}")
        return cls(subdivisions=sub)

    def loop_preferences(self) -> tuple[int, int, int]:
        return self.rounds, self.solver_steps, min(len(self.scales), self.rounds)

    # --- set-up -------------------------------------------------------------------------------------
    def prepare(self, mesh, model, cameras):
        """The sparse viewpoint model of a rigid mesh (cached on disk by the mesh's content); None for a
        chain (its contour comes from a render per frame)."""
        if model.num_joints > 0 or model.num_parts > 1:
            return None
        return load_or_build_view_model(mesh, num_points=self.num_points, subdivisions=self.subdivisions,
                                        image_size=self.image_size)

    @staticmethod
    def _per_camera(ctx, fn, points, *per_camera):
        """`fn(camera, c, points, occluder_depth, *arrays)` of every camera, vmapped over a rig of several (one
        compiled copy of the line code, not one per camera); outputs get a leading C axis.

        points: the view model (shared by the cameras: its nearest view is looked up per pose) or (C, N) render-based
        contour points (chains); per_camera: further pytrees with a leading C axis; the occluder depth is None (one
        object) or (C, H, W) depth of the other tracked objects."""
        shared = isinstance(points, SparseViewModel)
        occluder = ctx.occluder_depth

        def one(cam, c, pts, occ, *arrays):
            return fn(cam, c, points if shared else pts, occ, *arrays)

        num = ctx.cameras.K.shape[0]
        axes = (0, 0, None if shared else 0, None if occluder is None else 0) + (0,) * len(per_camera)
        args = (ctx.cameras, jnp.arange(num, dtype=jnp.int32), None if shared else points, occluder, *per_camera)
        if num == 1:  # unbatched: a vmap of one measured 5 ms slower per all-cue step (batched gathers)
            first = [a if ax is None else jax.tree.map(lambda x: x[0], a) for a, ax in zip(args, axes, strict=True)]
            return jax.tree.map(lambda x: x[None], one(*first))
        return jax.vmap(one, in_axes=axes)(*args)

    @staticmethod
    def _contour(ctx, frame):
        """The contour points the cameras use: the view model, or the frame's render-based (C, N) points (chains)."""
        return ctx.prepared if isinstance(ctx.prepared, SparseViewModel) else frame

    def _render_points(self, ctx, pose: Pose) -> ContourPoints:
        """(C, N) contour points of a full-frame render at `pose` (kinematic chains)."""
        T_parts = part_transforms(ctx.model, pose.T_world_root, pose.theta)

        def one(cam):
            out = render(ctx.mesh, cam, pose.T_world_root, pose.theta, ctx.model, ctx.plan)
            return contour_points_from_render(out, cam, self.num_points, T_parts)[0]

        return jax.vmap(one)(ctx.cameras)

    def init_state(self, ctx: StartContext, params) -> LineState:
        """Histograms learned on the lines at the known first pose (rate 1)."""
        pose = ctx.pose
        points = None if isinstance(ctx.prepared, SparseViewModel) else self._render_points(ctx, pose)
        frames = ctx.frames.astype(pose.T_world_root.dtype)

        def learn(cam, c, pts, occ, image):
            return learn_line_histograms(cam, pose.T_world_root, pts, image, params.lines, self.bins, self.config, ctx.model,
                                         pose.theta, occ)

        return LineState(self._per_camera(ctx, learn, self._contour(ctx, points), frames))

    # --- per frame ----------------------------------------------------------------------------------
    def start(self, ctx: FrameContext, state, host, params):
        return None

    def check_prediction(self, ctx: FrameContext, state, frame, pose: Pose, params):
        """Chains: the contour points of a render at the prediction, carried through the rounds."""
        if isinstance(ctx.prepared, SparseViewModel):
            return None
        return self._render_points(ctx, pose)

    def round_start(self, ctx: FrameContext, state: LineState, frame, params):
        """Each camera's `LogOddsTable` (C, B³): the histograms are fixed during the rounds."""
        return jax.vmap(lambda h: log_odds_table(h, params.lines.posterior_prior))(state.histograms)

    def rows(self, ctx: FrameContext, state: LineState, frame, carry, pose: Pose, render, round_index, params):
        scale, std = schedule(jnp.asarray(self.scales, jnp.int32), jnp.asarray(self.standard_deviations, pose.T_world_root.dtype),
                              round_index)
        images = ctx.frames

        def one(cam, c, pts, occ, image, table):  # table: this camera's log-odds table (round_start)
            return line_rows(cam, pose.T_world_root, pts, image, table, params.lines, scale, std, self.config, ctx.model,
                             pose.theta, cue=self.cue, camera_index=c, undistort=True, occluder_depth=occ)

        rows = self._per_camera(ctx, one, self._contour(ctx, frame), images, carry)
        return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), rows), carry  # camera-major, as concatenated

    def update(self, ctx: FrameContext, state: LineState, frame, carry, pose: Pose, params) -> LineState:
        """The histograms learn the lines' pixels at the final pose (M3T's rate, `TrackerParams.line_learning_rate`)."""
        images = ctx.frames

        def one(cam, c, pts, occ, image, hists):
            new = learn_line_histograms(cam, pose.T_world_root, pts, image, params.lines, self.bins, self.config, ctx.model,
                                        pose.theta, occ)
            return update_histograms(hists, new, params.line_learning_rate)

        return LineState(self._per_camera(ctx, one, self._contour(ctx, frame), images, state.histograms))

    def evidence(self, ctx: FrameContext, state: LineState, frame, carry, pose: Pose, render, params) -> dict:
        """At the final pose, finest scale: the fraction of valid lines whose contour lies within `inlier_px`
        ("confidence"), and per camera whether any line is valid ("seen")."""
        images = ctx.frames
        scale = jnp.asarray(self.scales[-1], jnp.int32)

        tables = state.histograms if carry is None else carry  # the rounds' log-odds tables (same histograms)

        def one(cam, c, pts, occ, image, table):
            m = measure_lines(cam, pose.T_world_root, pts, image, table, params.lines, scale, self.config, ctx.model,
                              pose.theta, occ)
            return jnp.sum(m.valid), jnp.sum(m.valid & (jnp.abs(m.mean) <= self.inlier_px))

        valid, close = self._per_camera(ctx, one, self._contour(ctx, frame), images, tables)
        dtype = pose.T_world_root.dtype
        return {"confidence": (jnp.sum(close) / jnp.maximum(jnp.sum(valid), 1)).astype(dtype), "seen": valid > 0,
                "valid_lines": valid}

    def weight_scale(self, counts: FusionCounts, params, prediction: bool):
        return params.weights.region  # contour evidence: the region factor, as the level set's rows
