r"""Does a model learn to match from scratch? Held-out EPE against the zero-flow EPE, fast.

  python benchmarks/synthetic_learning.py                      # configs/synthetic.py as it is
  python benchmarks/synthetic_learning.py --arg model=tiny,steps=3000     # the untied 14 px model

The step is train.py's own (model, loss and optimizer built from the config by train.py's
builders); the data is a fixed set of the config's synthetic pairs made once into memory and
sampled without augmentation, and the held-out EPE (train.py's own evaluator on the config's
held-out pairs) is printed as often as asked. Per step it costs what train.py costs once compiled (~0.1 s for `tiny` at 56 px,
batch 8, on 2 cores; ~0.2 s for `synth`), so a 3000-step probe takes minutes. Parameters come
from train.py's init (`ufm_jax.training.trainer.init_params`, the modules' own initializers). `pairs=shift` (translated textures) is the easiest matching task:
a model that cannot learn it cannot learn the scenes.

Each line prints the held-out EPE on covisible pixels, the zero-flow EPE of the same pixels (the
error of predicting no motion) and the ratio to the step-0 EPE. Prints figures, asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import time

REPO = pathlib.Path(__file__).resolve().parents[1]

import numpy as np

KEYS = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")


def render_set(options, seed, split, num_pairs):
  """Stacked arrays of `num_pairs` synthetic pairs, both directions of each, interleaved."""
  from tqdm import tqdm
  from ufm_jax.data import get_source
  src = get_source("synthetic", None, **{**options, "split": split, "num_pairs": num_pairs,
                                        "seed": seed})
  samples = []
  for i in tqdm(range(num_pairs), desc=f"render {split}", unit="pair", leave=False):
    samples += src.both(i)
  return {k: np.stack([s[k] for s in samples]) for k in KEYS}


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default=str(REPO / "configs" / "synthetic.py"))
  parser.add_argument("--arg", default="",
                      help="the config arg, e.g. model=tiny_synth,steps=3000")
  parser.add_argument("--train_pairs", type=int, default=2000, help="rendered once, then reused")
  parser.add_argument("--val_pairs", type=int, default=32)
  parser.add_argument("--every", type=int, default=250)
  args = parser.parse_args(argv)

  import jax
  from ufm_jax.training import optim, sharding, trainer
  from ufm_jax.training.config_lib import load_config
  from ufm_jax.evaluators import train_evals

  spec = args.config + (f":{args.arg}" if args.arg else "")
  config = load_config(spec)
  if "heldout" not in config.evals:
    raise SystemExit(f"{spec}: the config has no held-out evaluation (evals.heldout)")
  t0 = time.time()
  train_opts = dict(config.input.datasets.synthetic.options)
  tr = render_set(train_opts, config.seed, "train", args.train_pairs)
  heldout = config.evals.heldout
  heldout.num_pairs = heldout.kwargs.num_pairs = args.val_pairs
  heldout.num_images = 0
  evaluator = train_evals.HeldoutEval(heldout, sharding.make_mesh(config.mesh))  # train.py's own
  print(f"{spec}: {args.train_pairs} {train_opts.get('pair_type')} training pairs made in "
        f"{time.time() - t0:.0f} s", flush=True)

  model = trainer.build_model(config)
  hw = tuple(heldout.shape)
  params = jax.jit(lambda r: trainer.init_params(model, hw, r))(jax.random.PRNGKey(config.seed))
  steps = int(config.total_steps)
  tx, labels, _ = optim.make_optimizer(config.optim, params, steps)
  state = optim.TrainState.create(params, tx)
  step_fn = jax.jit(trainer.make_train_step(model, trainer.build_loss(config), tx, labels,
                                          dict(config.get("apply_kwargs", {}))),
                    donate_argnums=(0,))
  predict = jax.jit(trainer.make_predict(model, dict(config.get("apply_kwargs", {}))))

  def heldout_epe(variables):
    scalars = evaluator.run(predict, variables).scalars
    return scalars["epe"], scalars["epe_zero"]

  epe0, zero = heldout_epe(state.variables())
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
      epe, _ = heldout_epe(state.variables())
      t_eval += time.time() - t
      per_step = (time.time() - t0 - t_eval) / max(step - 1, 1)
      print(f"step {step}: held-out EPE {epe:.3f} px ({epe0 / epe:.2f}x of step 0; zero-flow "
            f"{zero:.3f}), train loss {float(m['loss']):.3f}, {per_step:.3f} s/step", flush=True)


if __name__ == "__main__":
  os.environ.setdefault("JAX_PLATFORMS", "cpu")
  main()
