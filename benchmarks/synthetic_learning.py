r"""Does a model learn to match from scratch? Held-out EPE against the zero-flow EPE, fast.

  python benchmarks/synthetic_learning.py                                   # configs/synthetic.py
  python benchmarks/synthetic_learning.py --arg model=tiny_synth,pairs=pan,steps=3000
  python benchmarks/synthetic_learning.py --shift 10 --arg model=tiny_synth,steps=3000

The step is train.py's own (model, loss and optimizer built from the config by train.py's
builders); the data is a fixed set rendered once into memory and sampled without augmentation,
and the held-out EPE is printed as often as asked. Per step it costs what train.py costs once
compiled (~0.1 s for `tiny` at 56 px, batch 8, on 2 cores; ~0.3 s for `tiny_synth`), so a
3000-step probe takes minutes. The model's parameters come from `ufm.init_params` (the
configured position table), which also starts the heads closer to zero flow than `model.init`.

`--shift S` swaps the 3D scenes for the easiest matching task there is: a smooth random texture
and the same texture translated by an integer (dx, dy) in [-S, S]^2 (flow constant, covisible
where the shifted pixel stays inside). A model that cannot learn this cannot learn the scenes.

Each line prints the held-out EPE on covisible pixels, the zero-flow EPE of the same pixels (the
error of predicting no motion) and the ratio to the step-0 EPE. Prints figures, asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

KEYS = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")


def shift_pair(seed, size, max_shift):
  """(forward, backward) samples of one translated-texture pair (see the module docstring)."""
  import cv2
  rng = np.random.default_rng(seed)
  h, w = size
  pad = max_shift + 1
  tex = np.zeros((h + 2 * pad, w + 2 * pad, 3), np.float32)
  for sigma, amp in ((1.5, 30.0), (4.0, 50.0), (10.0, 60.0)):  # fine detail + blobs + shading
    noise = cv2.GaussianBlur(rng.normal(size=tex.shape).astype(np.float32), (0, 0), sigma)
    tex += amp * noise / (noise.std() + 1e-6)
  tex = np.clip(128 + tex, 0, 255).astype(np.uint8)
  d = rng.integers(-max_shift, max_shift + 1, 2)
  img0 = tex[pad:pad + h, pad:pad + w]
  img1 = tex[pad - d[1]:pad - d[1] + h, pad - d[0]:pad - d[0] + w]  # img1(p + d) = img0(p)
  v, u = np.mgrid[0:h, 0:w]
  out = []
  for a, b, dd in ((img0, img1, d), (img1, img0, -d)):
    covis = (u + dd[0] >= 0) & (u + dd[0] < w) & (v + dd[1] >= 0) & (v + dd[1] < h)
    out.append(dict(image0=a, image1=b, covisibility=covis, covis_valid=np.ones((h, w), bool),
                    flow=np.broadcast_to(dd.astype(np.float32), (h, w, 2)).copy(),
                    flow_valid=np.ones((h, w), bool)))
  return out


def render_set(config, split, num_pairs, max_shift, both):
  """Stacked arrays of `num_pairs` pairs (both directions, interleaved, when `both`)."""
  from tqdm import tqdm
  from ufm_jax.data import synthetic
  syn = config.input.datasets.synthetic.options
  size = tuple(syn["size"])
  scene_cfg = synthetic.SyntheticConfig(size=size, pair_type=syn.get("pair_type", "mixed"))
  samples = []
  for i in tqdm(range(num_pairs), desc=f"render {split}", unit="pair", leave=False):
    seed = synthetic.pair_seed(config.seed, split, i)
    if max_shift:
      pair = shift_pair(seed, size, max_shift)
    else:
      pair = synthetic.generate_pair(seed, scene_cfg)
    samples += pair if both else pair[:1]
  return {k: np.stack([s[k] for s in samples]) for k in KEYS}


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default=str(REPO / "configs" / "synthetic.py"))
  parser.add_argument("--arg", default="",
                      help="the config arg, e.g. model=tiny_synth,steps=3000")
  parser.add_argument("--train_pairs", type=int, default=2000, help="rendered once, then reused")
  parser.add_argument("--val_pairs", type=int, default=32)
  parser.add_argument("--shift", type=int, default=0, help="translated textures, |d| <= SHIFT px")
  parser.add_argument("--every", type=int, default=250)
  args = parser.parse_args(argv)

  sys.path.insert(0, str(REPO / "benchmarks"))
  from train_step import load_config  # the same config loader as the step benchmark
  import jax
  import train
  from ufm_jax import optim
  from ufm_jax.models import ufm

  spec = args.config + (f":{args.arg}" if args.arg else "")
  config = load_config(spec)
  t0 = time.time()
  tr = render_set(config, "train", args.train_pairs, args.shift, both=True)
  va = render_set(config, "val", args.val_pairs, args.shift, both=False)
  mask = va["flow_valid"] & va["covisibility"]
  zero = float(np.linalg.norm(va["flow"], axis=-1)[mask].mean())
  print(f"{spec}  {'shift<=%d' % args.shift if args.shift else 'scenes'}: {args.train_pairs} "
        f"train pairs rendered in {time.time() - t0:.0f} s; held-out zero-flow EPE {zero:.3f} px",
        flush=True)

  model = train.build_model(config)
  params = ufm.init_params(model, config.seed)  # the configured position table, no compile
  steps = int(config.total_steps)
  tx, labels, _ = optim.make_optimizer(config.optim, params, steps)
  state = optim.TrainState.create(params, tx)
  step_fn = jax.jit(train.make_train_step(model, train.build_loss(config), tx, labels,
                                          dict(config.get("apply_kwargs", {}))),
                    donate_argnums=(0,))
  predict = jax.jit(lambda p, a, b: model.apply({"params": p}, a, b)["flow"])

  def heldout_epe(params):
    flow = np.asarray(predict(params, va["image0"], va["image1"]), np.float64)
    return float(np.linalg.norm(flow - va["flow"], axis=-1)[mask].mean())

  epe0 = heldout_epe(state.params)
  print(f"step 0: held-out EPE {epe0:.3f} px (zero-flow {zero:.3f})", flush=True)
  rng = np.random.default_rng(config.seed)
  batch = int(config.input.batch_size)
  unique = batch // 2  # symmetrized: both directions of each drawn pair, as train.py's batches
  n = len(tr["image0"]) // 2
  t0, t_eval = None, 0.0
  for step in range(1, steps + 1):
    pick = rng.choice(n, unique, replace=False)
    rows = np.stack([2 * pick, 2 * pick + 1], 1).reshape(-1)
    state, metrics = step_fn(state, {k: v[rows] for k, v in tr.items()})
    if t0 is None:  # compile time stays out of the per-step figure
      jax.block_until_ready(metrics)
      t0 = time.time()
    if step % args.every == 0 or step == steps:
      m = jax.device_get(metrics)
      t = time.time()
      epe = heldout_epe(state.params)
      t_eval += time.time() - t
      per_step = (time.time() - t0 - t_eval) / max(step - 1, 1)
      print(f"step {step}: held-out EPE {epe:.3f} px ({epe0 / epe:.2f}x of step 0; zero-flow "
            f"{zero:.3f}), train loss {float(m['loss']):.3f}, {per_step:.3f} s/step", flush=True)


if __name__ == "__main__":
  os.environ.setdefault("JAX_PLATFORMS", "cpu")
  main()
