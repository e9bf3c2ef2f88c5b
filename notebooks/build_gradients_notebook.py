"""Builds and executes notebooks/gradients.ipynb (run: python notebooks/build_gradients_notebook.py).

Gradient checks against central finite differences: the flow energy (eq. 6), the level-set energy
(eq. 11), the solved pose with respect to the correspondence weights (implicit derivative of eq. 5),
and a tracking loss with respect to the cue-weight factors through the tracker's whole per-frame step
(forward mode; experiment 8). `--smoke` (or JAXTRACK_NOTEBOOK_SMOKE=1) runs the tracking part on the
smoke configuration (occluded box 96x72, region cue, one frame).
Needs the notebook extra: pip install -e ".[notebooks]".
"""

import sys

CELLS = [
    ("md", "# jaxtrack gradients: energies, solved poses, and a tracking loss w.r.t. the cue weights\n\n"
           "Everything between image arrays and poses is JAX, so derivatives come for free where the maths has "
           "them. This notebook checks them against central finite differences in float64: the energies the cues "
           "minimise, the pose solved from weighted correspondences (implicit differentiation, no unrolled "
           "iterations), and finally the derivative of a tracking error with respect to the cue-weight factors "
           "through the whole per-frame step."),
    ("code", "import os, sys, json, pathlib, time\nimport numpy as np, jax, jax.numpy as jnp\n"
             "jax.config.update('jax_enable_x64', True)\nimport matplotlib.pyplot as plt\nimport jaxtrack as jt\n"
             "SMOKE = os.environ.get('JAXTRACK_NOTEBOOK_SMOKE') == '1'\n"
             "ROOT = pathlib.Path(os.environ.get('JAXTRACK_ROOT', pathlib.Path.cwd().parent))\n"
             "def compare(name, analytic, fd):\n"
             "    analytic, fd = np.asarray(analytic, float), np.asarray(fd, float)\n"
             "    rel = np.max(np.abs(analytic - fd)) / max(np.max(np.abs(fd)), 1e-300)\n"
             "    print(f'{name}: max |analytic - FD| / max |FD| = {rel:.2e}')\n"
             "    return rel\n"
             "print(jax.__version__, jax.devices(), 'smoke' if SMOKE else 'full')"),
    ("md", "## Flow energy (eq. 6): ∂E/∂(u, v) by `jax.grad` against central differences\n\n"
           "Gray value and gradient constancy (γ), robust Ψ(s²) = √(s² + ε²), robust smoothness (α = 50, the "
           "articulated setting), on a smooth random texture moved by (0.4, −0.2) px."),
    ("code", "from jaxtrack.cues.flow import flow_energy, articulated_params\n"
             "rng = np.random.default_rng(0)\nfreq, phase = rng.uniform(0.05, 0.35, (6, 2)), rng.uniform(0, 6.3, 6)\n"
             "tex = lambda x, y: 128 + sum(20 * np.sin(fx * x + fy * y + p) for (fx, fy), p in zip(freq, phase))\n"
             "y, x = np.mgrid[0:12, 0:14].astype(float)\nimg1, img2 = jnp.asarray(tex(x, y)), jnp.asarray(tex(x - 0.4, y + 0.2))\n"
             "flow = jnp.asarray(rng.normal(scale=0.3, size=(12, 14, 2)))\nparams = articulated_params()\n"
             "E = jax.jit(lambda f: flow_energy(f, img1, img2, params))\ng = jax.jit(jax.grad(E))(flow)\nh = 1e-6\n"
             "idx = [(3, 4, 0), (7, 9, 1), (0, 0, 0), (11, 13, 1), (5, 5, 1)]\n"
             "fd = [(E(flow.at[i].add(h)) - E(flow.at[i].add(-h))) / (2 * h) for i in idx]\n"
             "for i, a, b in zip(idx, [g[i] for i in idx], fd): print(i, f'grad {float(a): .8e}  FD {float(b): .8e}')\n"
             "flow_rel = compare('flow energy', [g[i] for i in idx], fd)"),
    ("md", "## Level-set energy (eq. 11): ∂E/∂Φ against central differences\n\n"
           "Region terms with local Gaussian densities, the length term ν|∇H(Φ)| and the shape prior λ(Φ − Φ0)²; a "
           "noisy disc segmenting a slightly shifted bright disc."),
    ("code", "from jaxtrack.cues.levelset import levelset_energy, local_densities, log_likelihoods, region_membership, region_params\n"
             "H, W = 24, 28\nyy, xx = np.mgrid[0:H, 0:W].astype(float)\n"
             "phi0 = 7.0 - np.hypot(xx - 13.3, yy - 11.7)\nphi = jnp.asarray(phi0 + rng.normal(scale=0.7, size=phi0.shape))\n"
             "img = np.where(7.5 - np.hypot(xx - 14.5, yy - 12.0) > 0, 180.0, 60.0) + rng.normal(scale=10, size=phi0.shape)\n"
             "feats = jnp.asarray(img[..., None])\nrp = region_params((H, W), jnp.float64, rho=4.0)\n"
             "dens = local_densities(feats, region_membership(jnp.asarray(phi0)), rp.rho, rp.kappa, rp.sigma_min, factor=1)\n"
             "log_p = log_likelihoods(feats, dens, factor=1)\nphi0 = jnp.asarray(phi0)\n"
             "E = jax.jit(lambda p: levelset_energy(p, phi0, log_p, rp))\ng = jax.jit(jax.grad(E))(phi)\n"
             "idx = [(11, 5), (12, 20), (4, 13), (18, 14), (0, 0)]\n"
             "fd = [(E(phi.at[i].add(1e-6)) - E(phi.at[i].add(-1e-6))) / 2e-6 for i in idx]\n"
             "for i, b in zip(idx, fd): print(i, f'grad {float(g[i]): .8e}  FD {float(b): .8e}')\n"
             "levelset_rel = compare('level-set energy', [g[i] for i in idx], fd)"),
    ("md", "## The solved pose (eq. 4-5) w.r.t. the correspondence weights\n\n"
           "`solve_pose` runs a damped Gauss-Newton `while_loop`; its derivative comes from the implicit function "
           "theorem on the optimality condition (`lax.custom_root`), so forward and reverse mode both work and "
           "nothing is unrolled. 40 noisy correspondences in two cameras; derivative of the translation."),
    ("code", "from jaxtrack.synth import random_pose_scene\nfrom jaxtrack.solve import SolverConfig, make_correspondences, solve_pose\n"
             "model = jt.rigid_model(jnp.float64)\nscene = random_pose_scene(21, num_points=40, noise_px=2.0, num_cameras=2, model=model)\n"
             "corr = make_correspondences(scene.cameras, scene.pixel, scene.p_model, camera_index=scene.camera_index, part=scene.part,\n"
             "                            num_parts=1)\n"
             "T0 = jnp.asarray(scene.T_world_root)\ntight = SolverConfig(max_steps=100, rtol=1e-13, atol=1e-13)\n"
             "f = lambda w: solve_pose(model, corr.with_weight(w), T0, None, tight).T_world_root[:3, 3]\n"
             "w0 = jnp.asarray(rng.uniform(0.5, 1.5, 40))\nJr = jax.jit(jax.jacrev(f))(w0)  # reverse mode: 40 weights, 3 outputs\n"
             "step = 1e-5 * jnp.eye(40)\nfd = np.asarray((jax.vmap(f)(w0 + step) - jax.vmap(f)(w0 - step)) / 2e-5).T  # 40 solves per side, one call\n"
             "pose_rel = compare('pose w.r.t. weights (jacrev vs FD)', Jr, fd)\nJf = Jr\n"
             "plt.figure(figsize=(8, 2.6)); plt.plot(np.asarray(Jf).T, '.-'); plt.xlabel('correspondence'); plt.ylabel('∂t / ∂w (mm)')\n"
             "plt.legend(['x', 'y', 'z'], fontsize=8); plt.title('how much each correspondence weight moves the solved translation')"),
    ("md", "## A tracking loss w.r.t. the cue-weight factors, through the whole per-frame step\n\n"
           "Loss: the mean squared error of the model's bounding-box corners (camera 0) / the box diagonal², over a "
           "window of frames tracked from the true pose; parameters θ = (log flow factor, log SIFT factor). "
           "Reverse mode stops at the refinement loop (a `while_loop` with a data-dependent trip count, which JAX "
           "cannot transpose). Forward mode goes through it, through the solves by implicit differentiation and "
           "from frame to frame through the carried state; with two parameters it is also the cheaper direction "
           "(`experiments/learn_weights.py`). The smoke version uses the region cue only, where the flow and SIFT "
           "factors have nothing to weigh: both derivatives are exactly zero there."),
    ("code", "sys.path.insert(0, str(ROOT / 'experiments'))\nimport tempfile, learn_weights as lw\n"
             "folder = pathlib.Path(tempfile.mkdtemp())\n"
             "if SMOKE:\n"
             "    prob = lw.load_problem('occluded-box', 0.15, 4, 0, ('region',), folder); length, hs = 1, [0.03]\n"
             "else:\n"
             "    prob = lw.load_problem('noisy-moving-camera', 0.25, 4, 5, ('region', 'flow', 'sift'), folder); length, hs = 2, [0.05, 0.01]\n"
             "prob.corners = lw.box_corners(prob.tracker.mesh)\n"
             "if not SMOKE:\n"
             "    print('reverse mode:', lw.reverse_mode_probe(prob))\n"
             "theta = np.log([0.1, 1.0])\nt = time.perf_counter()\n"
             "loss, grad, status, secs = lw.window_loss(prob, 0, length, theta)\n"
             "print(f'loss {loss:.6g}; forward-mode gradient {grad} ({secs[0]:.1f} s for the first step, incl. compile)')\n"
             "for h in hs:\n"
             "    fd = []\n"
             "    for p in range(2):\n"
             "        e = np.zeros(2); e[p] = h\n"
             "        fd.append((lw.window_loss(prob, 0, length, theta + e, False)[0] - lw.window_loss(prob, 0, length, theta - e, False)[0]) / (2 * h))\n"
             "    print(f'central FD (h = {h} in log space): {np.array(fd)}')\n"
             "tracking_grad = grad"),
    ("md", "### The check at full size (from `experiments/learn_weights.py`, when it has been run)"),
    ("code", "res = ROOT / 'experiments' / 'results' / 'learn_weights.json'\n"
             "if res.is_file():\n"
             "    data = json.loads(res.read_text())\n"
             "    c = data['check']\n"
             "    print('reverse mode:', data['probe'])\n"
             "    print('forward mode:', np.round(c['jvp'], 6), ' central FD:', {h: np.round(fd, 6).tolist() for h, fd in zip(c['h'], c['fd'])})\n"
             "else:\n"
             "    print('experiments/results/learn_weights.json not found: run python experiments/learn_weights.py')"),
]


def main(argv=None):
    import os

    args = sys.argv[1:] if argv is None else argv
    if "--smoke" in args:
        os.environ["JAXTRACK_NOTEBOOK_SMOKE"] = "1"
    from _notebook import build

    build(CELLS, "gradients.ipynb", timeout=1800)


if __name__ == "__main__":
    main()
