"""Builds and executes notebooks/optical_flow.ipynb (run: python notebooks/build_flow_notebook.py).

Needs the notebook extra (pip install -e ".[notebooks]") and ../shared/data/flow beside the repository.
"""

from _notebook import build

CELLS = [
    ("md", "# jaxtrack optical flow: Brox et al. 2004 in JAX, with occlusion weights and a region\n\n"
           "The motion cue of the tracker (eq. 6-8 of Brox et al. 2010): a variational flow whose data term can be "
           "switched off where the object is occluded (r(x) = 0) and which is integrated over the object region Ω1 only. "
           "This notebook runs it on a Middlebury pair, shows what r(x) does on a synthetic occluder, checks occlusions "
           "with forward-backward consistency, and sweeps the smoothness weight α with `vmap` in one compiled call."),
    ("code", "import time, pathlib\nimport cv2, jax, jax.numpy as jnp, numpy as np\nimport matplotlib.pyplot as plt\n"
             "from jaxtrack.cues.flow import (FlowEnergyParams, compute_flow, compute_flow_bidirectional, middlebury_config,\n"
             "                                middlebury_params)\nfrom jaxtrack.io import flow_errors, flow_to_colour, read_flo\n"
             "DATA = pathlib.Path('..').resolve().parent / 'shared' / 'data' / 'flow'\nprint(jax.__version__, jax.devices())"),
    ("md", "## RubberWhale (584x388): first call compiles, the second is the solve"),
    ("code", "seq = DATA / 'RubberWhale'\nimg1 = cv2.imread(str(seq / 'frame10.png'), cv2.IMREAD_GRAYSCALE)\n"
             "img2 = cv2.imread(str(seq / 'frame11.png'), cv2.IMREAD_GRAYSCALE)\ngt = read_flo(seq / 'flow10.flo')\n"
             "params, config = middlebury_params(), middlebury_config()\n"
             "t = time.perf_counter(); res = compute_flow(img1, img2, params, config); res.flow.block_until_ready()\n"
             "print('first call (compile + solve) %.1f s' % (time.perf_counter() - t))\n"
             "t = time.perf_counter(); res = compute_flow(img1, img2, params, config); flow = np.asarray(res.flow)\n"
             "print('solve %.2f s' % (time.perf_counter() - t), flow_errors(flow, gt))\n"
             "scale = np.abs(gt[np.abs(gt) < 1e9]).max()\n"
             "fig, ax = plt.subplots(1, 4, figsize=(16, 3.2))\n"
             "for a, im, title in zip(ax, [img1, flow_to_colour(gt, scale), flow_to_colour(flow, scale), np.asarray(res.confidence)],\n"
             "                        ['frame 10', 'ground truth', 'jaxtrack', 'confidence c = β/(1+e) (eq. 8)']):\n"
             "    a.imshow(im, cmap='gray' if im.ndim == 2 else None); a.set_title(title); a.axis('off')"),
    ("md", "## Occlusion weights r(x): a square occluder crosses a moving background\n\n"
           "Without r the flow on the occluder follows the occluder; with r = 0 there, smoothness fills in the "
           "background's motion, which is what the tracker needs for the object behind an occluder."),
    ("code", "rng = np.random.default_rng(0)\nfreq, phase = rng.uniform(-0.35, 0.35, (12, 2)), rng.uniform(0, 6.3, 12)\n"
             "tex = lambda x, y, s=0: 128 + sum(15 * np.sin(fx * x + fy * y + p + s) for (fx, fy), p in zip(freq, phase))\n"
             "y, x = np.mgrid[0:96, 0:128].astype(float)\nbox1 = (x >= 48) & (x < 80) & (y >= 32) & (y < 64)\n"
             "box2 = (x >= 44) & (x < 76) & (y >= 33) & (y < 65)  # the occluder moves by (-4, 1)\n"
             "f1 = np.where(box1, tex(1.3 * y, 0.7 * x, 1), tex(x, y))\n"
             "f2 = np.where(box2, tex(1.3 * (y - 1), 0.7 * (x + 4), 1), tex(x - 1, y))  # background moves by (1, 0)\n"
             "occluded = cv2.dilate((box1 | box2).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)\n"
             "plain = np.asarray(compute_flow(f1, f2, params, config).flow)\n"
             "filled = np.asarray(compute_flow(f1, f2, params, config, data_weight=(~occluded).astype(float)).flow)\n"
             "bi = compute_flow_bidirectional(f1, f2, params, config)\n"
             "print('mean flow on the occluder: without r', plain[box1].mean(0).round(2), ' with r = 0:', filled[box1].mean(0).round(2))\n"
             "fig, ax = plt.subplots(1, 4, figsize=(16, 3.2))\n"
             "for a, im, title in zip(ax, [f1, flow_to_colour(plain, 5), flow_to_colour(filled, 5), np.asarray(bi.consistent_forward)],\n"
             "                        ['frame 1', 'flow, r = 1', 'flow, r = 0 on the occluder', 'forward-backward consistent']):\n"
             "    a.imshow(im, cmap='gray' if im.ndim == 2 else None); a.set_title(title); a.axis('off')"),
    ("md", "## Sweep α with `vmap`: eight smoothness weights in one compiled call (a 192x192 crop)"),
    ("code", "from jaxtrack.cues.flow._solver import flow_core\n"
             "c1, c2, cgt = img1[100:292, 200:392], img2[100:292, 200:392], gt[100:292, 200:392]\n"
             "alphas = jnp.asarray([1.0, 2.0, 3.5, 5.0, 7.5, 10.0, 20.0, 40.0])\n"
             "ones, full = jnp.ones(c1.shape), jnp.ones(c1.shape, bool)\n"
             "run = lambda a: flow_core(c1, c2, FlowEnergyParams(a, params.gamma, params.epsilon), config, ones, full, None, 3.0, jnp.float32).flow\n"
             "sweep = jax.jit(jax.vmap(run))\nflows = np.asarray(sweep(alphas))\n"
             "epe = [flow_errors(f, cgt)['epe'] for f in flows]\n"
             "plt.figure(figsize=(5, 3)); plt.semilogx(np.asarray(alphas), epe, 'o-'); plt.xlabel('α'); plt.ylabel('EPE (px)')\n"
             "plt.title('RubberWhale crop'); print(dict(zip(np.asarray(alphas).tolist(), np.round(epe, 3).tolist())))"),
]


def main():
    build(CELLS, "optical_flow.ipynb", timeout=900)


if __name__ == "__main__":
    main()
