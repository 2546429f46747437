r"""Train-step benchmark: step time, pairs/s, peak memory; memory estimate of a full config.

  python benchmarks/train_step.py --config synthetic               # time the tiny config here
  python benchmarks/train_step.py --config ufm560 --estimate_only  # full UFM-Base, no compute
  python benchmarks/train_step.py --config configs/ufm560.py:data=of --batch 8 --size 420x560

Timing runs the exact train.py step (same loss, optimizer, shardings, donation) on random batches
of the config's model at --size/--batch. The estimate uses jax.eval_shape (params and optimizer
state, no allocation) and XLA's memory analysis of the lowered and compiled (never run) step at
the config's per-device batch, with and without remat, plus the bytes of the activations the
backward pass keeps (JAX's saved residuals of the loss, traced abstractly). XLA:CPU's temp figure
is a schedule of the whole step that ignores remat; the saved-residual figure is what remat
changes and what dominates on accelerators. Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import resource
import statistics
import sys
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def load_config(spec: str):
  path, _, arg = spec.partition(":")
  p = pathlib.Path(path)
  if not p.suffix:
    p = REPO / "configs" / f"{path}.py"
  module_spec = importlib.util.spec_from_file_location("bench_config", p)
  module = importlib.util.module_from_spec(module_spec)
  module_spec.loader.exec_module(module)
  return module.get_config(arg or None)


def _gib(n):
  return f"{n / 2**30:.2f} GiB"


def _tree_bytes(tree):
  import jax
  return sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(tree))


def build(config, batch: int, hw):
  """(step_fn jitted, abstract state, state shardings, batch sharding, mesh, model)."""
  import jax
  import jax.numpy as jnp
  import train
  from ufm_jax import optim, sharding

  mesh = sharding.make_mesh(config.mesh)
  model = train.build_model(config)
  dummy = jax.ShapeDtypeStruct((1, *hw, 3), jnp.uint8)
  abstract_params = jax.eval_shape(lambda r, x: model.init(r, x, x)["params"],
                                   jax.random.PRNGKey(0), dummy)
  tx, labels, _ = optim.make_optimizer(config.optim, abstract_params, 1000)
  abstract_state = jax.eval_shape(lambda p: optim.TrainState.create(p, tx), abstract_params)
  state_sh = sharding.tree_shardings(abstract_state, mesh, config.sharding_rules)
  step = train.make_train_step(model, train.build_loss(config), tx, labels,
                               dict(config.get("apply_kwargs", {})))
  batch_sh = sharding.batch_sharding(mesh)
  jitted = jax.jit(step, in_shardings=(state_sh, batch_sh),
                   out_shardings=(state_sh, sharding.replicated(mesh)), donate_argnums=(0,))
  return jitted, abstract_state, abstract_params, state_sh, batch_sh, mesh, model, tx


def abstract_batch(batch, hw, refine=False):
  import jax
  import jax.numpy as jnp
  h, w = hw
  return {"image0": jax.ShapeDtypeStruct((batch, h, w, 3), jnp.uint8),
          "image1": jax.ShapeDtypeStruct((batch, h, w, 3), jnp.uint8),
          "flow": jax.ShapeDtypeStruct((batch, h, w, 2), jnp.float32),
          "covisibility": jax.ShapeDtypeStruct((batch, h, w), jnp.bool_),
          "flow_valid": jax.ShapeDtypeStruct((batch, h, w), jnp.bool_),
          "covis_valid": jax.ShapeDtypeStruct((batch, h, w), jnp.bool_)}


def random_batch(batch, hw, seed=0):
  import numpy as np
  rng = np.random.default_rng(seed)
  h, w = hw
  return {"image0": rng.integers(0, 256, (batch, h, w, 3), dtype=np.uint8),
          "image1": rng.integers(0, 256, (batch, h, w, 3), dtype=np.uint8),
          "flow": rng.normal(0, 5, (batch, h, w, 2)).astype(np.float32),
          "covisibility": rng.random((batch, h, w)) < 0.7,
          "flow_valid": np.ones((batch, h, w), bool), "covis_valid": np.ones((batch, h, w), bool)}


def time_steps(config, batch, hw, steps):
  import jax
  from ufm_jax import optim, sharding
  jitted, abstract_state, _, state_sh, _, mesh, model, tx = build(config, batch, hw)
  import jax.numpy as jnp
  params = jax.jit(lambda r: model.init(r, jnp.zeros((1, *hw, 3), jnp.uint8),
                                        jnp.zeros((1, *hw, 3), jnp.uint8))["params"])(
                                            jax.random.PRNGKey(0))
  state = jax.jit(lambda p: optim.TrainState.create(p, tx), out_shardings=state_sh)(params)
  b = sharding.make_global_batch(random_batch(batch, hw), mesh)
  t0 = time.perf_counter()
  compiled = jitted.lower(state, b).compile()
  compile_s = time.perf_counter() - t0
  state, m = compiled(state, b)
  jax.block_until_ready(m)
  times = []
  for _ in range(steps):
    t0 = time.perf_counter()
    state, m = compiled(state, b)
    jax.block_until_ready(m)
    times.append(time.perf_counter() - t0)
  med = statistics.median(times)
  dev = jax.devices()[0].memory_stats() or {}
  ma = compiled.memory_analysis()
  print(f"config {config_name}: batch {batch} at {hw[0]}x{hw[1]}, {len(jax.devices())} device(s) "
        f"({jax.devices()[0].platform})")
  print(f"  compile {compile_s:.1f} s; step median {med * 1e3:.1f} ms over {steps} "
        f"(min {min(times) * 1e3:.1f}); {batch / med:.1f} pairs/s; loss {float(m['loss']):.4f}")
  print(f"  peak host RSS {_gib(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)}; "
        f"device peak {_gib(dev['peak_bytes_in_use']) if 'peak_bytes_in_use' in dev else 'n/a (CPU)'}; "
        f"XLA temp {_gib(ma.temp_size_in_bytes)} + args {_gib(ma.argument_size_in_bytes)}")


def saved_activation_bytes(model, abstract_params, per_device_batch: int, hw) -> int:
  """Bytes of the forward activations kept for the backward pass (abstract trace, no compute)."""
  import jax
  import jax.numpy as jnp
  from jax._src.ad_checkpoint import saved_residuals  # also behind jax.ad_checkpoint.print_saved_residuals

  x = jax.ShapeDtypeStruct((per_device_batch, *hw, 3), jnp.uint8)

  def loss(params, a, b):
    out = model.apply({"params": params}, a, b)
    return jnp.mean(out["flow"]) + jnp.mean(out["covisibility_logits"])

  residuals = saved_residuals(loss, abstract_params, x, x)
  return sum(int(aval.size) * aval.dtype.itemsize for aval, why in residuals
             if not why.startswith("from the argument"))


def estimate(config, batch, hw, compile_step=True):
  import jax
  import train
  from ufm_jax import sharding
  results = {}
  for remat in (False, True):
    config.model.remat = remat
    jitted, abstract_state, abstract_params, state_sh, batch_sh, mesh, _, _ = build(config, batch, hw)
    n_params = sum(int(x.size) for x in jax.tree.leaves(abstract_params))
    p_bytes = _tree_bytes(abstract_params)
    o_bytes = _tree_bytes(abstract_state.opt_state)
    per_dev = batch // sharding.batch_divisor(mesh)
    line = {"params": n_params, "param_bytes": p_bytes, "opt_bytes": o_bytes}
    model = train.build_model(config)
    line["saved"] = saved_activation_bytes(model, abstract_params, per_dev, hw)
    if compile_step:
      st = jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                        abstract_state, state_sh)
      bt = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=batch_sh),
                        abstract_batch(batch, hw))
      t0 = time.perf_counter()
      ma = jitted.lower(st, bt).compile().memory_analysis()
      line.update(temp=ma.temp_size_in_bytes, args=ma.argument_size_in_bytes,
                  out=ma.output_size_in_bytes, alias=ma.alias_size_in_bytes,
                  compile_s=time.perf_counter() - t0, per_device_batch=per_dev)
    results[remat] = line
  r = results[False]
  print(f"config {config_name}: model {config.model_name} ({r['params'] / 1e6:.1f}M params), "
        f"batch {batch} at {hw[0]}x{hw[1]}, dtype {config.model.get('dtype', 'float32')}")
  print(f"  params {_gib(r['param_bytes'])} (f32 master), AdamW state {_gib(r['opt_bytes'])}")
  for remat, line in results.items():
    print(f"  remat={remat}: activations kept for the backward pass {_gib(line['saved'])} at "
          f"{per_dev} pairs/device (JAX saved residuals)")
    if "temp" in line:
      print(f"  remat={remat}: XLA temp (activations + workspace) {_gib(line['temp'])} at "
            f"{line['per_device_batch']} pairs/device; args {_gib(line['args'])}; "
            f"total live ~{_gib(line['temp'] + line['args'] + line['out'] - line['alias'])} "
            f"(compiled in {line['compile_s']:.0f} s, not run)")


def main():
  global config_name
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  ap.add_argument("--config", default="synthetic")
  ap.add_argument("--batch", type=int, default=None, help="global pairs per step")
  ap.add_argument("--size", default=None, help="HxW (multiples of 14)")
  ap.add_argument("--steps", type=int, default=5)
  ap.add_argument("--estimate_only", action="store_true", help="no compute: eval_shape + compile")
  ap.add_argument("--no_compile", action="store_true", help="estimate params/opt state only")
  args = ap.parse_args()
  config_name = args.config
  config = load_config(args.config)
  batch = args.batch or config.input.batch_size
  if args.size:
    hw = tuple(int(x) for x in args.size.lower().split("x"))
  else:
    side = int(config.input.get("longest_side", 112))
    hw = (side, side) if "synthetic" in args.config else (side * 3 // 4 // 14 * 14, side)
  if args.estimate_only:
    estimate(config, batch, hw, compile_step=not args.no_compile)
  else:
    time_steps(config, batch, hw, args.steps)


config_name = ""

if __name__ == "__main__":
  main()
