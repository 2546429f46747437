r"""Time to save a training checkpoint: what a preempted run must finish within its cluster's grace
time (Slurm's KillWait, GKE's terminationGracePeriodSeconds; docs/launch.md).

  python benchmarks/checkpoint_save.py                       # UFM-Base, the 560 recipe's state
  python benchmarks/checkpoint_save.py --config ufm560 --dir /mnt/fast/ckpt --repeats 3

Builds the recipe's train state (trainer.setup: float32 parameters and AdamW's two moments, on one
device of this host, filled with random values so that nothing compresses better than a trained
state would) and saves it through the project's own checkpoint code (ufm_jax.runtime.checkpoint:
make_manager and save, the calls train.py's preemption path makes), asynchronously as train.py
does, then waits until it is on disk. Prints the state's bytes, the seconds until save() returns
(the training loop blocks this long) and until the checkpoint is complete (what the grace time
must cover), per repeat, each into a fresh directory under --dir (removed afterwards).
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import functools
import json
import pathlib
import shutil
import statistics
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]


def main():
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  ap.add_argument("--config", default="ufm560", help="configs/NAME.py whose train state is saved")
  ap.add_argument("--dir", default=None, help="where to write (default: a temporary directory)")
  ap.add_argument("--repeats", type=int, default=2)
  args = ap.parse_args()

  import jax
  import jax.numpy as jnp
  from ufm_jax.planning import planner
  from ufm_jax.runtime import checkpoint
  from ufm_jax.training import config_lib, sharding, trainer

  config = config_lib.load_config(str(REPO / "configs" / f"{args.config}.py"))
  mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
  ts = trainer.setup(config, mesh, planner.largest_shape(config), total_steps=1000)
  @functools.partial(jax.jit, static_argnums=(1, 2))
  def normal(key, shape, dtype):
    return jax.random.normal(key, shape, dtype)

  def fill(i, a, sh):
    # One leaf at a time, on the device as train.py's state is (no second copy in host memory);
    # random, so that nothing compresses better than a trained state would.
    if jnp.issubdtype(a.dtype, jnp.floating) and a.shape:
      return jax.device_put(normal(jax.random.PRNGKey(i), a.shape, a.dtype), sh)
    return jax.device_put(jnp.zeros(a.shape, a.dtype), sh)

  leaves, tree = jax.tree.flatten(ts.abstract_state)
  state = jax.tree.unflatten(tree, [fill(i, a, sh) for i, (a, sh) in
                                    enumerate(zip(leaves, jax.tree.leaves(ts.state_sh)))])
  params = sum(int(x.size) for x in jax.tree.leaves(ts.abstract_params))
  nbytes = sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(state))
  opt = sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(state.opt_state))
  print(f"{config.get('model_name')}: {params / 1e6:.1f}M parameters; train state "
        f"{nbytes / 2**30:.3f} GiB (AdamW state {opt / 2**30:.3f} GiB)", flush=True)
  base = pathlib.Path(args.dir or tempfile.mkdtemp(prefix="ckpt_save_"))
  returned, finished = [], []
  for i in range(args.repeats):
    workdir = base / f"run{i}"
    manager = checkpoint.make_manager(workdir, 1, 1, async_save=True)
    t0 = time.perf_counter()
    checkpoint.save(manager, 1, state, None, force=True)
    t1 = time.perf_counter()
    manager.wait_until_finished()
    t2 = time.perf_counter()
    manager.close()
    on_disk = sum(f.stat().st_size for f in workdir.rglob("*") if f.is_file())
    returned.append(t1 - t0)
    finished.append(t2 - t0)
    print(f"  save {i}: save() returned after {t1 - t0:.2f} s, on disk after {t2 - t0:.2f} s "
          f"({on_disk / 2**30:.3f} GiB written)", flush=True)
    shutil.rmtree(workdir)
  if not args.dir:
    shutil.rmtree(base, ignore_errors=True)
  print(json.dumps({"config": args.config, "param_count": params, "state_bytes": nbytes,
                    "opt_state_bytes": opt, "save_returned_s": returned, "save_finished_s": finished,
                    "save_finished_s_median": statistics.median(finished)}))


if __name__ == "__main__":
  sys.exit(main())
