"""What FSDP gathers whole at the start of a step, by module: every parameter outside the scanned
blocks' stacks (those are gathered a layer at a time inside the scan, `sharding.layer_gather`).

  python benchmarks/fsdp_whole.py --config ufm560 --config ufm560_refine

Prints, per recipe, the float32 bytes of the whole parameter tree and of the part gathered whole
(each chip holds that part whole for the step), then the largest modules of that part.
"""

import argparse
import collections

import jax
import numpy as np

from ufm_jax.training import config_lib, optim, trainer
from ufm_jax.models import scan, ufm


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--config", action="append", default=None,
                 help="a recipe under configs/ (repeatable; default ufm560)")
  p.add_argument("--top", type=int, default=8, help="modules listed per recipe")
  args = p.parse_args()
  for name in args.config or ["ufm560"]:
    config = config_lib.load_config(f"configs/{name}.py")
    shapes = ufm.variable_shapes(trainer.build_model(config))["params"]
    total, whole = 0, collections.Counter()
    for path, a in jax.tree_util.tree_flatten_with_path(shapes)[0]:
      nbytes = int(np.prod(a.shape)) * 4
      total += nbytes
      key = optim.path_str(path)
      if not scan.STACKED_PATH.search(key):
        whole["/".join(key.split("/")[:2])] += nbytes
    part = sum(whole.values())
    print(f"{name}: parameters {total / 2**30:.3f} GiB in float32; gathered whole at the step's "
          f"start {part / 2**20:.1f} MiB ({100 * part / total:.1f}%), the rest a layer at a time")
    for module, nbytes in whole.most_common(args.top):
      print(f"  {module:48s} {nbytes / 2**20:8.1f} MiB")


if __name__ == "__main__":
  main()
