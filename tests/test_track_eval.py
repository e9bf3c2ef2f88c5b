"""Cue fusion weights (Section V) and the evaluation metrics of the tracker."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack.geometry import make_transform, so3_exp
from jaxtrack.solve import Correspondences, Cue
from jaxtrack.track import (
    CueWeights,
    add_error,
    adds_error,
    fuse_cue_weights,
    model_diameter,
    pose_errors,
    precision_recall,
    success_mask,
)


def _set(cues, weights):
    n = len(cues)
    z3 = jnp.zeros((n, 3))
    return Correspondences(
        n=z3, m=z3, p_model=z3, part=jnp.zeros(n, jnp.int32), camera=jnp.zeros(n, jnp.int32),
        pixel=jnp.zeros((n, 2)), weight=jnp.asarray(weights, jnp.float64), cue=jnp.asarray(cues, jnp.int32),
    )


def test_fusion_follows_section_v():
    # 4 contour rows (one padding), 2 flow rows with confidences 0.5 and 2, 3 SIFT rows.
    R, F, S = Cue.REGION, Cue.FLOW, Cue.SIFT
    corr = _set([R, R, R, R, R, F, F, S, S, S], [1, 1, 1, 1, 0, 0.5, 2.0, 1, 1, 1])
    w = np.asarray(fuse_cue_weights(corr, CueWeights()).weight)
    n_c, n_of = 4, 2
    np.testing.assert_allclose(w[:5], [1, 1, 1, 1, 0])
    np.testing.assert_allclose(w[5:7], np.array([0.5, 2.0]) * n_c / n_of)
    np.testing.assert_allclose(w[7:], 0.002 * n_c)
    # Prediction: n_C replaced by n_OF.
    w = np.asarray(fuse_cue_weights(corr, CueWeights(), prediction=True).weight)
    np.testing.assert_allclose(w[5:7], [0.5, 2.0])
    np.testing.assert_allclose(w[7:], 0.002 * n_of)
    # User factors multiply each cue; a sweep over factors is one vmapped call.
    factors = jax.vmap(lambda f: CueWeights(flow=f, sift=2 * f))(jnp.linspace(0.0, 2.0, 5))
    sweep = jax.vmap(lambda fw: fuse_cue_weights(corr, fw).weight)(factors)
    np.testing.assert_allclose(sweep[:, 5], np.linspace(0, 2, 5) * 0.5 * n_c / n_of)
    np.testing.assert_allclose(sweep[:, 7], 2 * np.linspace(0, 2, 5) * 0.002 * n_c)


def test_fusion_without_flow_or_contour_gives_zero_not_nan():
    corr = _set([Cue.SIFT, Cue.SIFT], [1.0, 1.0])
    w = fuse_cue_weights(corr, CueWeights()).weight
    assert np.all(np.isfinite(w)) and np.all(np.asarray(w) == 0.0)
    g = jax.grad(lambda f: jnp.sum(fuse_cue_weights(corr, CueWeights(flow=f)).weight))(1.0)
    assert np.isfinite(g)


def test_pose_errors_and_add():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3)) * 50
    T_gt = np.stack([make_transform(np.asarray(so3_exp(jnp.asarray(rng.normal(size=3)))), rng.normal(size=3) * 100)
                     for _ in range(3)])
    delta = make_transform(np.asarray(so3_exp(jnp.array([0.0, 0.0, np.radians(2.0)]))), np.array([3.0, 0, 4]))
    T_est = np.einsum("ij,fjk->fik", np.asarray(delta), T_gt)
    rot, trans = pose_errors(T_est, T_gt)
    np.testing.assert_allclose(rot, 2.0, atol=1e-6)
    # A left perturbation moves the translation by R_d t + t_d − t.
    np.testing.assert_allclose(trans, np.linalg.norm(T_est[:, :3, 3] - T_gt[:, :3, 3], axis=-1))
    add = add_error(T_est, T_gt, pts)
    adds = adds_error(T_est, T_gt, pts)
    assert np.all(adds <= add + 1e-9) and np.all(add > 0)
    np.testing.assert_allclose(add_error(T_gt, T_gt, pts), 0.0, atol=1e-9)
    np.testing.assert_allclose(adds_error(T_gt, T_gt, pts), 0.0, atol=1e-6)


def test_adds_is_blind_to_symmetry():
    # A cube's vertices map onto themselves under a 90° turn: ADD sees an error, ADD-S none.
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * 10
    turn = make_transform(np.asarray(so3_exp(jnp.array([0.0, 0.0, np.pi / 2]))), np.zeros(3))[None]
    eye = np.eye(4)[None]
    assert add_error(turn, eye, cube)[0] > 10
    assert adds_error(turn, eye, cube)[0] == pytest.approx(0.0, abs=1e-6)
    assert model_diameter(cube) == pytest.approx(20 * np.sqrt(3))


def test_success_and_status_quality():
    ok = success_mask([1.0, 6.0, 1.0], [10.0, 10.0, 60.0])
    np.testing.assert_array_equal(ok, [True, False, False])
    p, r = precision_recall([True, True, False, False], [True, False, True, False])
    assert (p, r) == (0.5, 0.5)
    p, r = precision_recall([False, False], [False, False])
    assert np.isnan(p) and np.isnan(r)
    with pytest.raises(ValueError, match="T_est"):
        pose_errors(np.eye(4), np.eye(4)[None])


def test_failure_episodes_count_frames_until_back():
    from jaxtrack.track import failure_episodes

    assert failure_episodes([0, 1, 1, 0, 0, 1, 0, 1, 1, 1]) == [(2, True), (1, True), (3, False)]
    assert failure_episodes([0, 0]) == [] and failure_episodes([]) == []
    rng = np.random.default_rng(0)
    for _ in range(20):  # every failed frame is in exactly one run; only the last run can be unfinished
        failed = rng.random(30) < 0.4
        runs = failure_episodes(failed)
        assert sum(n for n, _ in runs) == failed.sum()
        assert all(back for _, back in runs[:-1]) and (not runs or runs[-1][1] == (not failed[-1]))
