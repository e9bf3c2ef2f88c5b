"""The flow minimiser: known motions, occlusion weights, convergence, consistency, ROI, compile counts."""

import dataclasses
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtrack import Status, StatusError
from jaxtrack.cues.flow import (
    FlowConfig,
    FlowEnergyParams,
    _api,
    _solver,
    compute_flow,
    compute_flow_bidirectional,
    compute_flow_roi,
    flow_energy,
    flow_level_energies,
    linearised_flow_energy,
    median_filter_flow,
    prepare_image,
    refine_flow,
    roi_crop,
)
from jaxtrack.image import pyramid_shapes
from jaxtrack.io import read_flo

# Small, fast settings shared by the tests (one compile per image size within a worker).
CFG = FlowConfig(eta=0.5, min_size=8, warps=5, lagged=2, sor_iters=20, presmooth_sigma=0.8)
PARAMS = FlowEnergyParams(jnp.asarray(8.0), jnp.asarray(7.0), jnp.asarray(1e-3), True)
H, W = 64, 80


def _texture(seed=0, n=12, fmax=0.35):
    """A band-limited random texture (sum of sinusoids) that can be sampled exactly anywhere."""
    rng = np.random.default_rng(seed)
    freq = rng.uniform(-fmax, fmax, size=(n, 2))
    phase = rng.uniform(0, 2 * np.pi, size=n)
    amp = rng.uniform(8, 20, size=n)

    def sample(x, y):
        return 128 + sum(a * np.sin(fx * x + fy * y + p) for a, (fx, fy), p in zip(amp, freq, phase))

    return sample


def _grid(h=H, w=W):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return x, y


def _interior(flow_shape, margin=6):
    m = np.zeros(flow_shape[:2], bool)
    m[margin:-margin, margin:-margin] = True
    return m


def _epe(flow, truth, mask):
    return float(np.mean(np.linalg.norm(np.asarray(flow) - truth, axis=-1)[mask]))


def test_pyramid_shapes_are_even_and_shrink():
    shapes = pyramid_shapes(480, 640, 0.5, 16, 100)
    assert shapes[0] == (480, 640) and all(h % 2 == 0 and w % 2 == 0 for h, w in shapes)
    assert all(a[0] > b[0] for a, b in itertools.pairwise(shapes)) and min(shapes[-1]) >= 16
    with pytest.raises(ValueError, match="eta"):
        pyramid_shapes(480, 640, 1.2, 16, 100)


def test_known_subpixel_translation_is_recovered():
    sample = _texture(0)
    x, y = _grid()
    shift = np.array([0.6, -0.35])
    img1, img2 = sample(x, y), sample(x - shift[0], y - shift[1])  # img2(x + w) = img1(x)
    res = compute_flow(img1, img2, PARAMS, CFG)
    assert _epe(res.flow, shift, _interior(img1.shape)) < 0.05


def test_known_subpixel_rotation_is_recovered():
    sample = _texture(1)
    x, y = _grid()
    c = np.array([W / 2 - 0.3, H / 2 + 0.2])
    a = np.radians(1.0)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    # img2(R (x − c) + c) = img1(x): sample img2 at p through the inverse rotation.
    q = np.einsum("ij,hwj->hwi", R.T, np.stack([x - c[0], y - c[1]], -1)) + c
    img1, img2 = sample(x, y), sample(q[..., 0], q[..., 1])
    moved = np.einsum("ij,hwj->hwi", R, np.stack([x - c[0], y - c[1]], -1)) + c
    truth = moved - np.stack([x, y], -1)
    assert np.linalg.norm(truth, axis=-1).max() > 0.7  # sub-pixel, but far from a translation
    # Gradient constancy is not rotation invariant (∇I turns with the image by 1°, which biases the
    # data term: measured EPE 0.056 at γ = 7), so this test uses grey-value constancy only.
    params = FlowEnergyParams(PARAMS.alpha, jnp.asarray(0.0), PARAMS.epsilon, True)
    res = compute_flow(img1, img2, params, CFG)
    assert _epe(res.flow, truth, _interior(img1.shape)) < 0.05


def _occluder_pair():
    """Background texture moving by (1, 0); a 24 px square occluder, own texture, moving by (−4, 1).

    Returns frame 1, frame 2, the occluder's mask in frame 1, its eroded core, the background pixels
    it covers in frame 2 (eroded), and the two motions.
    """
    bg, fg = _texture(2), _texture(3, fmax=0.3)
    x, y = _grid()
    w_bg, w_fg = np.array([1.0, 0.0]), np.array([-4.0, 1.0])
    x0, x1, y0, y1 = 30.0, 54.0, 18.0, 42.0  # the occluder's box in frame 1

    def frame(t):
        img = bg(x - t * w_bg[0], y - t * w_bg[1])
        ox, oy = t * w_fg[0], t * w_fg[1]
        inside = (x >= x0 + ox) & (x < x1 + ox) & (y >= y0 + oy) & (y < y1 + oy)
        return np.where(inside, fg(x - ox, y - oy), img), inside

    (img1, occ1), (img2, occ2) = frame(0.0), frame(1.0)
    core = np.zeros_like(occ1)
    core[24:36, 36:48] = True  # the occluder's centre, 6 px from its edges
    return img1, img2, occ1, core, occ2 & ~occ1, w_bg, w_fg


def test_zero_data_weight_lets_smoothness_fill_the_occluder():
    img1, img2, occ1, core, covered, w_bg, w_fg = _occluder_pair()
    # Without r, the flow on the occluder follows the occluder.
    plain = np.asarray(compute_flow(img1, img2, PARAMS, CFG).flow)
    assert np.linalg.norm(plain[core].mean(0) - w_fg) < 0.2  # the two motions are 5.1 px apart
    # With r = 0 on the occluder and the background it covers in frame 2 (occluded pixels, as the
    # tracker's occlusion test marks them), the flow there is filled in from the object around it.
    occluded = occ1 | covered
    r = 1.0 - np.asarray(jax.lax.reduce_window(occluded.astype(float), 0.0, jax.lax.max, (5, 5), (1, 1), "SAME"))
    filled = np.asarray(compute_flow(img1, img2, PARAMS, CFG, data_weight=r).flow)
    assert np.linalg.norm(filled[core].mean(0) - w_bg) < 0.2


def test_region_restricts_the_solution():
    sample = _texture(4)
    x, y = _grid()
    img1, img2 = sample(x, y), sample(x - 0.5, y - 0.25)
    region = np.zeros((H, W), bool)
    region[10:50, 15:60] = True
    res = compute_flow(img1, img2, PARAMS, CFG, region=region)
    flow = np.asarray(res.flow)
    assert np.all(flow[~region] == 0) and np.all(np.asarray(res.confidence)[~region] == 0)
    inner = np.zeros_like(region)
    inner[14:46, 19:56] = True
    assert _epe(flow, np.array([0.5, 0.25]), inner) < 0.05
    conf = np.asarray(res.confidence)[region]
    assert np.all((conf > 0) & (conf <= 3.0))  # β = 3 for robust smoothness, c = β / (1 + e)


def test_energy_decreases_at_every_level():
    sample = _texture(5)
    x, y = _grid()
    img1, img2 = sample(x, y), sample(x - 2.3, y + 1.1)  # a motion that needs the pyramid
    e = np.asarray(flow_level_energies(img1, img2, PARAMS, CFG, dtype=jnp.float64))
    assert e.shape == (len(pyramid_shapes(H, W, CFG.eta, CFG.min_size, CFG.max_levels)), 2)
    assert np.all(e[:, 1] < e[:, 0])
    res = compute_flow(img1, img2, PARAMS, CFG, dtype=jnp.float64)
    smooth1, smooth2 = prepare_image(img1, CFG.presmooth_sigma, jnp.float64), prepare_image(img2, CFG.presmooth_sigma, jnp.float64)
    assert float(flow_energy(res.flow, smooth1, smooth2, PARAMS)) == pytest.approx(e[0, 1], rel=1e-9)


def test_same_size_frames_compile_once():
    sample = _texture(7)
    x, y = _grid(48, 56)
    before = eqx.debug.get_num_traces(_solver._compute_flow_body)
    for k, alpha in enumerate((8.0, 12.0, 20.0)):
        params = FlowEnergyParams(jnp.asarray(alpha), jnp.asarray(7.0), jnp.asarray(1e-3), True)
        compute_flow(sample(x, y), sample(x - 0.3 * k, y), params, CFG).flow.block_until_ready()
    assert eqx.debug.get_num_traces(_solver._compute_flow_body) == before + 1


def test_forward_backward_consistency_flags_occlusions():
    img1, img2, occ1, core, covered, _w_bg, w_fg = _occluder_pair()
    out = compute_flow_bidirectional(img1, img2, PARAMS, CFG)
    assert np.linalg.norm(np.asarray(out.backward.flow)[core].mean(0) + w_fg) < 0.2
    ok = np.asarray(out.consistent_forward)
    # Background that the occluder covers in frame 2 has no match: the round trip cannot close.
    assert covered.sum() >= 90
    assert ok[covered].mean() < 0.5
    near = np.asarray(jax.lax.reduce_window(occ1.astype(float), 0.0, jax.lax.max, (13, 13), (1, 1), "SAME")).astype(bool)
    far = _interior(ok.shape, 4) & ~near
    assert ok[far].mean() > 0.95 and np.isfinite(np.asarray(out.forward.flow)).all()
    assert int(out.status) == Status.OK


def test_consistency_tolerances_are_arrays_and_failures_are_statuses():
    img1, img2 = _occluder_pair()[:2]
    strict = compute_flow_bidirectional(img1, img2, PARAMS, CFG)  # compiled once (shared with the test above)
    traces = eqx.debug.get_num_traces(_api._bidirectional_body)
    loose = compute_flow_bidirectional(img1, img2, PARAMS, CFG, a1=0.5, a2=1e6)
    assert eqx.debug.get_num_traces(_api._bidirectional_body) == traces  # new a1, a2: no new trace
    inside = np.asarray(loose.consistent_forward) | ~np.asarray(strict.consistent_forward)
    assert inside.all() and np.asarray(loose.consistent_forward).sum() > np.asarray(strict.consistent_forward).sum()
    # Finite frames whose squared derivatives overflow float32: a NONFINITE status, raised with throw.
    with pytest.raises(StatusError, match="NONFINITE"):
        compute_flow_bidirectional(img1 * 1e25, img2 * 1e25, PARAMS, CFG)
    bad = compute_flow_bidirectional(img1 * 1e25, img2 * 1e25, PARAMS, CFG, throw=False)
    assert int(bad.status) == Status.NONFINITE and int(bad.forward.status) == Status.NONFINITE
    assert not np.asarray(bad.forward.flow).any() and not np.asarray(bad.consistent_forward).any()
    assert eqx.debug.get_num_traces(_api._bidirectional_body) == traces


def test_roi_mode_matches_the_motion_and_reuses_its_compile():
    sample = _texture(8)
    y, x = np.mgrid[0:120, 0:160].astype(float)
    img1, img2 = sample(x, y), sample(x - 0.7, y - 0.2)
    region = np.zeros((120, 160), bool)
    region[40:80, 50:100] = True
    before = eqx.debug.get_num_traces(_api._roi_body)
    res, box = compute_flow_roi(img1, img2, PARAMS, region, CFG, margin=8)
    assert box[2:] == (64, 96) and box[2] >= 40 + 16
    inner = np.zeros_like(region)
    inner[44:76, 54:96] = True
    assert _epe(res.flow, np.array([0.7, 0.2]), inner) < 0.05
    assert np.all(np.asarray(res.flow)[~region] == 0)
    moved = np.roll(region, (3, 5), axis=(0, 1))  # same size class: no new compile
    _, box2 = compute_flow_roi(img1, img2, PARAMS, moved, CFG, margin=8)
    assert box2 != box and box2[2:] == box[2:]
    assert eqx.debug.get_num_traces(_api._roi_body) == before + 1
    with pytest.raises(ValueError, match="empty"):
        roi_crop(np.zeros((10, 10), bool), 4)


def test_bad_input_names_the_problem():
    a = np.zeros((20, 30))
    with pytest.raises(ValueError, match="same shape"):
        compute_flow(a, np.zeros((20, 31)), PARAMS, CFG)
    with pytest.raises(ValueError, match="region"):
        compute_flow(a, a, PARAMS, CFG, region=np.ones((20, 29), bool))
    with pytest.raises(ValueError, match="data_weight"):
        compute_flow(a, a, PARAMS, CFG, data_weight=np.ones((3,)))
    with pytest.raises(ValueError, match="sor_relaxation"):
        FlowConfig(sor_relaxation=2.5)


def _bad_inputs():
    """(name, kwargs, message) for every non-finite input and out-of-domain parameter."""
    img = np.zeros((20, 30))
    nan_img = img.copy()
    nan_img[3, 7] = np.nan
    weight = np.ones((20, 30))
    weight[5, 2] = np.inf
    start = np.zeros((20, 30, 2))
    start[9, 11, 1] = np.nan

    def params(alpha=8.0, gamma=7.0, eps=1e-3):
        return FlowEnergyParams(jnp.asarray(alpha), jnp.asarray(gamma), jnp.asarray(eps), True)

    return [
        ("nan-img1", {"img1": nan_img}, r"img1 has 1 non-finite pixel\(s\), first at \(y, x\) = \(3, 7\)"),
        ("nan-img2", {"img2": nan_img}, r"img2 has 1 non-finite pixel\(s\), first at \(y, x\) = \(3, 7\)"),
        ("inf-weight", {"data_weight": weight},
         r"data_weight has 1 non-finite value\(s\), first at \(y, x\) = \(5, 2\)"),
        ("nan-start", {"init_flow": start}, r"init_flow has 1 non-finite value\(s\), first at \(y, x\) = \(9, 11\)"),
        ("alpha<0", {"params": params(alpha=-1.0)}, "params.alpha must be finite and ≥ 0"),
        ("gamma<0", {"params": params(gamma=-0.5)}, "params.gamma must be finite and ≥ 0"),
        ("eps=0", {"params": params(eps=0.0)}, "params.epsilon must be finite and > 0"),
        ("nan-alpha", {"params": params(alpha=np.nan)}, "params.alpha must be finite"),
    ], img, params()


@pytest.mark.parametrize("entry", ["compute_flow", "compute_flow_roi", "compute_flow_bidirectional", "refine_flow"])
def test_non_finite_input_and_bad_parameters_raise_at_the_edge(entry):
    cases, img, params = _bad_inputs()
    region = np.zeros(img.shape, bool)
    region[4:16, 4:26] = True
    for name, kw, message in cases:
        args = {"img1": img, "img2": img, "params": params, "data_weight": None, "init_flow": None} | kw
        if entry == "compute_flow_bidirectional" and name == "nan-start":
            continue  # no start flow there
        with pytest.raises(ValueError, match=entry + ": " + message):
            if entry == "compute_flow":
                compute_flow(**args, config=CFG)
            elif entry == "compute_flow_roi":
                compute_flow_roi(**args, region=region, config=CFG)
            elif entry == "compute_flow_bidirectional":
                args.pop("init_flow")
                compute_flow_bidirectional(**args, config=CFG)
            else:
                start = args.pop("init_flow")
                refine_flow(np.zeros((*img.shape, 2)) if start is None else start, **args, config=CFG)
    with pytest.raises(ValueError, match="a2 must be ≥ 0"):
        compute_flow_bidirectional(img, img, params, CFG, a2=-1.0)


# Tiny settings for the in-jit status test: one small compile for all cases (vmapped).
TINY = FlowConfig(eta=0.5, min_size=8, warps=1, lagged=1, sor_iters=2, presmooth_sigma=0.8)


def test_inside_jit_bad_input_is_a_status_and_zeros_not_nan():
    sample = _texture(13)
    x, y = _grid(16, 16)
    img1, img2 = sample(x, y), sample(x - 0.4, y)
    ones, start = np.ones((16, 16)), np.zeros((16, 16, 2))
    nan_img, bad_w, bad_start = img1.copy(), ones.copy(), start.copy()
    nan_img[3, 7] = np.nan
    bad_w[5, 2] = np.nan
    bad_start[9, 11, 0] = np.nan
    # case: (img1, img2, data_weight, init_flow, alpha, gamma, epsilon, expected status)
    ok, invalid, nonfinite = int(Status.OK), int(Status.INVALID_INPUT), int(Status.NONFINITE)
    cases = [
        (img1, img2, ones, start, 8.0, 7.0, 1e-3, ok),
        (nan_img, img2, ones, start, 8.0, 7.0, 1e-3, invalid),
        (img1, nan_img, ones, start, 8.0, 7.0, 1e-3, invalid),
        (img1, img2, bad_w, start, 8.0, 7.0, 1e-3, invalid),
        (img1, img2, ones, bad_start, 8.0, 7.0, 1e-3, invalid),
        (img1, img2, ones, start, -1.0, 7.0, 1e-3, invalid),
        (img1, img2, ones, start, 8.0, -1.0, 1e-3, invalid),
        (img1, img2, ones, start, 8.0, 7.0, 0.0, invalid),
        # Finite input whose squared derivatives overflow float32: the solution is not finite.
        (img1 * 1e25, img2 * 1e25, ones, start, 8.0, 7.0, 1e-3, nonfinite),
    ]
    stack = [jnp.asarray(np.stack([c[k] for c in cases]), jnp.float32) for k in range(7)]

    def one(i1, i2, w, f0, alpha, gamma, eps):
        p = FlowEnergyParams(alpha, gamma, eps, True)
        return _solver.flow_core(i1, i2, p, TINY, w, jnp.ones((16, 16), bool), f0, 3.0, jnp.float32)

    res = jax.jit(jax.vmap(one))(*stack)
    np.testing.assert_array_equal(np.asarray(res.status), [c[-1] for c in cases])
    for field in (res.flow, res.local_energy, res.confidence):
        a = np.asarray(field)
        assert np.isfinite(a).all()
        assert not a[1:].any()  # every failure comes back as zeros
    # The valid case is a real solution (moving in +x after two SOR sweeps), not a fallback.
    assert np.asarray(res.flow[0, ..., 0]).mean() > 0 and (np.asarray(res.confidence[0]) > 0).all()


def test_odd_sized_frames_and_colour():
    sample = _texture(9)
    x, y = _grid(37, 51)
    shift = np.array([0.4, 0.3])
    img1 = np.stack([sample(x, y), sample(y, x), sample(x + 5, y)], -1)
    img2 = np.stack([sample(x - shift[0], y - shift[1]), sample(y - shift[1], x - shift[0]), sample(x + 5 - shift[0], y - shift[1])], -1)
    res = compute_flow(img1, img2, PARAMS, CFG)
    assert res.flow.shape == (37, 51, 2)
    assert _epe(res.flow, shift, _interior((37, 51))) < 0.05


def test_vmap_over_alpha_matches_single_solves():
    sample = _texture(10)
    x, y = _grid(32, 40)
    img1, img2 = jnp.asarray(sample(x, y)), jnp.asarray(sample(x - 0.5, y))
    alphas = jnp.asarray([5.0, 20.0])
    ones, full = jnp.ones((32, 40)), jnp.ones((32, 40), bool)

    def run(a):
        p = FlowEnergyParams(a, jnp.asarray(7.0), jnp.asarray(1e-3), True)
        return _solver.flow_core(img1, img2, p, CFG, ones, full, None, 3.0, jnp.float64).flow

    batched = jax.jit(jax.vmap(run))(alphas)
    for k in range(2):
        np.testing.assert_allclose(np.asarray(batched[k]), np.asarray(jax.jit(run)(alphas[k])), atol=1e-8)


def test_cli_writes_flo_and_visualisation(tmp_path):
    import cv2

    from jaxtrack.cli import main
    from jaxtrack.io import write_flo

    sample = _texture(11)
    x, y = _grid()
    shift = np.array([0.5, -0.25])
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    cv2.imwrite(str(a), np.clip(sample(x, y), 0, 255).astype(np.uint8))
    cv2.imwrite(str(b), np.clip(sample(x - shift[0], y - shift[1]), 0, 255).astype(np.uint8))
    gt = tmp_path / "gt.flo"
    write_flo(gt, np.broadcast_to(shift, (H, W, 2)).astype(np.float32))
    out, viz = tmp_path / "out.flo", tmp_path / "out.png"
    args = ["flow", str(a), str(b), "-o", str(out), "--viz", str(viz), "--gt", str(gt), "--no-cache", "--warps", "5"]
    assert main(args) == 0
    flow = read_flo(out)
    assert flow.shape == (H, W, 2)
    assert _epe(flow, shift, _interior((H, W))) < 0.1  # 8-bit quantised frames
    assert cv2.imread(str(viz)).shape == (H, W, 3)
    assert main(["flow", str(tmp_path / "missing.png"), str(b), "-o", str(out)]) == 2  # named on stderr (test_cli.py)


def test_median_filter_removes_outliers_and_respects_the_region():
    flow = np.zeros((20, 24, 2))
    flow[..., 0] = 1.5
    flow[8, 9] = (40.0, -30.0)  # an isolated outlier
    region = np.ones((20, 24), bool)
    region[:, 16:] = False
    flow[:, 16:] = 0.0  # zero outside Ω1, as compute_flow returns it
    out = np.asarray(median_filter_flow(jnp.asarray(flow), jnp.asarray(region), 3))
    np.testing.assert_allclose(out[region], np.broadcast_to([1.5, 0.0], (region.sum(), 2)))
    np.testing.assert_array_equal(out[~region], 0.0)  # outside untouched; inside not pulled to zero
    # The min/max selection networks are exact medians (compared with scipy away from the border).
    from scipy.ndimage import median_filter

    noisy = np.random.default_rng(0).normal(size=(12, 14, 2))
    for size in (3, 5):
        ours = np.asarray(median_filter_flow(jnp.asarray(noisy), jnp.ones((12, 14), bool), size))
        ref = np.stack([median_filter(noisy[..., k], size=size) for k in range(2)], -1)
        np.testing.assert_allclose(ours[2:-2, 2:-2], ref[2:-2, 2:-2], atol=1e-12)
    with pytest.raises(ValueError, match="median"):
        FlowConfig(median=4)


@pytest.mark.parametrize("separate", [False, True], ids=["joint-penalty", "separate-penalties"])
def test_solver_minimises_the_energy_it_is_given(separate):
    """One warp minimises the linearised energy (either data-term form): its gradient (jax.grad,
    float64) drops below 1% of its value at dw = 0, and at dw = 0 it equals eq. 6."""
    sample = _texture(12)
    x, y = _grid(24, 28)
    img1, img2 = sample(x, y), sample(x - 0.3, y - 0.2)
    params = FlowEnergyParams(PARAMS.alpha, PARAMS.gamma, PARAMS.epsilon, True, separate)
    cfg = FlowConfig(warps=1, lagged=80, sor_iters=60, presmooth_sigma=0.0)
    w0 = jnp.zeros((24, 28, 2), jnp.float64)
    w1 = refine_flow(w0, img1, img2, params, cfg, dtype=jnp.float64)
    i1, i2 = jnp.asarray(img1[..., None]), jnp.asarray(img2[..., None])
    assert float(linearised_flow_energy(jnp.zeros_like(w0), w0, i1, i2, params)) == pytest.approx(
        float(flow_energy(w0, i1, i2, params)), rel=1e-12
    )
    grad = jax.grad(linearised_flow_energy)
    g0 = np.linalg.norm(np.asarray(grad(jnp.zeros_like(w0), w0, i1, i2, params)))
    g1 = np.linalg.norm(np.asarray(grad(w1 - w0, w0, i1, i2, params)))
    assert g1 < 1e-2 * g0
    e = lambda d: float(linearised_flow_energy(d, w0, i1, i2, params))
    assert e(w1 - w0) < e(jnp.zeros_like(w0))


def test_shared_coarse_levels_give_the_same_flow():
    """`FlowConfig.shared_levels_from`: the coarse levels as one compiled level on a padded grid give the flow of
    the unrolled pyramid (to rounding), for a motion the coarse levels must find."""
    sample = _texture(3)
    x, y = _grid()
    shift = np.array([4.5, -3.0])
    img1, img2 = sample(x, y), sample(x - shift[0], y - shift[1])
    unrolled = compute_flow(img1, img2, PARAMS, CFG)  # Ω1 the whole frame: the padded levels' borders matter
    shared_cfg = dataclasses.replace(CFG, shared_levels_from=1)
    assert len(pyramid_shapes(H, W, CFG.eta, CFG.min_size, CFG.max_levels)) - 1 >= 2  # two or more levels share
    shared = compute_flow(img1, img2, PARAMS, shared_cfg)
    assert _epe(unrolled.flow, shift, _interior(img1.shape, 12)) < 0.1  # the motion was found at all
    np.testing.assert_allclose(np.asarray(shared.flow), np.asarray(unrolled.flow), atol=2e-3)


@pytest.mark.parametrize("src,dst", [((4, 6), (8, 12)), ((8, 10), (16, 20)), ((16, 20), (30, 38)), ((6, 8), (6, 8))])
def test_flow_resize_with_sizes_as_data_matches_the_static_one(src, dst):
    from jaxtrack.image import upsample_flow

    rng = np.random.default_rng(0)
    grid = (32, 40)
    flow = rng.normal(size=(*src, 2)).astype(np.float32)
    padded = np.zeros((*grid, 2), np.float32)
    padded[: src[0], : src[1]] = flow
    out = _solver._resize_flow_within(jnp.asarray(padded), jnp.asarray(src, jnp.int32), jnp.asarray(dst, jnp.int32))
    np.testing.assert_allclose(np.asarray(out)[: dst[0], : dst[1]], np.asarray(upsample_flow(jnp.asarray(flow), dst)),
                               atol=1e-5)


def test_sampling_within_a_size_equals_sampling_the_cropped_image():
    from jaxtrack.image import sample_bilinear

    rng = np.random.default_rng(1)
    img = rng.uniform(0, 255, (20, 30, 2)).astype(np.float32)
    x, y = rng.uniform(-3, 25, 50).astype(np.float32), rng.uniform(-3, 18, 50).astype(np.float32)
    crop, inside = sample_bilinear(jnp.asarray(img[:14, :22]), x, y)
    within, inside_w = sample_bilinear(jnp.asarray(img), x, y, (jnp.asarray(14), jnp.asarray(22)))
    np.testing.assert_allclose(np.asarray(within), np.asarray(crop), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(inside_w), np.asarray(inside))


def test_derivative_stack_of_a_padded_level_equals_that_of_the_level():
    rng = np.random.default_rng(2)
    level = rng.uniform(0, 255, (10, 14, 1)).astype(np.float32)
    padded = np.pad(level, ((0, 6), (0, 10), (0, 0)), mode="edge")
    out = _solver.derivative_stack(jnp.asarray(padded), (jnp.asarray(10), jnp.asarray(14)))
    np.testing.assert_allclose(np.asarray(out)[:10, :14], np.asarray(_solver.derivative_stack(jnp.asarray(level))),
                               rtol=1e-5, atol=1e-3)
