"""Normal equations of the Plücker-line cost (eq. 5): analytic Jacobian vs autodiff, H = JᵀWJ, and a
traced program whose size does not grow with the joint count (compile time; no timed tests)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtrack as jt
import jaxtrack.solve._pose_solver as pose_solver_module
from jaxtrack.solve import SolverConfig, make_correspondences, solve_pose
from jaxtrack.solve._moments import moment_normal_equations, plane_moments
from jaxtrack.solve._normal_equations import (
    RayDepths,
    line_planes,
    plane_normal_equations,
    plane_residuals,
    plane_residuals_and_jacobian,
)
from jaxtrack.synth import demo_chain, random_pose_scene

# The functions under test, each called as one compiled program per shape: called eagerly, each of their operations
# compiles on its own (150-210 XLA programs per test of this file before).
line_planes = eqx.filter_jit(line_planes)
plane_normal_equations = eqx.filter_jit(plane_normal_equations)
plane_residuals = eqx.filter_jit(plane_residuals)
plane_residuals_and_jacobian = eqx.filter_jit(plane_residuals_and_jacobian)
plane_moments = eqx.filter_jit(plane_moments)
moment_normal_equations = eqx.filter_jit(moment_normal_equations)

MODELS = {
    "rigid": lambda: jt.rigid_model(jnp.float64),
    "chain3": lambda: demo_chain(3, dtype=jnp.float64),
    "tree2x2": lambda: demo_chain(4, branches=2, dtype=jnp.float64),
}


def _problem(model, seed=3, num_points=40):
    scene = random_pose_scene(seed, num_points=num_points, noise_px=1.0, num_cameras=2, model=model)
    corr = make_correspondences(
        scene.cameras, scene.pixel, scene.p_model, camera_index=scene.camera_index, part=scene.part
    )
    normals, offsets, _ = line_planes(corr.n, corr.m)
    return scene, corr, normals, offsets


@pytest.mark.parametrize("model_name", list(MODELS))
def test_jacobian_matches_autodiff_of_the_residual(model_name):
    """Columns = d s / d(δ, Θ) with T = exp(δ̂) T0 (left increment of eq. 5), checked by jacfwd."""
    model = MODELS[model_name]()
    scene, corr, normals, offsets = _problem(model)
    T0 = jnp.asarray(scene.T_world_root)
    theta0 = jnp.asarray(scene.theta) + 0.05

    def s_of(y):
        return plane_residuals(model, jt.se3_exp(y[:6]) @ T0, y[6:], corr.p_model, corr.part, normals, offsets)

    y0 = jnp.concatenate([jnp.zeros(6), theta0])
    analytic = jax.jit(lambda T, th: plane_residuals_and_jacobian(model, T, th, corr.p_model, corr.part, normals, offsets))
    s, columns = analytic(T0, theta0)
    assert columns.shape == (model.num_dof, corr.capacity, 2)
    np.testing.assert_allclose(s, jax.jit(s_of)(y0), atol=1e-12)
    jac = jnp.moveaxis(columns, 0, -1)  # (N, 2, D), as jacfwd lays it out
    np.testing.assert_allclose(jac, jax.jit(jax.jacfwd(s_of))(y0), atol=1e-8, rtol=1e-8)
    # The plane form has the Plücker cost of eq. 4: Σ_k s_k² = |T X × n − m|².
    r = jt.solve.plucker_residuals(model, T0, theta0, corr)
    np.testing.assert_allclose(jnp.sum(s**2, axis=-1), jnp.sum(r**2, axis=-1), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("model_name", ["rigid", "tree2x2"])
def test_normal_equations_are_the_weighted_gauss_newton_system(model_name):
    model = MODELS[model_name]()
    scene, corr, normals, offsets = _problem(model, seed=5)
    weight = jnp.asarray(np.random.default_rng(0).uniform(0.0, 2.0, corr.capacity))
    T0, theta0 = jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta)
    H, g, cost = plane_normal_equations(model, T0, theta0, corr.p_model, corr.part, normals, offsets, weight)
    s, columns = plane_residuals_and_jacobian(model, T0, theta0, corr.p_model, corr.part, normals, offsets)
    J = np.moveaxis(np.asarray(columns), 0, -1).reshape(-1, model.num_dof)
    w = np.repeat(np.asarray(weight), 2)
    np.testing.assert_allclose(H, J.T @ (w[:, None] * J), rtol=1e-10)
    np.testing.assert_allclose(g, J.T @ (w * np.asarray(s).ravel()), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(cost, np.sum(w * np.asarray(s).ravel() ** 2), rtol=1e-12)
    np.testing.assert_allclose(H, H.T, rtol=1e-12)


def test_joint_off_the_path_has_a_zero_column():
    """A point's row only depends on the joints between the root and its part."""
    model = MODELS["tree2x2"]()
    scene, corr, normals, offsets = _problem(model)
    _, columns = plane_residuals_and_jacobian(
        model, jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta), corr.p_model, corr.part, normals, offsets
    )
    on_path = np.asarray(model.part_joints)[np.asarray(corr.part)]  # (N, J)
    joint_cols = np.abs(np.asarray(columns)[6:]).max(axis=-1).T  # (N, J)
    assert np.all(joint_cols[~on_path] == 0.0)
    assert np.all(joint_cols[on_path] > 0.0)


def _count_equations(jaxpr) -> int:
    """Equations of a jaxpr including every nested sub-jaxpr (while bodies, custom_root, pjit)."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)
                if isinstance(inner, jax.extend.core.Jaxpr):
                    total += _count_equations(inner)
    return total


def _solve_program_size(num_joints: int, rows: bool = False) -> int:
    model = demo_chain(num_joints, link_length=12.0, dtype=jnp.float64) if num_joints else jt.rigid_model(jnp.float64)
    capacity = 64
    corr = make_correspondences(
        jt.synth.camera_ring(1, dtype=np.float64),
        np.zeros((capacity, 2)),
        np.zeros((capacity, 3)),
        part=np.arange(capacity) % model.num_parts,
    )
    origins = jnp.zeros((1, 3)) if rows else None  # with ray origins: the rows summed at every iterate
    closed = jax.make_jaxpr(lambda c, T, th: solve_pose(model, c, T, th, ray_origins=origins))(
        corr, jnp.eye(4), jnp.zeros(model.num_joints)
    )
    return _count_equations(closed.jaxpr)


def test_solver_program_size_is_flat_in_the_joint_count():
    """Compile time follows the traced program: J = 24 (a body) must stay within 2x of J = 0.

    The builder of 33dcef2 traced D(D+1)/2 products and one column per joint (grew with (6 + J)²). Both builders:
    the per-part moments of eq. 4 as it is, and the rows summed at every iterate (depth-scaled residuals).
    """
    for rows in (False, True):
        sizes = {j: _solve_program_size(j, rows) for j in (0, 24)}
        assert sizes[24] < 2 * sizes[0], (rows, sizes)


@pytest.mark.parametrize("model_name", ["rigid", "chain3"])
def test_depth_invariant_normal_equations_are_the_gauss_newton_system_of_the_scaled_residual(model_name):
    """With `RayDepths`: s · (Z₀/z)^p and its analytic columns (through H, g, cost) against jacfwd of the residual."""
    model = MODELS[model_name]()
    scene, corr, normals, offsets = _problem(model, seed=7)
    origins = jnp.asarray(scene.cameras.center_world)[corr.camera]
    offset = jnp.sum(corr.n * origins, -1)
    T0, theta0 = jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta)
    a0 = jt.solve.model_points_world(model, T0, theta0, corr.p_model, corr.part)
    # A reference depth 20 % off the depth at T0: the scale and its derivative both matter.
    depths = RayDepths(offset, 1.2 * (jnp.sum(corr.n * a0, -1) - offset), jnp.asarray(0.7))
    weight = jnp.asarray(np.random.default_rng(1).uniform(0.5, 2.0, corr.capacity))

    def s_of(y):
        return plane_residuals(model, jt.se3_exp(y[:6]) @ T0, y[6:], corr.p_model, corr.part, normals, offsets, depths, corr.n)

    y0 = jnp.concatenate([jnp.zeros(6), theta0])
    s = s_of(y0)
    plain = plane_residuals(model, T0, theta0, corr.p_model, corr.part, normals, offsets)
    np.testing.assert_allclose(s, plain * 1.2**0.7, rtol=1e-9)  # z = Z₀ / 1.2 at T0
    J = np.asarray(jax.jit(jax.jacfwd(s_of))(y0)).reshape(-1, model.num_dof)
    w = np.repeat(np.asarray(weight), 2)
    H, g, cost = plane_normal_equations(model, T0, theta0, corr.p_model, corr.part, normals, offsets, weight, depths, corr.n)
    np.testing.assert_allclose(H, J.T @ (w[:, None] * J), rtol=1e-8, atol=1e-8 * np.abs(H).max())
    np.testing.assert_allclose(g, J.T @ (w * np.asarray(s).ravel()), rtol=1e-8, atol=1e-8 * np.abs(g).max())
    np.testing.assert_allclose(cost, np.sum(w * np.asarray(s).ravel() ** 2), rtol=1e-10)


def test_depth_invariant_solve_does_not_slide_the_object_toward_the_camera():
    """Rows that disagree (every other point seen 120 px to the side), weighted alike: eq. 4 fits them best by moving
    the object toward the camera (every distance across the rays shrinks: 0.59 of the depth); the depth-invariant
    residual keeps the depth within 15 % (1.11)."""
    model = jt.rigid_model(jnp.float64)
    scene = random_pose_scene(11, num_points=60, noise_px=0.0, num_cameras=1, model=model)
    pixel = np.asarray(scene.pixel, np.float64).copy()
    pixel[::2, 0] += 120.0
    corr = make_correspondences(scene.cameras, jnp.asarray(pixel), scene.p_model, camera_index=scene.camera_index,
                                part=scene.part)
    T0 = jnp.asarray(scene.T_world_root)
    centre = np.asarray(scene.cameras.center_world)[0]
    depth = lambda T: float(np.linalg.norm(np.asarray(T)[:3, 3] - centre))
    config = SolverConfig(max_steps=50)
    plain = solve_pose(model, corr, T0, config=config)
    # p as arrays: one compiled solve for both.
    invariant = solve_pose(model, corr, T0, config=config, ray_origins=scene.cameras.center_world,
                           depth_invariance=jnp.asarray(1.0))
    off = solve_pose(model, corr, T0, config=config, ray_origins=scene.cameras.center_world,
                     depth_invariance=jnp.asarray(0.0))
    assert jt.is_usable(plain.status) and jt.is_usable(invariant.status)
    assert depth(plain.T_world_root) < 0.7 * depth(T0)  # the collapse this option exists for
    assert abs(depth(invariant.T_world_root) / depth(T0) - 1.0) < 0.15
    np.testing.assert_allclose(off.T_world_root, plain.T_world_root, atol=1e-6)  # p = 0 is eq. 4


@pytest.mark.parametrize("model_name", list(MODELS))
def test_moments_of_the_rows_give_their_normal_equations_at_any_iterate(model_name):
    """The per-part moments taken at one pose give H, g and the cost of the rows at another (eq. 5): the rows summed
    once per solve instead of at every Gauss-Newton iterate."""
    model = MODELS[model_name]()
    scene, corr, normals, offsets = _problem(model, seed=9)
    rng = np.random.default_rng(2)
    weight = jnp.asarray(rng.uniform(0.0, 2.0, (corr.capacity, 2)) * (rng.uniform(size=(corr.capacity, 1)) > 0.2))
    T0, theta0 = jnp.asarray(scene.T_world_root), jnp.asarray(scene.theta)
    moments = plane_moments(model, T0, theta0, corr.p_model, corr.part, normals, offsets, weight)
    assert moments.Q.shape == (model.num_parts, 13, 13)
    np.testing.assert_allclose(moments.Q, np.swapaxes(np.asarray(moments.Q), 1, 2), rtol=0, atol=0)
    T1 = jt.se3_exp(jnp.asarray([8.0, -5.0, 12.0, 0.05, -0.08, 0.03])) @ T0  # mm, rad: a step a solve takes
    for T, theta in ((T0, theta0), (T1, theta0 + 0.1)):
        want = plane_normal_equations(model, T, theta, corr.p_model, corr.part, normals, offsets, weight)
        got = moment_normal_equations(model, T, theta, moments)
        for a, b in zip(got, want):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(np.asarray(b)).max())


@pytest.mark.parametrize("model_name", ["rigid", "tree2x2"])
def test_moments_keep_float32_precision_metres_from_the_origin(model_name):
    """In float32, with the object 3 m from the world origin, residuals of a few mm and the iterate a solve's step from
    the moments' pose, H and g keep the precision of the float32 rows: each entry within 2e-5 of √(H_ii H_jj) (g of
    √(H_ii cost)) of the float64 rows', and the cost within 1e-4. Uncentred moments lost H's joint entries
    ((|a| / limb)² of cancellation: 1.2e-4 in a probe of this kind) and the cost (1e-4, steps of ω × t)."""
    model = MODELS[model_name]()
    scene, corr, _, _ = _problem(model, seed=4, num_points=400)
    shift = jnp.eye(4, dtype=jnp.float64).at[:3, 3].set(jnp.asarray([2000.0, -1500.0, 1800.0]))
    T_true = shift @ jnp.asarray(scene.T_world_root)
    theta_true = jnp.asarray(scene.theta)
    rng = np.random.default_rng(5)
    a = jt.solve.model_points_world(model, T_true, theta_true, corr.p_model, corr.part)
    a = a + jnp.asarray(rng.normal(size=a.shape) * 2.0)  # mm
    centre = jnp.asarray(shift[:3, 3]) + jnp.asarray([0.0, 0.0, -1500.0])
    n = (a - centre) / jnp.linalg.norm(a - centre, axis=-1, keepdims=True)
    normals, offsets, _ = line_planes(n, jnp.cross(a, n))
    weight = jnp.asarray(rng.uniform(0.5, 2.0, corr.capacity))
    T0 = jt.se3_exp(jnp.asarray([6.0, -4.0, 5.0, 0.02, -0.015, 0.01])) @ T_true  # the solve's start
    theta0 = theta_true + 0.03
    T1 = jt.se3_exp(jnp.asarray([-1.0, 1.5, 0.5, -0.004, 0.003, 0.002])) @ T_true  # an iterate near the optimum
    theta1 = theta_true - 0.005
    H, g, cost = plane_normal_equations(model, T1, theta1, corr.p_model, corr.part, normals, offsets, weight)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    moments = plane_moments(model, f32(T0), f32(theta0), f32(corr.p_model), corr.part, f32(normals), f32(offsets),
                            f32(weight))
    H32, g32, cost32 = (np.asarray(x, np.float64) for x in moment_normal_equations(model, f32(T1), f32(theta1), moments))
    d = np.sqrt(np.diag(np.asarray(H)))
    assert np.max(np.abs(H32 - np.asarray(H)) / np.outer(d, d)) < 2e-5
    assert np.max(np.abs(g32 - np.asarray(g)) / (d * np.sqrt(float(cost)))) < 2e-5
    assert abs(cost32 - float(cost)) < 1e-4 * float(cost)


def test_a_chain_solved_from_moments_equals_the_solve_that_sums_its_rows_at_every_iterate():
    """`solve_pose` on eq. 4 as it is takes the moments path (`moments_from_rows` 0: whatever the rows; with a joint
    prior and a pose prior, whose stiffnesses read H at the start); with the cameras' centres and p = 0 it sums the
    rows at every iterate: the same pose. With the default threshold these 40 rows take the rows path."""
    model = MODELS["chain3"]()
    scene, corr, _, _ = _problem(model, seed=6)
    T0 = jt.se3_exp(jnp.asarray([6.0, -4.0, 5.0, 0.04, 0.03, -0.02])) @ jnp.asarray(scene.T_world_root)
    theta0 = jnp.asarray(scene.theta) + 0.08
    options = {"config": SolverConfig(max_steps=30, moments_from_rows=0), "prior": jt.solve.JointPrior(theta0, jnp.asarray(0.05)),
                   "pose_prior": jt.solve.PosePrior(T0, jnp.asarray(0.02), jnp.asarray(0.02))}
    moments = solve_pose(model, corr, T0, theta0, **options)
    rows = solve_pose(model, corr, T0, theta0, ray_origins=scene.cameras.center_world, depth_invariance=0.0, **options)
    assert jt.is_usable(moments.status) and int(moments.num_steps) == int(rows.num_steps)
    np.testing.assert_allclose(moments.T_world_root, rows.T_world_root, atol=1e-8)
    np.testing.assert_allclose(moments.theta, rows.theta, atol=1e-10)
    np.testing.assert_allclose(moments.cost, rows.cost, rtol=1e-8)
    calls = []
    original = pose_solver_module.plane_moments
    pose_solver_module.plane_moments = lambda *a, **k: calls.append(1) or original(*a, **k)
    try:
        jax.make_jaxpr(lambda c: solve_pose(model, c, T0, theta0, config=SolverConfig(max_steps=30)))(corr)
        assert not calls  # 40 rows < SolverConfig.moments_from_rows
        jax.make_jaxpr(lambda c: solve_pose(model, c, T0, theta0, config=options["config"]))(corr)
        assert calls
    finally:
        pose_solver_module.plane_moments = original
