"""How far apart the per-layer and per-step FSDP gathers train the tiny scanned model on this CPU
(the program pair of tests/test_fsdp_layer_gather.py, remat off, data 2 x fsdp 4): one step at a
time from the same state (what the test bounds) and along free-running trajectories (what it
used to bound). Prints one JSON line of relative loss and grad-norm differences and the largest
absolute param difference. Run with 8 fake devices; --xla_cpu_max_isa stands in for another CPU:

  XLA_FLAGS="--xla_force_host_platform_device_count=8 --xla_cpu_max_isa=AVX2" \
      python benchmarks/fsdp_rounding.py

Figures: docs/testing.md ('Tolerances across CPUs')."""

import json

import jax
import numpy as np

from ufm_jax.training import config_lib, sharding, trainer

STEPS = 3


def compile_steps():
  steps = {}
  for mode in ("layer", "step"):
    c = config_lib.load_config("configs/synthetic.py:eval=false")
    c.unlock()
    c.model_name, c.model.scan_blocks, c.model.remat = "tiny", True, False
    c.mesh, c.fsdp_gather = "data:2,fsdp:4", mode
    c.sharding_min_size = 2 ** 10
    c.optim.warmup_frac, c.optim.eps = 0.0, 1.0   # as the test: see its comments
    mesh = sharding.make_mesh(c.mesh)
    ts = trainer.setup(c, mesh, (56, 56), total_steps=100)
    state0 = ts.init_state(0)
    steps[mode] = ts.train_step.lower(state0, ts.random_batch(mesh, 16, (56, 56), 0)).compile()
  batches = [ts.random_batch(mesh, 16, (56, 56), i) for i in range(STEPS)]
  return steps, state0, batches


def flat(state):
  return {"/".join(str(getattr(k, "key", k)) for k in p): np.asarray(v)
          for p, v in jax.tree_util.tree_flatten_with_path(state.params)[0]}


def main():
  steps, state0, batches = compile_steps()
  copy = lambda s: jax.tree.map(lambda x: x.copy(), s)  # noqa: E731  (the steps donate it)
  free = {}
  for mode, f in steps.items():
    s, losses, norms = copy(state0), [], []
    for b in batches:
      s, m = f(s, b)
      losses.append(float(m["loss"]))
      norms.append(float(m["grad_norm"]))
    free[mode] = (losses, norms, flat(s))
  per = {mode: ([], [], []) for mode in steps}
  s = copy(state0)
  for b in batches:
    new = {}
    for mode, f in steps.items():
      new[mode], m = f(copy(s), b)
      per[mode][0].append(float(m["loss"]))
      per[mode][1].append(float(m["grad_norm"]))
      per[mode][2].append(flat(new[mode]))
    s = new["step"]
  rel = lambda a, b: [abs(x - y) / abs(y) for x, y in zip(a, b)]  # noqa: E731
  worst = lambda a, b: max(float(np.max(np.abs(a[k] - b[k]))) for k in b)  # noqa: E731
  print(json.dumps({
      "per_step_loss": rel(per["layer"][0], per["step"][0]),
      "per_step_grad_norm": rel(per["layer"][1], per["step"][1]),
      "per_step_param_abs": [worst(a, b) for a, b in zip(per["layer"][2], per["step"][2])],
      "free_loss": rel(free["layer"][0], free["step"][0]),
      "free_grad_norm": rel(free["layer"][1], free["step"][1]),
      "free_param_abs": worst(free["layer"][2], free["step"][2]),
      "grad_norms": per["step"][1]}))


if __name__ == "__main__":
  main()
