"""Builds and executes notebooks/pose_solver.ipynb (run: python notebooks/build_pose_solver_notebook.py).

Needs the notebook extra: pip install -e ".[notebooks]".
"""

from _notebook import build

CELLS = [
    ("md", "# jaxtrack pose solver: jit, vmap over cue weights, implicit gradients\n\n"
           "Every cue of the tracker ends as weighted 2D-3D correspondences; this notebook solves an "
           "articulated pose from them (eq. 4-5 of Brox et al. 2010), sweeps the weights with `vmap` in one "
           "compiled call, and differentiates the solution with respect to the weights."),
    ("code", "import time\nimport jax, jax.numpy as jnp, numpy as np\nimport matplotlib.pyplot as plt\n"
             "import jaxtrack as jt\nfrom jaxtrack.synth import demo_chain, random_pose_scene, perturb_pose\n"
             "print(jax.__version__, jax.devices())"),
    ("md", "## A 3-joint arm seen by two cameras, 1 px noise, 20% gross outliers"),
    ("code", "model = demo_chain(3)\nscene = random_pose_scene(0, num_points=300, noise_px=1.0, num_cameras=2, model=model, dtype=np.float32)\n"
             "rng = np.random.default_rng(0)\noutliers = rng.random(300) < 0.2\npixel = scene.pixel.copy()\n"
             "pixel[outliers] += rng.uniform(-60, 60, size=(outliers.sum(), 2))\n"
             "corr = jt.make_correspondences(scene.cameras, pixel, scene.p_model, camera_index=scene.camera_index,\n"
             "                               part=scene.part, capacity=512)\n"
             "T0 = jnp.asarray(perturb_pose(rng, scene.T_world_root, 0.2, 20.0), jnp.float32)\n"
             "theta0 = jnp.zeros(3, jnp.float32)\n"
             "solve = jax.jit(lambda w: jt.solve_pose(model, corr.with_weight(w), T0, theta0))\n"
             "def errors(sol):\n"
             "    R = np.asarray(sol.T_world_root[:3, :3], float)\n"
             "    rot = np.degrees(np.arccos(np.clip((np.trace(R @ scene.T_world_root[:3, :3].T) - 1) / 2, -1, 1)))\n"
             "    return rot, np.linalg.norm(np.asarray(sol.T_world_root[:3, 3], float) - scene.T_world_root[:3, 3]), np.degrees(np.abs(np.asarray(sol.theta) - scene.theta)).max()\n"
             "sol = solve(corr.weight)\nprint('status', jt.PoseStatus(int(sol.status)).name, 'steps', int(sol.num_steps))\n"
             "print('uniform weights: rot %.3f deg, trans %.2f mm, joints %.3f deg' % errors(sol))"),
    ("md", "## Sweep: down-weight the outliers by a factor s, 64 values of s in one vmapped call"),
    ("code", "scales = jnp.logspace(-4, 0, 64)\nweights = jnp.where(jnp.asarray(outliers)[None, :], scales[:, None], 1.0)\n"
             "weights = jnp.concatenate([weights, jnp.zeros((64, 512 - 300))], axis=1)\n"
             "sweep = jax.jit(jax.vmap(lambda w: jt.solve_pose(model, corr.with_weight(w), T0, theta0)))\n"
             "out = sweep(weights); jax.block_until_ready(out)\n"
             "t = time.perf_counter(); out = sweep(weights); jax.block_until_ready(out); dt = time.perf_counter() - t\n"
             "errs = np.array([errors(jax.tree_util.tree_map(lambda x: x[k], out)) for k in range(64)])\n"
             "print(f'64 solves in {1e3 * dt:.1f} ms')\n"
             "fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))\nax[0].semilogx(scales, errs[:, 1]); ax[0].set_xlabel('outlier weight'); ax[0].set_ylabel('translation error (mm)')\n"
             "ax[1].semilogx(scales, errs[:, 2]); ax[1].set_xlabel('outlier weight'); ax[1].set_ylabel('max joint error (deg)')\nplt.tight_layout()"),
    ("md", "## Gradient of the solved pose with respect to every weight (implicit differentiation)\n\n"
           "The largest derivatives belong to the outliers: gradient descent on the weights would switch them off."),
    ("code", "dt_dw = jax.jacrev(lambda w: solve(w).T_world_root[:3, 3])(corr.weight)\n"
             "influence = np.linalg.norm(np.asarray(dt_dw[:, :300]), axis=0)\n"
             "print('mean |d t / d w| inliers %.3f mm, outliers %.3f mm' % (influence[~outliers].mean(), influence[outliers].mean()))\n"
             "plt.figure(figsize=(6, 3)); plt.hist([influence[~outliers], influence[outliers]], bins=40, label=['inliers', 'outliers'], log=True)\n"
             "plt.xlabel('|d t / d w_i| (mm)'); plt.legend();"),
]


def main():
    build(CELLS, "pose_solver.ipynb", timeout=600)


if __name__ == "__main__":
    main()
