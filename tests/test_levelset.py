"""Region cue (eq. 11-15): energy/update consistency, densities, shape matching, segmentation and
region-only refinement (rigid, two cameras, a 2-joint chain), compile counts."""

import itertools

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack._status import Status
from jaxtrack.cues.levelset import (
    RegionConfig,
    RegionRefiner,
    closest_point_matches,
    closest_point_matches_at,
    contour_pixels,
    data_term,
    evolve,
    feature_channels,
    levelset_energy,
    levelset_update,
    local_densities,
    log_likelihoods,
    nearest_seed_points,
    refine_pose_region,
    region_membership,
    region_params,
    regularised_matches,
    smoothed_features,
    time_step,
)
from jaxtrack.geometry import chain_model, make_camera, se3_exp, stack_cameras
from jaxtrack.image import silhouette_sdf
from jaxtrack.render import Renderer, make_mesh
from jaxtrack.synth import look_at


def _disc_sdf(h, w, cx, cy, r):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return r - np.hypot(xx - cx, yy - cy)


# ----------------------------------------------------------------------------------------------
# Energy and descent (eq. 11, 13)


def _toy_problem(seed=0, h=24, w=28):
    rng = np.random.default_rng(seed)
    phi0 = _disc_sdf(h, w, 13.3, 11.7, 7.0)
    phi = phi0 + rng.normal(scale=0.7, size=phi0.shape)
    img = np.where(_disc_sdf(h, w, 14.5, 12.0, 7.5) > 0, 180.0, 60.0) + rng.normal(scale=10, size=phi0.shape)
    feats = jnp.asarray(img[..., None])
    params = region_params((h, w), jnp.float64, rho=4.0)
    dens = local_densities(feats, region_membership(jnp.asarray(phi0)), params.rho, params.kappa, params.sigma_min, factor=1)
    return jnp.asarray(phi), jnp.asarray(phi0), feats, dens, params


def test_update_is_minus_energy_gradient():
    phi, phi0, feats, dens, params = _toy_problem()
    log_p = log_likelihoods(feats, dens, factor=1)
    grad = jax.grad(levelset_energy)(phi, phi0, log_p, params)
    update = levelset_update(phi, phi0, log_p[0] - log_p[1], params)
    band = jnp.abs(phi) < 3.0
    assert int(band.sum()) > 50
    np.testing.assert_allclose(np.asarray(update), -np.asarray(grad), rtol=1e-9, atol=1e-10)
    # A small step along the update lowers the energy.
    e0 = levelset_energy(phi, phi0, log_p, params)
    e1 = levelset_energy(phi + 1e-3 * update, phi0, log_p, params)
    assert float(e1) < float(e0)


def test_energy_decreases_over_iterations():
    _, phi0, feats, dens, params = _toy_problem(1)
    phi = jnp.asarray(_disc_sdf(24, 28, 11.0, 10.0, 6.0))  # a signed distance function, off target
    log_p = log_likelihoods(feats, dens, factor=1)
    force = log_p[0] - log_p[1]
    energies = [float(levelset_energy(phi, phi0, log_p, params))]
    step = jax.jit(lambda p: evolve(p, phi0, force, params, iterations=1, redistance_every=1))
    dt = float(time_step(params))
    assert dt > 0
    p = phi
    # Plain clipped descent steps (no re-distancing) decrease the energy monotonically.
    for _ in range(10):
        p = p + jnp.clip(dt * levelset_update(p, phi0, force, params), -params.max_step, params.max_step)
        energies.append(float(levelset_energy(p, phi0, log_p, params)))
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(energies)), energies
    # With re-distancing the energy still ends far below the start.
    q = phi
    for _ in range(10):
        q = step(q)
    assert float(levelset_energy(q, phi0, log_p, params)) < energies[0]


def test_params_vmap_without_recompiling():
    phi, phi0, feats, dens, params = _toy_problem(2)
    force = data_term(feats, dens, factor=1)
    lams = jnp.asarray([0.0, 0.05, 0.5])
    out = jax.vmap(lambda lam: levelset_update(phi, phi0, force, eqx.tree_at(lambda p: p.lam, params, lam)))(lams)
    assert out.shape == (3,) + phi.shape
    # More shape prior pulls harder towards Φ0.
    pull = [float(jnp.sum((o - 0) * (phi0 - phi))) for o in out]
    assert pull[0] < pull[1] < pull[2]


# ----------------------------------------------------------------------------------------------
# Local densities (eq. 12)


def _direct_densities(feats, weight, rho, kappa, sigma_min):
    """Per-pixel normalised Gaussian sums in numpy (the definition of eq. 12 with the κ blend)."""
    h, w, k = feats.shape
    yy, xx = np.mgrid[0:h, 0:w]
    mean = np.zeros((2, h, w, k))
    var = np.zeros((2, h, w, k))
    for r, wr in enumerate((weight, 1.0 - weight)):
        g_mean = (wr[..., None] * feats).sum((0, 1)) / wr.sum()
        g_sq = (wr[..., None] * feats**2).sum((0, 1)) / wr.sum()
        for y in range(h):
            for x in range(w):
                g = np.exp(-0.5 * ((yy - y) ** 2 + (xx - x) ** 2) / rho**2) / (2 * np.pi * rho**2) * wr
                s0 = g.sum()
                m = ((g[..., None] * feats).sum((0, 1)) + kappa * g_mean) / (s0 + kappa)
                sq = ((g[..., None] * feats**2).sum((0, 1)) + kappa * g_sq) / (s0 + kappa)
                mean[r, y, x] = m
                var[r, y, x] = np.maximum(sq - m**2, sigma_min**2)
    return mean, var


def test_local_densities_match_direct_sum():
    rng = np.random.default_rng(3)
    h, w = 16, 20
    feats = rng.uniform(0, 255, size=(h, w, 2))
    weight = np.clip(0.5 + _disc_sdf(h, w, 9, 8, 5), 0, 1)
    for kappa in (0.0, 0.05):
        mean, var = _direct_densities(feats, weight, 3.0, kappa, 2.0)
        dens = local_densities(jnp.asarray(feats), jnp.asarray(weight), jnp.asarray(3.0), jnp.asarray(kappa), jnp.asarray(2.0), 1)
        np.testing.assert_allclose(np.asarray(dens.mean), mean, rtol=1e-9)
        np.testing.assert_allclose(np.asarray(dens.var), var, rtol=1e-9)


def test_coarse_densities_close_to_exact():
    """The factor-4 grid (the default, for speed) against the exact ρ = 12 normalised convolution."""
    rng = np.random.default_rng(4)
    h, w = 64, 64
    base = np.where(_disc_sdf(h, w, 30, 34, 18) > 0, 170.0, 70.0)
    feats = jnp.asarray((base + rng.normal(scale=15, size=(h, w)))[..., None])
    weight = jnp.asarray(np.clip(0.5 + _disc_sdf(h, w, 31, 33, 17), 0, 1))
    args = (jnp.asarray(12.0), jnp.asarray(0.05), jnp.asarray(5.0))
    exact = data_term(feats, local_densities(feats, weight, *args, 1), 1)
    coarse = data_term(feats, local_densities(feats, weight, *args, 4), 4)
    # Same sign almost everywhere (the force decides the motion), small relative difference.
    agree = np.mean(np.sign(np.asarray(exact)) == np.sign(np.asarray(coarse)))
    assert agree > 0.98, agree
    rel = np.median(np.abs(np.asarray(exact - coarse)) / (np.abs(np.asarray(exact)) + 1))
    assert rel < 0.1, rel


# ----------------------------------------------------------------------------------------------
# Shape matching (eq. 14-15)


def test_nearest_seed_points_brute_force():
    rng = np.random.default_rng(5)
    seeds = rng.random((37, 45)) < 0.02
    near = np.asarray(nearest_seed_points(jnp.asarray(seeds)))
    sy, sx = np.nonzero(seeds)
    yy, xx = np.mgrid[0:37, 0:45]
    d_brute = np.sqrt(np.min((yy[..., None] - sy) ** 2 + (xx[..., None] - sx) ** 2, axis=-1))
    d_jfa = np.hypot(near[..., 0] - yy, near[..., 1] - xx)
    assert np.all(seeds[near[..., 0].astype(int), near[..., 1].astype(int)])
    assert np.mean(np.abs(d_jfa - d_brute) < 1e-6) > 0.99
    assert np.max(d_jfa - d_brute) < 1.0


def test_closest_point_matches_circle():
    """Φ0 a disc, Φ the disc shifted: matches equal the analytic closest points on Φ's circle."""
    h, w = 64, 64
    phi0 = _disc_sdf(h, w, 30.2, 31.6, 14.0)
    phi = _disc_sdf(h, w, 33.0, 30.1, 15.5)
    d = np.asarray(closest_point_matches(jnp.asarray(phi0), jnp.asarray(phi)))
    ys, xs = np.nonzero(np.asarray(contour_pixels(jnp.asarray(phi0))) & (phi0 > 0))
    # Source: the pixel moved onto Φ0's circle; target: its closest point on Φ's circle.
    src = np.stack([xs, ys], -1).astype(float)
    c0 = np.array([30.2, 31.6])
    src = c0 + 14.0 * (src - c0) / np.linalg.norm(src - c0, axis=1, keepdims=True)
    c1 = np.array([33.0, 30.1])
    tgt = c1 + 15.5 * (src - c1) / np.linalg.norm(src - c1, axis=1, keepdims=True)
    err = np.linalg.norm(d[ys, xs] - (tgt - src), axis=1)
    # Measured: median 0.005 px; a few pixels fall back to the jump-flooding guess (≤ 2.6 px off).
    assert np.median(err) < 0.02 and np.mean(err < 0.1) > 0.95 and np.max(err) < 3.0, (np.median(err), np.sort(err)[-5:])
    # Identical contours give exactly zero matches (source and target are projected by the same
    # operator; before, 162 of 263 contour pixels of a box silhouette got non-zero matches).
    same = np.asarray(closest_point_matches(jnp.asarray(phi0), jnp.asarray(phi0)))[ys, xs]
    assert np.max(np.abs(same)) == 0.0


def test_sparse_closest_points_against_brute_force():
    """The refinement's sparse matcher (Newton projection at the contour pixels only) against a
    brute-force nearest point on a densely sampled circle, Φ the circle's exact signed distance."""
    h, w = 64, 64
    phi0 = _disc_sdf(h, w, 30.2, 31.6, 14.0)
    c1, r1 = np.array([33.0, 30.1]), 15.5
    phi = _disc_sdf(h, w, c1[0], c1[1], r1)
    ys, xs = np.nonzero(np.asarray(contour_pixels(jnp.asarray(phi0))) & (phi0 > 0))
    pixels = jnp.asarray(np.stack([xs, ys], -1), jnp.float64)
    d, ok, normal = (np.asarray(a) for a in closest_point_matches_at(jnp.asarray(phi0), jnp.asarray(phi), pixels))
    c0 = np.array([30.2, 31.6])
    src = np.stack([xs, ys], -1).astype(float)
    src = c0 + 14.0 * (src - c0) / np.linalg.norm(src - c0, axis=1, keepdims=True)
    t = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    circle = c1 + r1 * np.stack([np.cos(t), np.sin(t)], -1)
    nearest = circle[np.argmin(np.linalg.norm(src[:, None] - circle[None], axis=-1), axis=1)]
    err = np.linalg.norm(src + d - nearest, axis=1)
    assert ok.all(), ok.mean()
    assert np.median(err) < 0.02 and np.max(err) < 0.1, (np.median(err), np.max(err))
    # The normal is ∇Φ/|∇Φ| at the match: Φ > 0 inside, so the circle's inward radial direction.
    radial = (nearest - c1) / r1
    assert np.min(np.sum(normal * -radial, 1)) > 0.99
    # Identical contours: exactly zero.
    same, ok_same, _ = closest_point_matches_at(jnp.asarray(phi0), jnp.asarray(phi0), pixels)
    assert np.max(np.abs(np.asarray(same))) == 0.0 and np.asarray(ok_same).all()


def test_regularised_matches_ignore_spike():
    h, w = 72, 72
    shift = np.array([2.0, 0.0])
    phi0 = _disc_sdf(h, w, 34.0, 36.0, 16.0)
    sil = _disc_sdf(h, w, 36.0, 36.0, 16.0) > 0
    sil[35:38, 8:22] = True  # a thin spike out of the shifted disc's left side, across Φ0's contour
    phi = np.asarray(silhouette_sdf(jnp.asarray(sil)), np.float64)
    ys, xs = np.nonzero(np.asarray(contour_pixels(jnp.asarray(phi0))) & (phi0 > 0))
    near_spike = (np.abs(ys - 36) <= 6) & (xs < 26)
    assert near_spike.sum() >= 4
    closest = np.asarray(closest_point_matches(jnp.asarray(phi0), jnp.asarray(phi)))[ys, xs]
    regular = np.asarray(regularised_matches(jnp.asarray(phi0), jnp.asarray(phi), jnp.asarray(10.0)))[ys, xs]
    err_c = np.linalg.norm(closest - shift, axis=1)
    err_r = np.linalg.norm(regular - shift, axis=1)
    # Near the spike the closest points jump onto it; the regularised field stays nearer the shift
    # (measured: worst 1.21 px vs 2.19 px, mean 1.0 vs 1.6 px).
    assert err_r[near_spike].max() < 0.7 * err_c[near_spike].max(), (err_r[near_spike].max(), err_c[near_spike].max())
    assert err_r[near_spike].mean() < err_c[near_spike].mean()
    # Measured median 1.03 px from the true 2-px shift: 5 warps x 60 Jacobi sweeps under-resolve it.
    assert np.median(err_r) < 1.2


# ----------------------------------------------------------------------------------------------
# Segmentation and region-only refinement on synthetic frames


def _background(h, w):
    import skimage.data

    return cv2.resize(skimage.data.coffee(), (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)


def _paint(renderer, mesh, T, theta, h, w, colour=(215.0, 185.0, 60.0)):
    """A noise-free frame: the object shaded by face orientation over the coffee photo."""
    out = renderer(jnp.asarray(T), None if theta is None else jnp.asarray(theta))
    fid = np.asarray(out.face_id)
    v = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    shade = 0.65 + 0.35 * np.abs(n @ np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
    img = _background(h, w)
    hit = fid >= 0
    img[hit] = np.asarray(colour) * shade[fid[hit], None]
    return img, hit


def _chain_mesh():
    parts = []
    for k, (x0, x1) in enumerate(((-60.0, 50.0), (50.0, 130.0), (130.0, 200.0))):
        sx, sy, sz = (x1 - x0) / 2, 22.0 - 4 * k, 22.0 - 4 * k
        cx = (x0 + x1) / 2
        v = np.array([[cx + a, b, c] for a in (-sx, sx) for b in (-sy, sy) for c in (-sz, sz)])
        parts.append(v)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    verts = np.concatenate(parts)
    all_faces = np.concatenate([faces + 8 * k for k in range(3)])
    return make_mesh(verts, all_faces, vertex_part=np.repeat(np.arange(3), 8), dtype=jnp.float64)


def _box_mesh():
    v = np.array([[x, y, z] for x in (-70.0, 70.0) for y in (-45.0, 45.0) for z in (-35.0, 35.0)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    return make_mesh(v, faces, dtype=jnp.float64)


H, W, F = 144, 192, 380.0


def _camera(R=None, t=None, w=W, h=H, f=F):
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    return make_camera(K, w, h, R, t, dtype=jnp.float64)


def _pose(rot, trans):
    return np.asarray(se3_exp(jnp.asarray(np.concatenate([trans, rot]))))


def _mean_vertex_error(mesh, model, T_a, th_a, T_b, th_b):
    from jaxtrack.geometry import part_transforms

    v = np.asarray(mesh.vertices)
    part = np.asarray(mesh.vertex_part)
    Ta = np.asarray(part_transforms(model, jnp.asarray(T_a), jnp.asarray(th_a)))[part]
    Tb = np.asarray(part_transforms(model, jnp.asarray(T_b), jnp.asarray(th_b)))[part]
    pa = np.einsum("vij,vj->vi", Ta[:, :3, :3], v) + Ta[:, :3, 3]
    pb = np.einsum("vij,vj->vi", Tb[:, :3, :3], v) + Tb[:, :3, 3]
    return float(np.linalg.norm(pa - pb, axis=1).mean())


@pytest.fixture(scope="module")
def rigid_scene():
    mesh = _box_mesh()
    cam = _camera()
    T_true = _pose([0.5, 0.6, 0.2], [5.0, -4.0, 0.0])
    T_true = T_true.copy()
    T_true[2, 3] += 520.0
    img, mask = _paint(Renderer(mesh, cam), mesh, T_true, None, H, W)
    refiner = RegionRefiner(mesh, cam)
    return {"mesh": mesh, "cam": cam, "T": T_true, "img": img, "mask": mask, "refiner": refiner}


def _perturb(T, scale, direction=(1.0, 1.0, 1.0, 0.05, 0.05, 0.05)):
    # The paper's Fig. 6 twist (mm, rad), applied in the object frame.
    return T @ np.asarray(se3_exp(jnp.asarray(0.01 * scale * np.asarray(direction) * [10, 10, 10, 10, 10, 10])))


def test_segmentation_iou_homogeneous_object(shared_data):
    """A flat-coloured (shaded) teapot on the coffee photo from `jaxtrack.synth`, shape prior from a
    pose θ = 10 off (Fig. 6 twist, ~6 mm / 6°): IoU against the generator's mask."""
    from jaxtrack.cues.levelset import RegionConfig as _RC
    from jaxtrack.cues.levelset import segment
    from jaxtrack.synth import SynthConfig, render_sequence

    w, h = 320, 240  # the teapot ~130 px wide: IoU is boundary-limited on smaller objects
    cfg = SynthConfig(
        object="teapot", appearance="flat", colour=(210, 180, 60), background="coffee", frames=1,
        width=w, height=h, focal=450.0, motion="turntable",
    )
    seq = render_sequence(cfg)
    mesh = make_mesh(seq["mesh"].vertices, seq["mesh"].faces, dtype=jnp.float64)
    cam = make_camera(seq["K"], w, h, dtype=jnp.float64)
    T_true = seq["T_cam_obj"][0][0]
    T0 = _perturb(T_true, 10.0)
    sil0 = np.asarray(Renderer(mesh, cam)(jnp.asarray(T0)).face_id >= 0)
    gt = seq["object_mask"][0][0]
    params = region_params((h, w), jnp.float64)

    @jax.jit  # one program, not one per operation
    def prepare(image, silhouette):
        feats = feature_channels(image)
        phi0 = silhouette_sdf(silhouette).astype(jnp.float64)
        return feats, phi0, local_densities(feats, region_membership(phi0), params.rho, params.kappa, params.sigma_min, 4)

    feats, phi0, dens = prepare(jnp.asarray(seq["images"][0][0], jnp.float64), jnp.asarray(sil0))
    phi = phi0
    run = jax.jit(lambda p, d: segment(feats, phi0, p, d, params, _RC(levelset_iterations=20)))
    for _ in range(5):
        phi, dens = run(phi, dens)
    seg = np.asarray(phi) > 0
    iou0 = (sil0 & gt).sum() / (sil0 | gt).sum()
    iou = (seg & gt).sum() / (seg | gt).sum()
    assert iou > iou0 and iou >= 0.95, (iou0, iou)


def test_refine_rigid_one_camera(rigid_scene):
    s = rigid_scene
    model = s["refiner"].model
    for scale in (3.0,):
        T0 = _perturb(s["T"], scale)
        s["refiner"].reset()
        res, _ = s["refiner"](s["img"], T0)
        e0 = _mean_vertex_error(s["mesh"], model, T0, np.zeros(0), s["T"], np.zeros(0))
        e1 = _mean_vertex_error(s["mesh"], model, np.asarray(res.T_world_root), np.zeros(0), s["T"], np.zeros(0))
        # Measured: 1.89 → 0.77 mm (one camera: depth is weakly constrained by a contour).
        assert e1 < 0.5 * e0 and e1 < 1.0, (scale, e0, e1, int(res.status))


def test_refine_rigid_two_cameras(rigid_scene):
    s = rigid_scene
    R1, t1 = look_at([400.0, 0.0, 0.0], target=(0.0, 0.0, 520.0))
    cams = stack_cameras([_camera(), _camera(R1, t1)])
    from jaxtrack.geometry import select_camera

    imgs = np.stack([_paint(Renderer(s["mesh"], select_camera(cams, c)), s["mesh"], s["T"], None, H, W)[0] for c in range(2)])
    refiner = RegionRefiner(s["mesh"], cams)
    T0 = _perturb(s["T"], 5.0)
    res, _ = refiner(imgs, T0)
    model = refiner.model
    e0 = _mean_vertex_error(s["mesh"], model, T0, np.zeros(0), s["T"], np.zeros(0))
    e1 = _mean_vertex_error(s["mesh"], model, np.asarray(res.T_world_root), np.zeros(0), s["T"], np.zeros(0))
    assert int(np.sum(np.asarray(res.correspondences.camera)[np.asarray(res.correspondences.weight) > 0] == 1)) >= 0
    assert e1 < 0.25 * e0 and e1 < 1.0, (e0, e1, int(res.status))


def test_refine_from_truth_settles_near_truth(rigid_scene):
    """Regression: refinement from the true pose must stay there and settle. Measured on this
    frame (/tmp/hF/truthtest.py): before the fixes 0.649 mm mean vertex error after 30 rounds
    without settling (non-zero matches for identical contours, zero-length matches dropped);
    after, 0.117 mm, settled in 10 rounds."""
    s = rigid_scene
    refiner = RegionRefiner(s["mesh"], s["cam"])
    res, _ = refiner(s["img"], s["T"])
    e1 = _mean_vertex_error(s["mesh"], refiner.model, np.asarray(res.T_world_root), np.zeros(0), s["T"], np.zeros(0))
    assert int(res.status) == int(Status.OK) and int(res.iterations) < 20, (int(res.status), int(res.iterations))
    assert e1 < 0.25, e1
    # Zero-length matches are kept (they anchor the pose): every contour row carries weight.
    assert int(res.num_matches) > 100


def test_refine_two_joint_chain():
    """Two cameras at 320x240 sharing χ = (ξ, Θ). With one camera the refinement did not converge
    (measured 4.5 → 5.1 mm, joints 0.06 rad off: the root drifts in depth); left open in the report."""
    num_cameras = 2
    from jaxtrack.geometry import select_camera

    mesh = _chain_mesh()
    model = chain_model([-1, 0, 1], [(0.0, 0.0, 1.0), (0.0, 0.0, 1.0)], [(50.0, 0.0, 0.0), (130.0, 0.0, 0.0)], dtype=jnp.float64)
    R1, t1 = look_at([450.0, 0.0, 200.0], target=(0.0, 0.0, 650.0))
    # A larger frame than the rigid tests: the thin links cover ~3.5k px at 192x144 (1 px ≈ 1.7 mm).
    w, h, f = 320, 240, 600.0
    cams = stack_cameras([_camera(w=w, h=h, f=f), _camera(R1, t1, w=w, h=h, f=f)][:num_cameras])
    T_true = _pose([0.3, 0.2, 0.1], [-60.0, 0.0, 650.0])
    th_true = np.array([0.35, -0.4])
    imgs = np.stack([_paint(Renderer(mesh, select_camera(cams, c), model), mesh, T_true, th_true, h, w)[0] for c in range(num_cameras)])
    refiner = RegionRefiner(mesh, cams, model)
    T0 = _perturb(T_true, 3.0)
    th0 = th_true + np.array([0.06, -0.06])
    res, _ = refiner(imgs, T0, th0)
    e0 = _mean_vertex_error(mesh, model, T0, th0, T_true, th_true)
    e1 = _mean_vertex_error(mesh, model, np.asarray(res.T_world_root), np.asarray(res.theta), T_true, th_true)
    assert e1 < 0.3 * e0, (e0, e1, np.asarray(res.theta), int(res.status))
    assert np.all(np.abs(np.asarray(res.theta) - th_true) < 0.03)


def test_a_dozen_refinements_compile_once(rigid_scene):
    s = rigid_scene
    # Two rounds per refinement keep the 12 runs short; the compiled program is the same kind.
    refiner = RegionRefiner(s["mesh"], s["cam"], config=RegionConfig(outer_iterations=2))
    refiner(s["img"], s["T"])  # compiles this crop class
    before = eqx.debug.get_num_traces(refine_pose_region)
    rng = np.random.default_rng(7)
    for _ in range(12):
        res, _ = refiner(s["img"], _perturb(s["T"], 2.0, rng.normal(size=6) / np.sqrt(6) * [1, 1, 1, 0.05, 0.05, 0.05]))
        assert np.all(np.isfinite(np.asarray(res.T_world_root)))
    assert eqx.debug.get_num_traces(refine_pose_region) == before


def test_feature_smoothing_is_off_by_default_and_brings_salt_noise_pixels_toward_their_region():
    """`RegionParams.feature_sigma`: 0 by default (the channels as they are); σ = 1 on a flat region half of
    whose pixels are uniform noise narrows the channels' spread around the region's own mean."""
    rng = np.random.default_rng(1)
    img = np.full((40, 40, 3), (210.0, 180.0, 60.0))
    salt = rng.random((40, 40)) < 0.5
    img[salt] = rng.uniform(0, 255, (int(salt.sum()), 3))
    assert float(region_params((40, 40)).feature_sigma) == 0.0
    np.testing.assert_array_equal(smoothed_features(jnp.asarray(img), False, 0.0), feature_channels(jnp.asarray(img), False))
    raw = np.asarray(feature_channels(jnp.asarray(img), False))[8:-8, 8:-8]
    smooth = np.asarray(smoothed_features(jnp.asarray(img), False, 1.0))[8:-8, 8:-8]
    assert np.all(smooth.std(axis=(0, 1)) < 0.5 * raw.std(axis=(0, 1)))
