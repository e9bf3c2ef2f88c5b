"""Pose solver (eq. 3-5): recovery of known poses, noise bound, degenerate input, jit/vmap, gradients."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

import jaxtrack as jt
from jaxtrack.geometry import project_points, se3_inverse, se3_log, select_camera
from jaxtrack.solve import PoseStatus, SolverConfig, make_correspondences, pad_rows, solve_pose
from jaxtrack.solve._normal_equations import line_planes, plane_normal_equations
from jaxtrack.synth import demo_chain, perturb_pose, random_pose_scene

MODELS = {
    "rigid": lambda: jt.rigid_model(jnp.float64),
    "chain3": lambda: demo_chain(3, dtype=jnp.float64),
    "tree2x2": lambda: demo_chain(4, branches=2, dtype=jnp.float64),
}


def _corr(scene, capacity=None, weight=None):
    return make_correspondences(
        scene.cameras,
        scene.pixel,
        scene.p_model,
        camera_index=scene.camera_index,
        part=scene.part,
        weight=weight,
        capacity=capacity,
        num_parts=scene.model.num_parts,
    )


def _pose_error(sol, scene):
    err = np.asarray(se3_log(sol.T_world_root @ se3_inverse(jnp.asarray(scene.T_world_root))))
    return err, np.abs(np.asarray(sol.theta) - scene.theta)


@pytest.mark.parametrize("model_name", list(MODELS))
@pytest.mark.parametrize("num_cameras", [1, 2, 4])
@pytest.mark.parametrize("backend", ["gauss-newton", "optimistix"])
def test_recovers_known_pose_noise_free(model_name, num_cameras, backend):
    model = MODELS[model_name]()
    scene = random_pose_scene(3 + num_cameras, num_points=150, num_cameras=num_cameras, model=model)
    rng = np.random.default_rng(7)
    T0 = perturb_pose(rng, scene.T_world_root, max_angle=0.35, max_translation=40.0)
    theta0 = scene.theta + rng.uniform(-0.2, 0.2, size=model.num_joints)
    sol = jt.estimate_pose(model, _corr(scene), T0, theta0, SolverConfig(max_steps=100, backend=backend))
    assert int(sol.status) == PoseStatus.OK
    err, theta_err = _pose_error(sol, scene)
    assert np.abs(err).max() < 1e-6, err
    assert theta_err.max(initial=0.0) < 1e-6
    assert float(sol.cost) < 1e-10


@pytest.mark.parametrize("model_name", ["rigid", "chain3"])
def test_noise_within_derived_bound(model_name):
    """With σ = 1 px pixel noise the error follows the Gauss-Newton covariance (eq. 5).

    For an unweighted least-squares estimate the covariance is the sandwich H⁻¹ (Σ σ_i² J_iᵀJ_i) H⁻¹
    with σ_i = σ_px · z_i / f the pixel noise seen at the point's depth (mm across the ray). The error
    e = (log(T T_gt⁻¹), Θ − Θ_gt) must then satisfy eᵀ Cov⁻¹ e < χ²_D(0.9999) in every trial.
    """
    model = MODELS[model_name]()
    sigma_px, focal = 1.0, 800.0
    bound = chi2.ppf(0.9999, model.num_dof)
    stats = []
    for seed in range(10):
        scene = random_pose_scene(seed, num_points=300, noise_px=sigma_px, num_cameras=2, model=model)
        corr = _corr(scene)
        sol = solve_pose(model, corr, jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta))
        assert int(sol.status) == PoseStatus.OK
        # Depth of each point in its camera, at the true pose.
        T_parts = np.asarray(jt.part_transforms(model, jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta)))
        p_world = np.einsum("nij,nj->ni", T_parts[scene.part, :3, :3], scene.p_model) + T_parts[scene.part, :3, 3]
        T_cw = np.asarray(scene.cameras.T_cam_world)[scene.camera_index]
        depth = np.einsum("nj,nj->n", T_cw[:, 2, :3], p_world) + T_cw[:, 2, 3]
        sigma_mm = sigma_px * depth / focal
        normals, offsets, _ = line_planes(corr.n, corr.m)
        args = (model, jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta), corr.p_model, corr.part, normals, offsets)
        H, _, _ = plane_normal_equations(*args, jnp.ones(len(depth)))
        S, _, _ = plane_normal_equations(*args, jnp.asarray(sigma_mm**2))
        H_inv = np.linalg.inv(np.asarray(H))
        cov = H_inv @ np.asarray(S) @ H_inv
        err, _ = _pose_error(sol, scene)
        e = np.concatenate([err, np.asarray(sol.theta) - scene.theta])
        stats.append(e @ np.linalg.solve(cov, e))
    assert max(stats) < bound, (stats, bound)
    # The statistic is χ²_D distributed: its mean over the trials is near D, not ≪ D (the bound is tight).
    assert 0.25 * model.num_dof < np.mean(stats) < 2.5 * model.num_dof


def test_padding_count_does_not_matter_and_compiles_once():
    model = jt.rigid_model(jnp.float64)
    capacity = 256

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def solve(corr, T0):
        return solve_pose(model, corr, T0)

    rng = np.random.default_rng(0)
    for i in range(100):
        count = int(rng.integers(4, capacity))
        # The first `count` of `capacity` random points: a random scene of `count` points, generated at one shape
        # (`random_pose_scene` projects with a program per point count: ~100 compiles, about 18 of the test's 28 s alone).
        full = random_pose_scene(i, num_points=capacity)
        scene = dataclasses.replace(full, **{k: getattr(full, k)[:count] for k in ("pixel", "p_model", "part", "camera_index")})
        T0 = perturb_pose(rng, scene.T_world_root, 0.2, 20.0)
        sol = solve(_corr(scene, capacity=capacity), jnp.asarray(T0))
        err, _ = _pose_error(sol, scene)
        assert int(sol.status) == PoseStatus.OK and np.abs(err).max() < 1e-6, (i, count)
        assert int(sol.num_effective) == count


def test_vmap_over_weight_vectors_equals_loop():
    model = demo_chain(3, dtype=jnp.float64)
    scene = random_pose_scene(11, num_points=120, noise_px=1.5, num_cameras=2, model=model)
    corr = _corr(scene)
    weights = jnp.asarray(np.random.default_rng(3).uniform(0.0, 2.0, size=(64, 120)))
    T0, th0 = jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta)
    def solve(w):
        return solve_pose(model, corr.with_weight(w), T0, th0)

    batched = jax.jit(jax.vmap(solve))(weights)
    single = jax.jit(solve)
    for k in range(64):
        one = single(weights[k])
        np.testing.assert_allclose(batched.T_world_root[k], one.T_world_root, atol=1e-9)
        np.testing.assert_allclose(batched.theta[k], one.theta, atol=1e-9)
        assert int(batched.status[k]) == int(one.status)


def test_vmap_over_initial_poses_and_correspondence_sets():
    model = jt.rigid_model(jnp.float64)
    scenes = [random_pose_scene(s, num_points=80, noise_px=0.5) for s in range(8)]
    corr = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[_corr(s, capacity=100) for s in scenes])
    rng = np.random.default_rng(5)
    T0 = jnp.asarray(np.stack([perturb_pose(rng, s.T_world_root, 0.3, 30.0) for s in scenes]))
    out = jax.vmap(lambda c, T: solve_pose(model, c, T))(corr, T0)
    for k, s in enumerate(scenes):
        sol = solve_pose(model, jax.tree_util.tree_map(lambda x, k=k: x[k], corr), T0[k])
        np.testing.assert_allclose(out.T_world_root[k], sol.T_world_root, atol=1e-8)


TIGHT = SolverConfig(max_steps=100, rtol=1e-13, atol=1e-13)


def _translation_of_weights(model, corr, T0, th0):
    @jax.jit
    def f(w):
        sol = solve_pose(model, corr.with_weight(w), T0, th0, TIGHT)
        return jnp.concatenate([sol.T_world_root[:3, 3], sol.T_world_root[:3, :3].ravel(), sol.theta])

    return f


@pytest.mark.parametrize("model_name", ["rigid", "chain3"])
def test_solution_derivative_wrt_weights_matches_finite_differences(model_name):
    model = MODELS[model_name]()
    scene = random_pose_scene(21, num_points=40, noise_px=2.0, num_cameras=2, model=model)
    corr = _corr(scene)
    w0 = jnp.asarray(np.random.default_rng(2).uniform(0.5, 1.5, size=40))
    f = _translation_of_weights(model, corr, jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta))
    fwd = jax.jacfwd(f)(w0)
    rev = jax.jacrev(f)(w0)
    eps = 1e-4
    fd = np.stack([(f(w0.at[i].add(eps)) - f(w0.at[i].add(-eps))) / (2 * eps) for i in range(40)], -1)
    assert np.abs(fd).max() > 1e-3  # the weights do move the solution
    np.testing.assert_allclose(fwd, rev, atol=1e-8)
    np.testing.assert_allclose(fwd, fd, atol=1e-6 * max(1.0, np.abs(fd).max()))


def test_solution_derivative_wrt_model_points():
    model = jt.rigid_model(jnp.float64)
    scene = random_pose_scene(4, num_points=30, noise_px=1.0)
    corr = _corr(scene)
    T0 = jnp.asarray(scene.T_world_root)

    @jax.jit
    def f(p):
        return solve_pose(model, eqx.tree_at(lambda c: c.p_model, corr, p), T0, None, TIGHT).T_world_root[:3, 3]

    p0 = corr.p_model
    J = jax.jacrev(f)(p0)
    eps = 1e-5
    for i, k in [(0, 0), (7, 2), (19, 1)]:
        fd = (f(p0.at[i, k].add(eps)) - f(p0.at[i, k].add(-eps))) / (2 * eps)
        np.testing.assert_allclose(J[:, i, k], fd, atol=1e-6)


def test_residual_derivatives_agree():
    model = demo_chain(3, dtype=jnp.float64)
    scene = random_pose_scene(8, num_points=20, noise_px=1.0, model=model)
    corr = _corr(scene)

    @jax.jit
    def r(x):
        return jt.solve.plucker_residuals(model, jt.se3_exp(x[:6]) @ jnp.asarray(scene.T_world_root), x[6:], corr)

    x0 = jnp.concatenate([jnp.zeros(6), jnp.asarray(scene.theta)])
    fwd, rev = jax.jacfwd(r)(x0), jax.jacrev(r)(x0)
    eps = 1e-6
    fd = np.stack([(r(x0.at[i].add(eps)) - r(x0.at[i].add(-eps))) / (2 * eps) for i in range(9)], -1)
    np.testing.assert_allclose(fwd, rev, atol=1e-10)
    np.testing.assert_allclose(fwd, fd, atol=1e-5)


def test_degenerate_inputs_give_status_or_clear_errors():
    model = jt.rigid_model(jnp.float64)
    scene = random_pose_scene(0, num_points=10)
    T0 = jnp.asarray(scene.T_world_root)
    # Two correspondences: 4 constraints for 6 DoF.
    few = _corr(scene, capacity=10, weight=np.r_[np.ones(2), np.zeros(8)])
    sol = solve_pose(model, few, T0)
    assert int(sol.status) == PoseStatus.TOO_FEW and np.isfinite(sol.T_world_root).all()
    np.testing.assert_allclose(sol.T_world_root, T0)
    with pytest.raises(ValueError, match="too few"):
        jt.estimate_pose(model, few, T0)
    # NaN in a weighted row inside jit: a status, the initial pose, no NaN.
    corr = _corr(scene)
    bad = eqx.tree_at(lambda c: c.p_model, corr, corr.p_model.at[3, 1].set(jnp.nan))
    sol = jax.jit(lambda c: solve_pose(model, c, T0))(bad)
    assert int(sol.status) == PoseStatus.INVALID_INPUT and np.isfinite(sol.T_world_root).all()
    with pytest.raises(ValueError, match="non-finite"):
        jt.estimate_pose(model, bad, T0)
    # NaN in a padded (zero-weight) row is harmless.
    padded = eqx.tree_at(lambda c: (c.p_model, c.weight), corr, (corr.p_model.at[3].set(jnp.nan), corr.weight.at[3].set(0.0)))
    assert int(solve_pose(model, padded, T0).status) == PoseStatus.OK
    # Negative weights.
    neg = corr.with_weight(corr.weight.at[0].set(-1.0))
    assert int(solve_pose(model, neg, T0).status) == PoseStatus.INVALID_INPUT
    # Builder errors name the argument.
    with pytest.raises(ValueError, match="pixel must have shape"):
        make_correspondences(scene.cameras, scene.pixel[:, :1], scene.p_model)
    with pytest.raises(ValueError, match="p_model must have shape"):
        make_correspondences(scene.cameras, scene.pixel, scene.p_model[:5])
    with pytest.raises(ValueError, match="weight must be ≥ 0"):
        make_correspondences(scene.cameras, scene.pixel, scene.p_model, weight=-np.ones(10))
    with pytest.raises(ValueError, match="pixel has non-finite"):
        make_correspondences(scene.cameras, np.full((10, 2), np.nan), scene.p_model)
    with pytest.raises(ValueError, match="exceed the capacity"):
        make_correspondences(scene.cameras, scene.pixel, scene.p_model, capacity=5)
    with pytest.raises(ValueError, match="T_init must have shape"):
        jt.estimate_pose(model, corr, np.eye(3))
    with pytest.raises(ValueError, match="backend"):
        SolverConfig(backend="newton")


def test_unobserved_joint_is_damped_not_nan():
    """Rank deficiency: no point on the last link; LM keeps that angle at its start value."""
    model = demo_chain(3, dtype=jnp.float64)
    scene = random_pose_scene(5, num_points=200, model=model)
    keep = scene.part != 3
    corr = _corr(scene, weight=keep.astype(float))
    theta0 = jnp.asarray(scene.theta).at[2].set(0.123)
    sol = solve_pose(model, corr, jnp.asarray(scene.T_world_root), theta0)
    assert int(sol.status) <= PoseStatus.MAX_STEPS
    assert np.isfinite(sol.theta).all()
    np.testing.assert_allclose(sol.theta[:2], scene.theta[:2], atol=1e-6)
    assert float(sol.theta[2]) == pytest.approx(0.123, abs=1e-6)


def test_float32_solve_is_accurate():
    model = jt.rigid_model(jnp.float32)
    scene = random_pose_scene(2, num_points=200, dtype=np.float32)
    corr = make_correspondences(scene.cameras, scene.pixel, scene.p_model)
    assert corr.n.dtype == jnp.float32
    T0 = perturb_pose(np.random.default_rng(0), scene.T_world_root, 0.3, 30.0)
    sol = solve_pose(model, corr, jnp.asarray(T0, jnp.float32))
    assert sol.T_world_root.dtype == jnp.float32
    err, _ = _pose_error(sol, scene)
    assert np.abs(err[3:]).max() < 1e-4 and np.abs(err[:3]).max() < 0.1


def test_pad_rows():
    assert pad_rows(np.ones((2, 3)), 5).shape == (5, 3)
    assert pad_rows(np.ones(2), 4).tolist() == [1, 1, 0, 0]


def _rigid_scene(num_points=60, dtype=np.float64, p_model=None, seed=0, capacity=64):
    """One camera (at z = −1000 looking along +z), a rigid object at its true pose; optional model points.

    One capacity for all these tests, so that they share the compiled solver (per dtype).
    """
    scene = random_pose_scene(seed, num_points=num_points, dtype=dtype)
    if p_model is not None:
        T = scene.T_world_root
        p_world = p_model @ T[:3, :3].T + T[:3, 3]
        pixel, _ = project_points(select_camera(scene.cameras, 0), jnp.asarray(p_world, dtype))
        noisy = np.asarray(pixel, np.float64) + np.random.default_rng(seed).normal(0.0, 0.5, (len(p_model), 2))
        corr = make_correspondences(scene.cameras, noisy, p_model, capacity=capacity)
    else:
        corr = _corr(scene, capacity=capacity)
    return scene, corr


@pytest.mark.parametrize(
    "make_T",
    [
        lambda T: np.zeros((4, 4)),  # all-zero "pose"
        lambda T: np.block([[2.0 * T[:3, :3], T[:3, 3:]], [np.eye(4)[3:]]]),  # scaled rotation
        lambda T: np.block([[-T[:3, :3], T[:3, 3:]], [np.eye(4)[3:]]]),  # a reflection (det −1)
        lambda T: np.vstack([T[:3], [[0.0, 0.0, 1.0, 1.0]]]),  # last row not (0, 0, 0, 1)
    ],
    ids=["zero", "scaled", "reflection", "last-row"],
)
def test_non_rigid_initial_pose_is_rejected(make_T):
    model = jt.rigid_model(jnp.float64)
    scene, corr = _rigid_scene()
    T_bad = make_T(np.asarray(scene.T_world_root))
    with pytest.raises(ValueError, match="T_init"):
        jt.estimate_pose(model, corr, T_bad)
    sol = solve_pose(model, corr, jnp.asarray(T_bad))
    assert int(sol.status) == PoseStatus.INVALID_INPUT and not bool(sol.ok)
    assert np.isfinite(sol.T_world_root).all()
    np.testing.assert_array_equal(sol.T_world_root, T_bad)  # the input handed back, not a "solution"


def test_rigidity_tolerance_follows_the_dtype():
    """Rounding the pose to the solve's dtype (or to 6 decimals, as pose files store it) is accepted."""
    for dtype in (np.float32, np.float64):
        model = jt.rigid_model(dtype)
        scene, corr = _rigid_scene(dtype=dtype)
        T0 = perturb_pose(np.random.default_rng(1), scene.T_world_root, 0.1, 10.0)
        for T in (T0.astype(dtype), np.round(T0, 6)):
            sol = jt.estimate_pose(model, corr, T)
            assert int(sol.status) == PoseStatus.OK
        # 1% scale passes no dtype's tolerance.
        scaled = T0.copy()
        scaled[:3, :3] *= 1.01
        with pytest.raises(ValueError, match="T_init's rotation block"):
            jt.estimate_pose(model, corr, scaled.astype(dtype))
    assert jt.solve._pose_solver.rigidity_tolerance(np.float32) > jt.solve._pose_solver.rigidity_tolerance(np.float64)


def test_initial_pose_behind_the_camera_is_rejected_when_cameras_are_given():
    model = jt.rigid_model(jnp.float64)
    scene, corr = _rigid_scene()
    cameras = scene.cameras
    centre = np.asarray(cameras.center_world[0])
    T_true = np.asarray(scene.T_world_root)
    # The object mirrored through the camera centre: same lines, points behind the camera.
    T_behind = T_true.copy()
    T_behind[:3, 3] = 2 * centre - T_true[:3, 3]
    assert float(jt.solve.fraction_behind_cameras(model, corr, jnp.asarray(T_behind), jnp.zeros(0), cameras)) > 0.9
    assert float(jt.solve.fraction_behind_cameras(model, corr, jnp.asarray(T_true), jnp.zeros(0), cameras)) == 0.0
    with pytest.raises(ValueError, match="T_init puts 100% of the correspondence weight behind the cameras"):
        jt.estimate_pose(model, corr, T_behind, cameras=cameras)
    sol = solve_pose(model, corr, jnp.asarray(T_behind), cameras=cameras)
    assert int(sol.status) == PoseStatus.INVALID_INPUT
    np.testing.assert_allclose(sol.T_world_root, T_behind)
    # In front (a tracker's start near the truth) passes the same check, also for a rig of 2 cameras.
    T0 = perturb_pose(np.random.default_rng(2), T_true, 0.2, 20.0)
    assert int(jt.estimate_pose(model, corr, T0, cameras=cameras).status) == PoseStatus.OK
    rig_scene = random_pose_scene(9, num_points=60, num_cameras=2)
    rig_corr = _corr(rig_scene, capacity=64)
    assert int(jt.estimate_pose(model, rig_corr, rig_scene.T_world_root, cameras=rig_scene.cameras).status) == PoseStatus.OK
    # A camera index outside the rig is named.
    wrong = eqx.tree_at(lambda c: c.camera, rig_corr, rig_corr.camera.at[0].set(5))
    with pytest.raises(ValueError, match="correspondences.camera"):
        jt.estimate_pose(model, wrong, rig_scene.T_world_root, cameras=rig_scene.cameras)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("layout", ["one-spot", "collinear"])
def test_degenerate_point_sets_are_reported(layout, dtype):
    """Coincident or collinear model points leave root directions free: DEGENERATE, initial pose back."""
    model = jt.rigid_model(dtype)
    rng = np.random.default_rng(4)
    if layout == "one-spot":
        p_model = np.tile(rng.uniform(-50, 50, (1, 3)), (40, 1))
    else:
        p_model = rng.uniform(-50, 50, (1, 3)) + np.linspace(-80, 80, 40)[:, None] * np.array([[0.36, 0.48, 0.8]])
    scene, corr = _rigid_scene(p_model=p_model, dtype=dtype)
    T0 = perturb_pose(np.random.default_rng(3), scene.T_world_root, 0.1, 10.0).astype(dtype)
    sol = solve_pose(model, corr, jnp.asarray(T0))
    assert int(sol.status) == PoseStatus.DEGENERATE and not bool(sol.ok)
    np.testing.assert_array_equal(sol.T_world_root, T0)
    with pytest.raises(jt.StatusError, match="DEGENERATE"):
        jt.estimate_pose(model, corr, T0)
    # throw=False: the status comes back instead of an exception.
    assert int(jt.estimate_pose(model, corr, T0, throw=False).status) == PoseStatus.DEGENERATE
    # The same solver on a spread-out set of the same size is OK (the check is not a blanket refusal).
    spread_scene, spread = _rigid_scene(num_points=40, dtype=dtype)
    assert int(solve_pose(model, spread, jnp.asarray(spread_scene.T_world_root, dtype)).status) == PoseStatus.OK


def test_status_priority_names_the_cause():
    """An invalid input is reported as such even when it would also be degenerate or too few."""
    model = jt.rigid_model(jnp.float64)
    _, corr = _rigid_scene(p_model=np.zeros((10, 3)))
    assert int(solve_pose(model, corr, jnp.zeros((4, 4))).status) == PoseStatus.INVALID_INPUT
    few = corr.with_weight(corr.weight.at[2:].set(0.0))
    assert int(solve_pose(model, few, jnp.eye(4)).status) == PoseStatus.TOO_FEW


def test_joint_prior_holds_a_weakly_observed_joint_and_leaves_observed_ones():
    """The joint prior (damping for weakly observed joints): strength 0 is no prior; a joint seen by two
    noisy rows stays near its anchor while joints with many rows are still solved; the stronger the
    prior, the nearer the anchor, and the optimum satisfies its own normal equations (prior included)."""
    from jaxtrack.solve import JointPrior

    model = demo_chain(3, dtype=jnp.float64)
    scene = random_pose_scene(5, num_points=200, noise_px=1.0, model=model)
    weak = np.flatnonzero(scene.part == 3)
    keep = (scene.part != 3).astype(float)
    keep[weak[:2]] = 1.0  # the last joint: two rows only
    corr = _corr(scene, weight=keep)
    T0 = jnp.asarray(scene.T_world_root)
    anchor = jnp.asarray(scene.theta) + jnp.asarray([0.05, -0.05, 0.3])
    free = solve_pose(model, corr, T0, anchor, TIGHT)
    none = solve_pose(model, corr, T0, anchor, TIGHT, prior=JointPrior(anchor, jnp.asarray(0.0)))
    np.testing.assert_array_equal(np.asarray(free.theta), np.asarray(none.theta))
    gaps = []
    for strength in (0.01, 0.1, 1.0):
        sol = solve_pose(model, corr, T0, anchor, TIGHT, prior=JointPrior(anchor, jnp.asarray(strength)))
        assert int(sol.status) == PoseStatus.OK
        gaps.append(np.abs(np.asarray(sol.theta - anchor)))
    gaps = np.stack(gaps)
    assert np.all(np.diff(gaps[:, 2]) < 0)  # stronger prior, nearer the anchor
    # 0.01: the weak joint keeps most of its 0.3 rad offset from the truth (without the prior the two rows take
    # it to within 0.1 rad of the truth), the observed ones move to the data (< 0.01 rad).
    assert gaps[0, 2] < 0.5 * 0.3 and abs(float(free.theta[2] - scene.theta[2])) < 0.1
    sol = solve_pose(model, corr, T0, anchor, TIGHT, prior=JointPrior(anchor, jnp.asarray(0.01)))
    np.testing.assert_allclose(np.asarray(sol.theta[:2]), scene.theta[:2], atol=0.01)


def test_joint_prior_derivatives_match_finite_differences():
    """Implicit derivatives of the solution include the prior rows: d θ* / d anchor against central differences."""
    from jaxtrack.solve import JointPrior

    model = demo_chain(3, dtype=jnp.float64)
    scene = random_pose_scene(6, num_points=40, noise_px=2.0, num_cameras=2, model=model)
    corr = _corr(scene)
    T0 = jnp.asarray(scene.T_world_root)

    @jax.jit
    def f(anchor):
        return solve_pose(model, corr, T0, jnp.asarray(scene.theta), TIGHT, prior=JointPrior(anchor, jnp.asarray(0.2))).theta

    a0 = jnp.asarray(scene.theta) + 0.02
    jac = jax.jacfwd(f)(a0)
    eps = 1e-5
    fd = np.stack([(f(a0.at[i].add(eps)) - f(a0.at[i].add(-eps))) / (2 * eps) for i in range(3)], -1)
    assert np.abs(fd).max() > 1e-3
    np.testing.assert_allclose(jac, fd, atol=1e-6)


@pytest.mark.parametrize("model_name", ["rigid", "chain3"])
def test_weights_per_pixel_scale_each_row_by_its_focal_over_depth_squared(model_name):
    """`weights_per_pixel`: w · fx fy / Z² with Z the row point's depth in its own camera at the given pose (two
    cameras, parts of a chain), the rows as given when off."""
    from jaxtrack.solve import model_points_world, weights_per_pixel

    model = MODELS[model_name]()
    scene = random_pose_scene(3, num_points=40, num_cameras=2, model=model)
    rng = np.random.default_rng(0)
    corr = _corr(scene, weight=rng.uniform(0.5, 2.0, len(scene.pixel)))
    T, theta = jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta)
    out = weights_per_pixel(corr, scene.cameras, model, T, theta)
    X = np.asarray(model_points_world(model, T, theta, corr.p_model, corr.part))
    cams = np.asarray(corr.camera)
    T_cw, K = np.asarray(scene.cameras.T_cam_world)[cams], np.asarray(scene.cameras.K)[cams]
    z = np.einsum("nj,nj->n", T_cw[:, 2, :3], X) + T_cw[:, 2, 3]
    assert np.all(z > 1.0) and len(np.unique(cams)) == 2
    np.testing.assert_allclose(np.asarray(out.weight), np.asarray(corr.weight) * K[:, 0, 0] * K[:, 1, 1] / z**2, rtol=1e-9)
    np.testing.assert_array_equal(np.asarray(weights_per_pixel(corr, scene.cameras, model, T, theta, on=0.0).weight),
                                  np.asarray(corr.weight))
    for leaf_in, leaf_out in zip(jax.tree.leaves(eqx.filter(corr, eqx.is_array)), jax.tree.leaves(eqx.filter(out, eqx.is_array))):
        assert leaf_in.shape == leaf_out.shape
