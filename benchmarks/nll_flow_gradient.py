"""What `detach_flow=False` would add to a covariance run's flow training: at a trained workdir
(train.py with a `flow_nll` term), the gradient norm of the NLL with its residual not detached
against that of the run's flow term, on the flow head and on the trunk (encoder and fusion
transformer), over fresh pairs of the run's synthetic task (docs/uncertainty.md, "The loss").

  python benchmarks/nll_flow_gradient.py --workdir workdirs/synthetic_cov
"""

import argparse
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from ufm_jax.runtime import model_io
from ufm_jax.training import losses
from ufm_jax.data import synthetic


def main():
  ap = argparse.ArgumentParser(description=__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--workdir", required=True)
  ap.add_argument("--pairs", type=int, default=16, help="unique pairs (both directions each)")
  ap.add_argument("--seed", type=int, default=10_000, help="first pair seed (training uses 0..)")
  args = ap.parse_args()
  config = json.loads((pathlib.Path(args.workdir) / "config.json").read_text())
  loss = config["loss"]
  nll = next((n for n in loss["terms"] if loss[n]["type"] == "flow_nll"), None)
  if nll is None:
    raise SystemExit(f"{args.workdir}: the run's loss has no flow_nll term")
  flow_term = loss[nll]["pixels"]
  loss[nll]["detach_flow"] = False
  recipe = losses.recipe_from_config(loss)
  model, variables = model_io.load_workdir(args.workdir)
  task = config["evals"]["heldout"]["kwargs"]
  scfg = synthetic.SyntheticConfig(size=tuple(task["size"]), pair_type=task["pair_type"],
                                   max_shift=task.get("max_shift", 10))
  rows = [s for seed in range(args.seed, args.seed + args.pairs)
          for s in synthetic.generate_pair(seed, scfg)]
  keys = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")
  batch = {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in keys}

  def term(params, name):
    out = model.apply({**variables, "params": params}, batch["image0"], batch["image1"],
                      **config.get("apply_kwargs", {}))
    return recipe(out, batch)[1][f"loss_{name}"]

  norms = {}
  for name in (flow_term, nll):
    grads = traverse_util.flatten_dict(jax.jit(jax.grad(lambda p: term(p, name)))(
        variables["params"]), sep="/")
    part = {"flow head": lambda k: k.startswith("head1"),
            "trunk": lambda k: k.startswith(("encoder", "info_sharing"))}
    norms[name] = {where: float(np.sqrt(sum(float(jnp.sum(jnp.square(g)))
                                            for k, g in grads.items() if test(k))))
                   for where, test in part.items()}
  print(f"{args.workdir}: {2 * args.pairs} rows of {task['pair_type']} pairs at {task['size']}")
  for where in ("flow head", "trunk"):
    a, b = norms[flow_term][where], norms[nll][where]
    print(f"  {where}: |grad {flow_term}| {a:.4g}, |grad {nll} (detach_flow=False)| {b:.4g}, "
          f"ratio {b / a:.4f}")


if __name__ == "__main__":
  main()
