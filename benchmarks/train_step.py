r"""Train-step benchmark: the exact train.py step (ufm_jax.trainer.setup), timed or compiled only.

  python benchmarks/train_step.py --config synthetic                 # time the tiny config here
  python benchmarks/train_step.py --config ufm560 --model ufm_base --mesh data:2,fsdp:4 \
      --devices 8 --batch 96 --size 420x560 --aot --hlo_out /tmp/ufm560.hlo.txt
  python benchmarks/train_step.py --config ufm560 --mesh data:2,fsdp:4 --devices 8 --batch 96 \
      --size 420x560 --aot --scan false     # compile time with unrolled blocks
  python benchmarks/train_step.py --config ufm560 --estimate_only    # memory of the full config

--aot compiles (never runs) the step on --devices fake CPU devices (set before jax is imported)
and prints: parameter bytes (total, per device), optimizer-state bytes per device, XLA's memory
analysis per device, compile time, and the collectives of the compiled HLO by kind (executions,
result bytes per device, the 5 largest with shapes; ufm_jax.hlo_stats). The last line is one JSON
object. --estimate_only traces abstractly (no compile): params, AdamW state, and the activations
the backward pass keeps (JAX's saved residuals) with and without remat at the per-device batch.
Without either, random batches go through the compiled step and the step time is printed.
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import statistics
import sys
import time

REPO = pathlib.Path(__file__).resolve().parents[1]


def _gib(n):
  return f"{n / 2**30:.3f} GiB"


def _tree_bytes(tree):
  import jax
  return sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(tree))


def _per_device_bytes(tree, shardings):
  """Bytes one device holds of `tree` under `shardings` (the largest shard per leaf)."""
  import jax
  total = 0
  for x, s in zip(jax.tree.leaves(tree), jax.tree.leaves(shardings)):
    shape = s.shard_shape(x.shape) if len(x.shape) else ()
    n = 1
    for d in shape:
      n *= d
    total += n * x.dtype.itemsize
  return total


def load(args):
  from ufm_jax import config_lib
  spec = args.config
  path, _, arg = spec.partition(":")
  if not pathlib.Path(path).suffix:
    spec = str(REPO / "configs" / f"{path}.py") + (f":{arg}" if arg else "")
  config = config_lib.load_config(spec)
  config.unlock()
  if args.model:
    config.model_name = args.model
  if args.mesh:
    config.mesh = args.mesh
  if args.remat is not None:
    config.model.remat = args.remat == "true"
  if args.scan is not None:
    config.model.scan_blocks = args.scan == "true"
  batch = args.batch or int(config.input.batch_size)
  if args.size:
    hw = tuple(int(x) for x in args.size.lower().split("x"))
  else:
    side = int(config.input.get("longest_side", 112))
    hw = (side, side) if "synthetic" in args.config else (side * 3 // 4 // 14 * 14, side)
  return config, batch, hw


def aot(config, batch, hw, hlo_out=None):
  import jax
  from ufm_jax import hlo_stats, sharding, trainer
  mesh = sharding.make_mesh(config.mesh)
  t0 = time.perf_counter()
  ts = trainer.setup(config, mesh, hw, total_steps=1000)
  lowered = ts.train_step.lower(ts.sharded_abstract_state(), ts.abstract_batch(batch, hw))
  t_lower = time.perf_counter() - t0
  t0 = time.perf_counter()
  compiled = lowered.compile()
  compile_s = time.perf_counter() - t0
  text = compiled.as_text()
  if hlo_out:
    pathlib.Path(hlo_out).write_text(text)
  colls = hlo_stats.collectives(text)
  summ = hlo_stats.summary(colls)
  p_bytes = _tree_bytes(ts.abstract_params)
  p_dev = _per_device_bytes(ts.abstract_params, ts.param_sh)
  opt_dev = _per_device_bytes(ts.abstract_state.opt_state, ts.state_sh.opt_state)
  state_dev = _per_device_bytes(ts.abstract_state, ts.state_sh)
  ma = compiled.memory_analysis()
  n_params = sum(int(x.size) for x in jax.tree.leaves(ts.abstract_params))
  print(f"config {config.get('model_name', config.get('model_fn'))}: {n_params / 1e6:.1f}M params, "
        f"global batch {batch} at {hw[0]}x{hw[1]}, mesh {dict(mesh.shape)} on {len(jax.devices())} "
        f"{jax.devices()[0].platform} devices, dtype {config.model.get('dtype', 'float32')}, "
        f"remat {config.model.get('remat', False)}, scan_blocks {config.model.get('scan_blocks', False)}")
  print(f"  params {_gib(p_bytes)} total, {_gib(p_dev)} per device; optimizer state "
        f"{_gib(opt_dev)} per device (train state {_gib(state_dev)})")
  print(f"  XLA memory per device: temp {_gib(ma.temp_size_in_bytes)}, args "
        f"{_gib(ma.argument_size_in_bytes)}, out {_gib(ma.output_size_in_bytes)}, alias "
        f"{_gib(ma.alias_size_in_bytes)}")
  print(f"  trace+lower {t_lower:.1f} s, compile {compile_s:.1f} s")
  total = hlo_stats.total_bytes(colls)
  print(f"  collectives per device per step: {_gib(total)} ({total / max(p_bytes, 1):.2f}x the "
        f"parameter bytes)")
  print(hlo_stats.format_summary(summ))
  result = {"param_bytes": p_bytes, "param_bytes_per_device": p_dev,
            "state_bytes_per_device": state_dev, "opt_state_bytes_per_device": opt_dev,
            "temp_bytes_per_device": ma.temp_size_in_bytes, "compile_s": round(compile_s, 1),
            "lower_s": round(t_lower, 1),
            "collective_bytes": {k: v["bytes"] for k, v in summ.items()},
            "collective_count": {k: v["count"] for k, v in summ.items()},
            "collective_bytes_total": total, "mesh": dict(mesh.shape), "batch": batch,
            "size": list(hw), "devices": len(jax.devices())}
  print(json.dumps(result))
  return result


def time_steps(config, batch, hw, steps):
  import jax
  from ufm_jax import sharding, trainer
  mesh = sharding.make_mesh(config.mesh)
  ts = trainer.setup(config, mesh, hw, total_steps=1000)
  state = ts.init_state()
  b = ts.random_batch(mesh, batch, hw)
  h, w = hw
  t0 = time.perf_counter()
  compiled = ts.train_step.lower(state, b).compile()
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
  print(f"config {config.get('model_name')}: batch {batch} at {h}x{w}, {len(jax.devices())} "
        f"device(s) ({jax.devices()[0].platform})")
  print(f"  compile {compile_s:.1f} s; step median {med * 1e3:.1f} ms over {steps} "
        f"(min {min(times) * 1e3:.1f}); {batch / med:.1f} pairs/s; loss {float(m['loss']):.4f}")
  print(f"  peak host RSS {_gib(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)}; "
        f"device peak {_gib(dev['peak_bytes_in_use']) if 'peak_bytes_in_use' in dev else 'n/a (CPU)'}; "
        f"XLA temp {_gib(ma.temp_size_in_bytes)} + args {_gib(ma.argument_size_in_bytes)}")
  print(json.dumps({"step_ms_median": med * 1e3, "step_ms_min": min(times) * 1e3,
                    "pairs_per_s": batch / med, "compile_s": compile_s}))


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


def estimate(config, batch, hw):
  from ufm_jax import sharding, trainer
  mesh = sharding.make_mesh(config.mesh)
  per_dev = batch // sharding.batch_divisor(mesh)
  print(f"config {config.model_name}: batch {batch} at {hw[0]}x{hw[1]}, dtype "
        f"{config.model.get('dtype', 'float32')}, {per_dev} pairs/device")
  for remat in (False, True):
    config.model.remat = remat
    ts = trainer.setup(config, mesh, hw, total_steps=1000)
    if not remat:
      n = sum(int(x.size) for x in __import__("jax").tree.leaves(ts.abstract_params))
      print(f"  {n / 1e6:.1f}M params: {_gib(_tree_bytes(ts.abstract_params))} (f32 master), "
            f"AdamW state {_gib(_tree_bytes(ts.abstract_state.opt_state))}")
    saved = saved_activation_bytes(trainer.build_model(config), ts.abstract_params, per_dev, hw)
    print(f"  remat={remat}: activations kept for the backward pass {_gib(saved)} "
          f"(JAX saved residuals)")


def main():
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  ap.add_argument("--config", default="synthetic", help="configs/NAME.py[:arg] or a path")
  ap.add_argument("--model", default=None, help="model variant (ufm_jax.models.variants)")
  ap.add_argument("--mesh", default=None, help="e.g. data:2,fsdp:4 (default: the config's)")
  ap.add_argument("--devices", type=int, default=None,
                  help="fake CPU devices (--xla_force_host_platform_device_count)")
  ap.add_argument("--batch", type=int, default=None, help="global pairs per step")
  ap.add_argument("--size", default=None, help="HxW (multiples of 14)")
  ap.add_argument("--remat", choices=("true", "false"), default=None)
  ap.add_argument("--scan", choices=("true", "false"), default=None,
                  help="model.scan_blocks: one compiled block body (true) or unrolled blocks")
  ap.add_argument("--steps", type=int, default=5)
  ap.add_argument("--aot", action="store_true", help="compile only: memory, collectives, JSON")
  ap.add_argument("--hlo_out", default=None, help="with --aot: write compiled.as_text() here")
  ap.add_argument("--estimate_only", action="store_true", help="abstract trace, no compile")
  args = ap.parse_args()
  if args.devices:
    if "jax" in sys.modules:
      raise SystemExit("--devices must be set before jax is imported")
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               f" --xla_force_host_platform_device_count={args.devices}")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
  config, batch, hw = load(args)
  if args.aot:
    aot(config, batch, hw, args.hlo_out)
  elif args.estimate_only:
    estimate(config, batch, hw)
  else:
    time_steps(config, batch, hw, args.steps)


if __name__ == "__main__":
  main()
