"""Several objects in one scene: one `Tracker` per object, stepped together frame by frame.

What couples the objects is what each camera sees of them: the model depth of every object is rendered
once per frame, and each object's step sees the others as occluders (M3T's model occlusions):

- its correspondence lines leave out the lines whose contour point lies behind another object's surface
  (`TrackerState.occluder_depth`, min-filtered over `occluder_radius_px` so that a line grazing the other
  object's outline is left out too), in the refinement, the confidence and the histograms it learns;
- its flow and SIFT ignore the pixels of frame t where another object covered it then or covers it at its
  latest pose (r(x) = 0 and out of the SIFT mask, `TrackerState.data_weight` / `visible`).

The objects are stepped in turn (Gauss-Seidel): object i sees the objects before it at their new pose,
those after it at the previous frame's. An object whose frame is not OK (or RECOVERED) hides nothing until it is
OK again: a lost object's estimate may float in front of another and take its lines away. Each object keeps its own compiled step (objects with meshes of
equal vertex and face counts and equal settings share it), its own crop, status and confidence.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._status import Status
from ..render import RenderOutput, render
from ._step import FrameResult, TrackerState
from ._tracker import Tracker


@eqx.filter_jit
def _depth_maps(mesh, cameras, T, theta, model, plan) -> RenderOutput:
    """The object's full-frame render in every camera (C leading): depth (C, H, W), inf off the object."""
    return jax.vmap(lambda cam: render(mesh, cam, T, theta, model, plan))(cameras)


@functools.partial(jax.jit, static_argnums=2)
def _occluders(depths, i, radius: int):
    """(N, C, H, W) depths of N objects → (C, H, W) the nearest depth of every object but `i` (traced), raw and
    min-filtered over a (2r+1)² window (inf where none)."""
    others = jnp.min(jnp.where((jnp.arange(depths.shape[0]) == i)[:, None, None, None], jnp.inf, depths), axis=0)
    k = 2 * radius + 1
    grown = jax.lax.reduce_window(others, jnp.inf, jax.lax.min, (1, k, k), (1, 1, 1), "SAME")
    return others, grown


class JointTracker:
    """Tracks several objects seen by the same calibrated cameras, each with its own `Tracker`.

        joint = jt.JointTracker([jt.Tracker(mesh_a, cams), jt.Tracker(mesh_b, cams)])
        states = joint.start(frames0, [T_a, T_b])
        for frames in stream:
            states, results, infos = joint.step(states, frames)   # results[i].status per object

    Args:
        trackers: one `Tracker` per object, all on the same rig (cameras, image size, dtype).
        occluder_radius_px: pixels by which another object's outline grows before it hides a line.

    Raises:
        ValueError: fewer than one tracker, or trackers on different rigs.
    """

    def __init__(self, trackers: Sequence[Tracker], occluder_radius_px: int = 3):
        self.trackers = list(trackers)
        if not self.trackers:
            raise ValueError("JointTracker: trackers must name at least one Tracker")
        if any(not isinstance(t, Tracker) for t in self.trackers):
            raise TypeError("JointTracker: trackers must be jaxtrack Tracker objects")
        first = self.trackers[0].cameras
        for i, t in enumerate(self.trackers[1:], 1):
            c = t.cameras
            if (c.K.shape != first.K.shape or (c.height, c.width) != (first.height, first.width)
                    or not np.allclose(np.asarray(c.K), np.asarray(first.K))
                    or not np.allclose(np.asarray(c.T_cam_world), np.asarray(first.T_cam_world))
                    or c.K.dtype != first.K.dtype):
                raise ValueError(f"JointTracker: trackers[{i}] has another rig than trackers[0] (the objects must be seen by "
                                 "the same cameras)")
        for t in self.trackers:  # no search after a LOST frame (`step`): nor its keyframes, taken at `start` and on
            t.config = t.config.without_recovery()  # OK frames of a new view (a SIFT pass each)
        self.occluder_radius_px = int(occluder_radius_px)
        if self.occluder_radius_px < 0:
            raise ValueError(f"JointTracker: occluder_radius_px must be ≥ 0, got {occluder_radius_px}")
        self._depths: jax.Array | None = None  # (N, C, H, W) each object's depth at its latest pose

    @property
    def num_objects(self) -> int:
        return len(self.trackers)

    def _render_depth(self, i: int, T, theta) -> jax.Array:
        """(C, H, W) depth of object i at (T, Θ); the full-frame plan is made again after an overflow."""
        tracker = self.trackers[i]
        for _ in range(3):
            out = _depth_maps(tracker.mesh, tracker.cameras, jnp.asarray(T, tracker.dtype), jnp.asarray(theta, tracker.dtype),
                              tracker.model, tracker.plan)
            if not bool(jnp.any(out.overflow)):
                break
            tracker._replan(jnp.asarray(T, tracker.dtype), jnp.asarray(theta, tracker.dtype))
        return out.depth

    def _occluded(self, i: int, depths=None) -> tuple[jax.Array, jax.Array]:
        """(raw, grown) (C, H, W) depths of the objects other than `i` (in `depths`, default the latest)."""
        return _occluders(self._depths if depths is None else depths, jnp.asarray(i), self.occluder_radius_px)

    def start(self, frames, poses: Sequence, thetas: Sequence | None = None) -> list[TrackerState]:
        """Every object's state at the first frame (known poses `poses[i]`, (4, 4) model → world)."""
        if len(poses) != self.num_objects:
            raise ValueError(f"JointTracker.start: poses has {len(poses)} pose(s) for {self.num_objects} object(s)")
        thetas = [None] * self.num_objects if thetas is None else list(thetas)
        for i, t in enumerate(self.trackers):  # plans (full frame) first, then the depths that couple the objects
            T, theta = t._check_pose(poses[i], thetas[i])
            if t.plan is None:
                t._replan(T, theta)
        depths = []
        for i, t in enumerate(self.trackers):
            T, theta = t._check_pose(poses[i], thetas[i])
            depths.append(self._render_depth(i, T, theta))
        self._depths = jnp.stack(depths)
        return [t.start(frames, poses[i], thetas[i], occluder_depth=self._occluded(i)[1]) for i, t in enumerate(self.trackers)]

    def step(self, states: Sequence[TrackerState], frames) -> tuple[list[TrackerState], list[FrameResult], list[dict]]:
        """Frames t+1 for every object in turn; returns per object (state, `FrameResult`, info) as `Tracker.step`.

        Each info's timings gain "occluders_s" (the renders and occluder maps of this object's turn)."""
        if len(states) != self.num_objects:
            raise ValueError(f"JointTracker.step: states has {len(states)} state(s) for {self.num_objects} object(s)")
        if self._depths is None:
            raise ValueError("JointTracker.step: call start first")
        new_states, results, infos = [], [], []
        depths_t = self._depths  # every object as frame t showed it
        for i, (tracker, state) in enumerate(zip(self.trackers, states)):
            t0 = time.perf_counter()
            raw_t, _ = self._occluded(i, depths_t)
            raw, grown = self._occluded(i)  # the others at their latest poses (t+1 for those stepped already)
            own = self._depths[i] * (1.0 - 1e-4)
            # Own pixels of frame t that another object covered then, or covers where it is now: flow and SIFT from
            # them would follow the other object.
            hidden = (raw_t < own) | (raw < own)
            state = eqx.tree_at(lambda s: s.occluder_depth, state, grown.astype(tracker.dtype), is_leaf=lambda x: x is None)
            state = eqx.tree_at(lambda s: (s.data_weight, s.visible), state,
                                (jnp.where(hidden, 0.0, state.data_weight).astype(state.data_weight.dtype),
                                 state.visible & ~hidden))
            prep_s = time.perf_counter() - t0
            # No search after a LOST frame: it would score the lines the other objects hide (not measured).
            new, result, info = tracker.step(state, frames, recover=False)
            t1 = time.perf_counter()
            # Only a pose the object's own evidence supports hides the others (a lost object's estimate may float in
            # front of another and take its lines away).
            trusted = int(result.status) in (Status.OK, Status.RECOVERED)
            depth = self._render_depth(i, result.T_world_root, result.theta) if trusted else jnp.full_like(self._depths[i], jnp.inf)
            self._depths = self._depths.at[i].set(depth)
            info["timings"]["occluders_s"] = prep_s + time.perf_counter() - t1
            new_states.append(new)
            results.append(result)
            infos.append(info)
        return new_states, results, infos

    def join_background(self) -> None:
        for t in self.trackers:
            t.join_background()
