"""The modality protocol: a new modality is one module plus its registration; the fused loop; the pose prior."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
from jaxtrack.geometry import se3_exp, se3_inverse, se3_log
from jaxtrack.modality import (
    FrameContext,
    FusionCounts,
    Modality,
    Pose,
    RefineSettings,
    cue_names,
    fuse_rows,
    modality_names,
    refine_rounds,
    register_modality,
)
from jaxtrack.solve import (
    Cue,
    CueWeights,
    PosePrior,
    concatenate_correspondences,
    fuse_cue_weights,
    make_correspondences,
    solve_pose,
)
from jaxtrack.synth import perturb_pose, random_pose_scene


# --- a toy modality, defined and registered here without touching any other file -----------------------
@register_modality
class FixedPoints(Modality):
    """Known 2D-3D points (e.g. markers): the same rows every round, weight × a factor of its own."""

    name = "fixed_points"
    factor: float = eqx.field(static=True, default=1.0)

    @classmethod
    def from_config(cls, config):
        return cls()

    def start(self, ctx, state, host, params):
        return host  # the rows come from the host, as a detector's would

    def rows(self, ctx, state, frame, carry, pose, render, round_index, params):
        return frame.with_weight(frame.weight), carry

    def weight_scale(self, counts: FusionCounts, params, prediction):
        return jnp.asarray(self.factor, counts.own.dtype)


@register_modality
class ShiftedPoints(Modality):
    """A motion modality's stand-in: known rows that say another pose (a frame-to-frame cue carrying an error)."""

    name = "shifted_points"
    motion = True

    @classmethod
    def from_config(cls, config):
        return cls()

    def start(self, ctx, state, host, params):
        return host

    def rows(self, ctx, state, frame, carry, pose, render, round_index, params):
        return frame, carry

    def weight_scale(self, counts: FusionCounts, params, prediction):
        return jnp.ones((), counts.own.dtype)


def _scene_rows(seed=0, noise_px=0.5, capacity=64):
    scene = random_pose_scene(seed, num_points=60, noise_px=noise_px, num_cameras=1, dtype=np.float64)
    corr = make_correspondences(scene.cameras, scene.pixel, scene.p_model, camera_index=scene.camera_index,
                                capacity=capacity)
    return scene, corr


def _ctx(scene):
    """The parts of a `FrameContext` a modality without images reads (none of the image fields)."""
    return FrameContext(mesh=None, model=jt.rigid_model(jnp.float64), cameras=scene.cameras, crop_cameras=scene.cameras,
                        offsets=jnp.zeros((1, 2), jnp.int32), frames=None, crops=jnp.zeros((1, 4, 4, 3)), previous=None,
                        previous_crops=None, data_weight=None, render_t=None, pose_t=None, plan=None)


def test_a_registered_modality_is_a_tracker_choice_with_its_own_tag():
    assert "fixed_points" in modality_names()
    tag = FixedPoints.cue
    assert tag >= 16 and cue_names()[tag] == "fixed_points"
    assert tag not in (int(Cue.REGION), int(Cue.FLOW), int(Cue.SIFT))
    config = jt.TrackerConfig(cues=("region", "fixed_points"))
    mods = config.modalities()
    # "region" is the configured region modality ("auto": the lines, for a rigid object and for a chain)
    assert [m.name for m in mods] == ["lines", "fixed_points"] and config.cue_names == ("region", "fixed_points")
    assert [m.name for m in config.resolved(articulated=True).modalities()] == ["lines", "fixed_points"]
    chain = jt.TrackerConfig(cues=("region", "fixed_points"), region_modality="levelset").resolved(articulated=True)
    assert [m.name for m in chain.modalities()] == ["levelset", "fixed_points"]
    with pytest.raises(ValueError, match="twice"):
        jt.TrackerConfig(cues=("region", "lines"))
    from jaxtrack.cli import cue_choices

    assert "fixed_points" in cue_choices()
    with pytest.raises(ValueError, match="fixed_points"):  # the error lists the registered choices
        jt.TrackerConfig(cues=("region", "colour"))
    with pytest.raises(ValueError, match="already registered"):
        register_modality(type("Other", (FixedPoints,), {"name": "flow"}))


def test_refinement_loop_with_a_new_modality_alone():
    """The tracker's loop solves a toy modality's rows: the pose converges and the rows carry its tag."""
    scene, corr = _scene_rows()
    rows = corr.with_weight(corr.weight)
    rows = eqx.tree_at(lambda c: c.cue, rows, jnp.full_like(rows.cue, FixedPoints.cue))
    T0 = jnp.asarray(perturb_pose(np.random.default_rng(1), scene.T_world_root, 0.1, 10.0))
    mod = FixedPoints()
    zero = jnp.zeros(())
    settings = RefineSettings(jnp.asarray(1e-3), zero, zero, zero)
    ctx = _ctx(scene)
    frame = mod.start(ctx, None, rows, None)
    res = jax.jit(lambda T: refine_rounds((mod,), ctx, (None,), (frame,), Pose(T, jnp.zeros((0,))), None, settings, 5, 10))(T0)
    direct = solve_pose(jt.rigid_model(jnp.float64), rows, T0, config=jt.SolverConfig(max_steps=50))
    assert int(res.status) == jt.Status.OK
    assert np.abs(np.asarray(res.pose.T_world_root - direct.T_world_root)).max() < 1e-6
    assert np.all(np.asarray(res.rows.cue)[np.asarray(res.rows.weight) > 0] == FixedPoints.cue)


def test_the_motion_rows_leave_the_refinement_after_motion_rounds():
    """`RefineSettings.motion_rounds` K: the motion modalities' rows count in rounds 0 .. K − 1, × motion_late_factor
    f after. A contour stand-in's rows say the true pose, a motion stand-in's rows a pose 3° / 20 mm away: with every
    round (∞) the refinement settles between them; with K = 1 and f = 0 the later rounds solve the contour rows alone
    (their own solution) and the last round's motion rows weigh nothing; f = 0.3 ends strictly between, f = 1 is ∞.
    Rounds 0 .. K − 1 are ∞'s rounds (K = 2 with a cap of 2 rounds is ∞ with that cap, a third round is not), and a loop
    that could stop as settled after round 1 runs past K. One compiled program for every (K, f)."""
    from jaxtrack.geometry import project_points

    scene, corr = _scene_rows(noise_px=0.0)
    T_off = np.asarray(perturb_pose(np.random.default_rng(3), scene.T_world_root, np.radians(3.0), 20.0))
    pixel_off, _ = project_points(jax.tree.map(lambda a: a[0], scene.cameras),
                                  jnp.einsum("ij,nj->ni", T_off[:3, :3], scene.p_model) + T_off[:3, 3])
    motion = make_correspondences(scene.cameras, np.asarray(pixel_off), scene.p_model, camera_index=scene.camera_index,
                                  capacity=64)
    tag = lambda c, m: eqx.tree_at(lambda c: c.cue, c, jnp.full_like(c.cue, m.cue))
    contour_mod, motion_mod = FixedPoints(), ShiftedPoints()
    frames = (tag(corr, contour_mod), tag(motion, motion_mod))
    ctx = _ctx(scene)
    zero = jnp.zeros(())

    traces = []

    @eqx.filter_jit
    def run(K, f, cap, min_rounds):
        traces.append((cap, min_rounds))
        settings = RefineSettings(jnp.asarray(1e-6), zero, zero, zero, motion_rounds=K, motion_late_factor=f)
        return refine_rounds((contour_mod, motion_mod), ctx, (None, None), frames, Pose(jnp.asarray(T_off), jnp.zeros((0,))),
                             None, settings, cap, 10, min_rounds=min_rounds)

    refine = lambda K, f, cap=6, min_rounds=3: run(jnp.asarray(K, jnp.float64), jnp.asarray(f, jnp.float64), cap, min_rounds)
    every, split, ones, mid = refine(np.inf, 0.0), refine(1.0, 0.0), refine(1.0, 1.0), refine(1.0, 0.3)
    alone = solve_pose(jt.rigid_model(jnp.float64), frames[0], jnp.asarray(T_off), config=jt.SolverConfig(max_steps=50))
    err = lambda r: float(np.abs(np.asarray(r.pose.T_world_root) - np.asarray(alone.T_world_root)).max())
    assert err(split) < 1e-6 and err(every) > 1.0, (err(split), err(every))  # mm: between the two row sets with ∞
    assert err(every) > err(mid) + 0.1 and err(mid) > err(split) + 0.1, (err(every), err(mid), err(split))
    np.testing.assert_allclose(np.asarray(ones.pose.T_world_root), np.asarray(every.pose.T_world_root), atol=1e-9)
    last = np.asarray(split.rows.weight)[np.asarray(split.rows.cue) == motion_mod.cue]
    assert last.size and np.all(last == 0.0)
    # rounds 0 .. K − 1 are ∞'s rounds; round K is not
    first_two = (refine(2.0, 0.0, cap=2, min_rounds=0), refine(np.inf, 0.0, cap=2, min_rounds=0))
    np.testing.assert_allclose(np.asarray(first_two[0].pose.T_world_root), np.asarray(first_two[1].pose.T_world_root), atol=1e-12)
    assert err(refine(2.0, 0.0, cap=3, min_rounds=0)) < 1e-6
    # ∞ settles after its second round; with K = 3 the loop runs rounds 3 .. without the motion rows anyway
    free, late = refine(np.inf, 0.0, min_rounds=0), refine(3.0, 0.0, min_rounds=0)
    assert int(free.rounds) < 4 <= int(late.rounds) and err(late) < 1e-6, (int(free.rounds), int(late.rounds))
    assert traces == [(6, 3), (2, 0), (3, 0), (6, 0)], traces  # one program per (cap, min_rounds), none per (K, f)


def test_fuse_rows_is_the_section_v_rule():
    """The modalities' weight rules reproduce `fuse_cue_weights` on a region + flow + SIFT set."""
    from jaxtrack.track._builtin_modalities import LevelSetRegion, OpticalFlow, SiftKeypoints

    _, corr = _scene_rows(capacity=64)
    rng = np.random.default_rng(0)
    sets = []
    for cue, n in ((Cue.REGION, 50), (Cue.FLOW, 30), (Cue.SIFT, 10)):
        w = np.zeros(64)
        w[:n] = rng.uniform(0.2, 3.0, n) if cue == Cue.FLOW else 1.0
        c = corr.with_weight(jnp.asarray(w))
        sets.append(eqx.tree_at(lambda c: c.cue, c, jnp.full_like(c.cue, int(cue))))
    factors = CueWeights(region=0.7, flow=0.3, sift=2.0)

    class P(eqx.Module):
        weights: CueWeights

    mods = (LevelSetRegion(), OpticalFlow(), SiftKeypoints())
    for prediction in (False, True):
        ours = fuse_rows(mods, sets, P(factors), prediction=prediction)
        ref = fuse_cue_weights(concatenate_correspondences(*sets), factors, prediction=prediction)
        np.testing.assert_allclose(np.asarray(ours.weight), np.asarray(ref.weight), rtol=1e-12)


def test_fuse_rows_without_the_reference_modality_counts_the_next_one():
    """A configuration without the reference modality weighs its rows against the next one instead of zeroing them:
    SIFT alone counts its own rows in the prediction, flow + SIFT count n_OF in the refinement; with the reference
    present the rule is unchanged (`test_fuse_rows_is_the_section_v_rule`)."""
    from jaxtrack.track._builtin_modalities import LevelSetRegion, OpticalFlow, SiftKeypoints

    _, corr = _scene_rows(capacity=64)
    w = np.zeros(64)
    w[:10] = 1.0
    sift = eqx.tree_at(lambda c: c.cue, corr.with_weight(jnp.asarray(w)), jnp.full_like(corr.cue, int(Cue.SIFT)))
    w = np.zeros(64)
    w[:30] = np.linspace(0.5, 2.0, 30)
    flow = eqx.tree_at(lambda c: c.cue, corr.with_weight(jnp.asarray(w)), jnp.full_like(corr.cue, int(Cue.FLOW)))
    factors = CueWeights(region=0.7, flow=0.3, sift=2.0)

    class P(eqx.Module):
        weights: CueWeights

    ratio = float(factors.sift_ratio)
    for prediction in (True, False):  # SIFT alone: n_ref = its own 10 rows
        alone = np.asarray(fuse_rows((SiftKeypoints(),), [sift], P(factors), prediction=prediction).weight)
        np.testing.assert_allclose(alone[:10], 2.0 * ratio * 10, rtol=1e-12)
        assert np.all(alone[10:] == 0)
    both = np.asarray(fuse_rows((OpticalFlow(), SiftKeypoints()), [flow, sift], P(factors), prediction=False).weight)
    np.testing.assert_allclose(both[:30], 0.3 * np.linspace(0.5, 2.0, 30), rtol=1e-12)  # n_OF / n_OF = 1
    np.testing.assert_allclose(both[64:74], 2.0 * ratio * 30, rtol=1e-12)  # n_ref = n_OF
    # region + SIFT: the refinement counts n_C as before; the prediction (SIFT's rows only) counts SIFT's own
    region = eqx.tree_at(lambda c: c.cue, corr.with_weight(jnp.asarray((np.arange(64) < 50).astype(float))),
                         jnp.full_like(corr.cue, int(Cue.REGION)))
    refine = np.asarray(fuse_rows((LevelSetRegion(), SiftKeypoints()), [region, sift], P(factors)).weight)
    np.testing.assert_allclose(refine[64:74], 2.0 * ratio * 50, rtol=1e-12)


# --- the pose prior -------------------------------------------------------------------------------
def test_pose_prior_zero_is_no_prior_and_strong_holds_the_anchor():
    scene, corr = _scene_rows(noise_px=1.0)
    model = jt.rigid_model(jnp.float64)
    T0 = jnp.asarray(perturb_pose(np.random.default_rng(2), scene.T_world_root, 0.1, 10.0))
    free = solve_pose(model, corr, T0)
    zero = solve_pose(model, corr, T0, pose_prior=PosePrior(T0, 0.0, 0.0))
    np.testing.assert_allclose(np.asarray(zero.T_world_root), np.asarray(free.T_world_root), atol=1e-9)
    moved = []
    for s in (1e-3, 1e-1, 1e2):
        sol = solve_pose(model, corr, T0, pose_prior=PosePrior(T0, s, s))
        moved.append(np.linalg.norm(np.asarray(se3_log(se3_inverse(T0) @ sol.T_world_root))))
    full = np.linalg.norm(np.asarray(se3_log(se3_inverse(T0) @ free.T_world_root)))
    assert moved[0] > 0.9 * full and moved[0] > moved[1] > moved[2] and moved[2] < 0.05 * full, (moved, full)


def test_pose_prior_steadies_a_weakly_observed_direction():
    """Points on a small disc facing the camera: its depth is weakly observed; the prior holds it, and the
    well-observed directions still move to the data."""
    rng = np.random.default_rng(3)
    cam = jt.make_camera(np.diag([500.0, 500.0, 1.0]) + np.array([[0, 0, 160], [0, 0, 120], [0, 0, 0]]), 320, 240,
                         dtype=jnp.float64)
    ang = rng.uniform(0, 2 * np.pi, 60)
    p_model = np.stack([20 * np.cos(ang), 20 * np.sin(ang), np.zeros(60)], -1)
    T = np.eye(4)
    T[:3, 3] = [0, 0, 2000.0]
    p_cam = p_model + T[:3, 3]
    px = 500 * p_cam[:, :2] / p_cam[:, 2:] + [160, 120] + rng.normal(0, 1.0, (60, 2))
    corr = make_correspondences(cam, px, p_model, capacity=64)
    model = jt.rigid_model(jnp.float64)
    T0 = T.copy()
    T0[:3, 3] += [3.0, -2.0, 0.0]
    free = solve_pose(model, corr, jnp.asarray(T0))
    held = solve_pose(model, corr, jnp.asarray(T0), pose_prior=PosePrior(jnp.asarray(T0), 0.01, 0.01))
    dz_free = abs(float(free.T_world_root[2, 3]) - 2000.0)
    dz_held = abs(float(held.T_world_root[2, 3]) - 2000.0)
    assert dz_held < 0.5 * dz_free, (dz_free, dz_held)
    # x, y are well observed: both solves fix the 3 / 2 mm offset
    assert np.abs(np.asarray(held.T_world_root[:2, 3])).max() < 1.5


def test_pose_prior_far_from_its_anchor_agrees_with_the_autodiff_solver():
    """An anchor 15° and 46 mm from the start: the Gauss-Newton steps (the prior's Jacobian in closed form,
    J_l⁻¹ Ad) stop where optimistix's Levenberg-Marquardt on the residual (its Jacobian by autodiff) does."""
    scene, corr = _scene_rows(noise_px=1.0)
    model = jt.rigid_model(jnp.float64)
    T0 = jnp.asarray(perturb_pose(np.random.default_rng(6), scene.T_world_root, 0.1, 10.0))
    anchor = se3_exp(jnp.asarray([25.0, -20.0, 25.0, 0.2, -0.15, 0.1])) @ T0
    tight = {"max_steps": 200, "rtol": 1e-12, "atol": 1e-12}
    solves = [solve_pose(model, corr, T0, config=jt.SolverConfig(backend=backend, **tight),
                         pose_prior=PosePrior(anchor, 0.3, 0.3)) for backend in ("gauss-newton", "optimistix")]
    free = solve_pose(model, corr, T0, config=jt.SolverConfig(**tight))
    moved = np.linalg.norm(np.asarray(se3_log(se3_inverse(free.T_world_root) @ solves[0].T_world_root)))
    assert moved > 1e-2, moved  # the prior pulls
    np.testing.assert_allclose(np.asarray(solves[0].T_world_root), np.asarray(solves[1].T_world_root), atol=1e-7)


def test_pose_prior_strength_derivative_matches_finite_differences():
    scene, corr = _scene_rows(noise_px=1.0)
    model = jt.rigid_model(jnp.float64)
    T0 = jnp.asarray(perturb_pose(np.random.default_rng(4), scene.T_world_root, 0.1, 10.0))
    config = jt.SolverConfig(max_steps=100, rtol=1e-12, atol=1e-12)

    def t_of(s):
        return solve_pose(model, corr, T0, config=config, pose_prior=PosePrior(T0, s, s)).T_world_root[:3, 3]

    s, h = 0.05, 1e-4
    fd = (np.asarray(t_of(s + h)) - np.asarray(t_of(s - h))) / (2 * h)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(t_of)(s)), fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())


def test_pose_prior_vmaps_over_strengths():
    scene, corr = _scene_rows(noise_px=1.0)
    model = jt.rigid_model(jnp.float64)
    T0 = jnp.asarray(perturb_pose(np.random.default_rng(5), scene.T_world_root, 0.1, 10.0))
    strengths = jnp.asarray([0.0, 0.01, 1.0])
    batched = jax.vmap(lambda s: solve_pose(model, corr, T0, pose_prior=PosePrior(T0, s, s)).T_world_root)(strengths)
    for k, s in enumerate(np.asarray(strengths)):
        one = solve_pose(model, corr, T0, pose_prior=PosePrior(T0, s, s)).T_world_root
        np.testing.assert_allclose(np.asarray(batched[k]), np.asarray(one), atol=1e-8)


# --- the Cauchy loss on the motion rows (TrackerParams.motion_robust_px) ------------------------------------
def test_cauchy_weights_halve_at_the_scale_fall_with_the_error_and_are_off_at_zero():
    from jaxtrack.modality import cauchy_weights

    e = jnp.asarray([0.0, 1.0, 2.0, 4.0, 40.0])
    w = np.asarray(cauchy_weights(e, jnp.asarray(2.0)))
    np.testing.assert_allclose(w, 1.0 / (1.0 + (np.asarray(e) / 2.0) ** 2))
    assert w[0] == 1.0 and w[2] == pytest.approx(0.5) and np.all(np.diff(w) < 0)
    np.testing.assert_array_equal(np.asarray(cauchy_weights(e, jnp.asarray(0.0))), np.ones(5))
    np.testing.assert_array_equal(np.asarray(cauchy_weights(e, jnp.asarray(-1.0))), np.ones(5))


def test_reprojection_px_is_zero_at_the_pose_the_pixels_were_made_with():
    from jaxtrack.modality import reprojection_px

    scene, corr = _scene_rows(noise_px=0.0)
    err = reprojection_px(_ctx(scene), corr, Pose(jnp.asarray(scene.T_world_root), jnp.zeros((0,))))
    live = np.asarray(corr.weight) > 0
    assert np.abs(np.asarray(err)[live]).max() < 1e-6


def test_the_robust_prediction_is_not_pulled_by_rows_of_a_second_motion():
    """30 % of the motion rows follow another motion (an occluder's flow, 12 px away): the plain prediction
    (eq. 5) is biased toward them; the second, Cauchy-weighted pass lands near the object's true pose."""
    import types

    from jaxtrack.track._step import _robust_prediction

    scene, corr = _scene_rows(seed=3, noise_px=0.3)
    live = np.flatnonzero(np.asarray(corr.weight) > 0)
    pixel = np.asarray(corr.pixel).copy()
    pixel[live[: int(0.3 * len(live))]] += np.array([12.0, -5.0])
    moved = make_correspondences(scene.cameras, pixel[: len(scene.pixel)], scene.p_model,
                                 camera_index=scene.camera_index, capacity=corr.capacity)
    model = jt.rigid_model(jnp.float64)
    T0 = jnp.asarray(perturb_pose(np.random.default_rng(6), scene.T_world_root, 0.05, 5.0))
    ctx = _ctx(scene)

    @jax.jit
    def predict(scale):
        params = types.SimpleNamespace(motion_robust_px=scale, depth_invariant=jnp.zeros((), jnp.float64))
        return _robust_prediction(ctx, model, moved, T0, jnp.zeros((0,)), params, scene.cameras.center_world, 20)

    def error_px(out):  # mean reprojection error of the unmoved rows' true pixels at the predicted pose
        from jaxtrack.modality import reprojection_px

        e = np.asarray(reprojection_px(ctx, corr, Pose(out.T_world_root, jnp.zeros((0,)))))
        return float(e[live[int(0.3 * len(live)):]].mean())

    plain, robust = predict(jnp.asarray(-1.0)), predict(jnp.asarray(1.0))
    assert int(plain.passes) == 1 and int(robust.passes) == 2
    plain_err, robust_err = error_px(plain), error_px(robust)
    assert plain_err > 2.0, plain_err  # the outliers do bias eq. 5
    assert robust_err < 0.35 * plain_err, (plain_err, robust_err)
    # off, it is the plain solve
    one = solve_pose(model, moved, T0, config=jt.SolverConfig(max_steps=20), ray_origins=scene.cameras.center_world,
                     depth_invariance=0.0)
    np.testing.assert_allclose(np.asarray(plain.T_world_root), np.asarray(one.T_world_root), atol=1e-9)


def test_the_motion_rounds_default_to_every_round_and_a_bad_environment_value_names_its_variable(monkeypatch):
    """The tracker's defaults keep the motion rows in every round (K = ∞, f = 0 unused, no confidence gate), chains
    too; `late_rounds` sets (K, f, τ) and is checked; an opt-in value from the environment is checked with a message
    naming the variable."""
    from jaxtrack.track import default_params
    from jaxtrack.track._tracker import _env_number

    for model in (jt.rigid_model(jnp.float64), jt.chain_model([-1, 0], [(0.0, 0.0, 1.0)], [(0.0, 0.0, 0.0)], jnp.float64)):
        p = default_params(model, (96, 128), jnp.float64)
        assert np.isinf(float(p.motion_rounds)) and float(p.motion_late_factor) == 0.0
        assert float(p.motion_late_above) == 0.0
        # `late_rounds` = (K, f[, τ]) sets the three, chains too (an explicit choice); τ is 0 unless given
        q = default_params(model, (96, 128), jnp.float64, late_rounds=(3, 0.3, 0.9))
        assert (float(q.motion_rounds), float(q.motion_late_factor), float(q.motion_late_above)) == (3.0, 0.3, 0.9)
        q = default_params(model, (96, 128), jnp.float64, late_rounds=(2, 0.0))
        assert (float(q.motion_rounds), float(q.motion_late_factor), float(q.motion_late_above)) == (2.0, 0.0, 0.0)
    for bad in ((3,), (3, 1.5), (-1, 0.3), (float("nan"), 0.3), (3, 0.3, 2.0), (3, 0.3, 0.9, 1.0)):
        with pytest.raises(ValueError, match="late_rounds must be"):
            default_params(jt.rigid_model(jnp.float64), (96, 128), jnp.float64, late_rounds=bad)
    monkeypatch.setenv("JAXTRACK_MOTION_ROUNDS", "3")
    assert _env_number("JAXTRACK_MOTION_ROUNDS", "inf", 0.0, float("inf")) == 3.0
    for bad in ("", "three", "nan", "-1"):
        monkeypatch.setenv("JAXTRACK_MOTION_ROUNDS", bad)
        with pytest.raises(ValueError, match="JAXTRACK_MOTION_ROUNDS"):
            _env_number("JAXTRACK_MOTION_ROUNDS", "inf", 0.0, float("inf"))
