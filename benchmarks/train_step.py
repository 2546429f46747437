r"""Train-step benchmark: the exact train.py step (ufm_jax.trainer.setup), timed or compiled only.

  python benchmarks/train_step.py --config synthetic                 # time the tiny config here
  python benchmarks/train_step.py --config ufm560 --model ufm_base --mesh data:2,fsdp:4 \
      --devices 8 --batch 96 --size 420x560 --aot --hlo_out /tmp/ufm560.hlo.txt
  python benchmarks/train_step.py --config ufm560 --mesh data:2,fsdp:4 --devices 8 --batch 96 \
      --size 420x560 --aot --scan false     # compile time with unrolled blocks
  python benchmarks/train_step.py --config ufm560 --estimate_only    # memory of the full config
  python benchmarks/train_step.py --config ufm560 --topology v5e-8 --fit   # plan a TPU slice

--aot compiles (never runs) the step on --devices fake CPU devices (set before jax is imported)
and prints: parameter bytes (total, per device), optimizer-state bytes per device, XLA's memory
analysis per device, compile time, and the collectives of the compiled HLO by kind (executions,
result bytes per device, the 5 largest with shapes; ufm_jax.hlo_stats). The last line is one JSON
object. --estimate_only traces abstractly (no compile): params, AdamW state, and the activations
the backward pass keeps (JAX's saved residuals) with and without remat at the per-device batch.
Without either, random batches go through the compiled step and the step time is printed.

--topology NAME (a TPU slice of ufm_jax.topologies: v5e-4, v5e-8, v5e-256, v5p-8, v5p-128, ...)
compiles the step for that slice from this host (libtpu installed: `pip install "ufm_jax[tpu]"`,
no TPU) on the mesh --mesh (default data:1,fsdp:-1: FSDP over every chip), at the largest of the
recipe's training shapes (the most memory) or --size, and prints HBM per chip (temp + arguments +
outputs - aliases) against the chip's, the collectives by kind, the FLOPs per step (the unrolled
program's count, ufm_jax.hlo_stats.train_step_flops: XLA counts a scanned block once), and the
step time and days of the recipe's epochs (the mean over its training shapes) at --mfu of the
chips' bf16 peak. --fit searches the largest per-chip batch that fits, one compile per probe
(minutes each at full size). The last line is one JSON object (chips, device_kind,
hbm_bytes_per_chip, hbm_capacity_bytes, flops_per_step, collective_bytes, compile_s, ...).
--topology A,B,... --time_only skips the compile (and libtpu): step time and days per slice, GPU
nodes too (h100-8, h200-8, a100-8), from the FLOP count alone. docs/scale.md has the figures.
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


def parse_size(text: str):
  return tuple(int(x) for x in text.lower().split("x"))


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
  if args.fsdp_gather:
    config.fsdp_gather = args.fsdp_gather
  if args.grad_accum:
    config.grad_accum = args.grad_accum
  batch = args.batch or int(config.input.batch_size)
  if args.size:
    hw = parse_size(args.size)
  else:
    side = int(config.input.get("longest_side", 112))
    hw = (side, side) if "synthetic" in args.config else (side * 3 // 4 // 14 * 14, side)
  return config, batch, hw


def compile_step(ts, batch, hw, hlo_out=None) -> dict:
  """Compile (never run) the train step at global `batch`: XLA's memory analysis per device, the
  collectives of the compiled HLO, compile time. `fits` is False (and no figures but the error)
  when XLA:TPU refuses the program for want of HBM."""
  from ufm_jax import hlo_stats
  t0 = time.perf_counter()
  lowered = ts.train_step.lower(ts.sharded_abstract_state(), ts.abstract_batch(batch, hw))
  t_lower = time.perf_counter() - t0
  t0 = time.perf_counter()
  try:
    compiled = lowered.compile()
  except Exception as e:  # noqa: BLE001 - jaxlib's XlaRuntimeError
    if "RESOURCE_EXHAUSTED" not in str(e):
      raise
    return {"fits": False, "batch": batch, "error": str(e).splitlines()[0][:300],
            "compile_s": round(time.perf_counter() - t0, 1), "lower_s": round(t_lower, 1)}
  compile_s = time.perf_counter() - t0
  text = compiled.as_text()
  if hlo_out:
    pathlib.Path(hlo_out).write_text(text)
  colls = hlo_stats.collectives(text)
  summ = hlo_stats.summary(colls)
  ma = compiled.memory_analysis()
  hbm = (ma.temp_size_in_bytes + ma.argument_size_in_bytes + ma.output_size_in_bytes -
         ma.alias_size_in_bytes)
  return {"fits": True, "batch": batch, "hbm_bytes_per_chip": hbm,
          "temp_bytes_per_device": ma.temp_size_in_bytes,
          "argument_bytes_per_device": ma.argument_size_in_bytes,
          "output_bytes_per_device": ma.output_size_in_bytes,
          "alias_bytes_per_device": ma.alias_size_in_bytes,
          "compile_s": round(compile_s, 1), "lower_s": round(t_lower, 1),
          "collective_bytes": {k: v["bytes"] for k, v in summ.items()},
          "collective_count": {k: v["count"] for k, v in summ.items()},
          "collective_bytes_total": hlo_stats.total_bytes(colls), "_summary": summ,
          "_text": text}


def describe(config, ts, mesh, devices, batch, hw) -> dict:
  """Prints the run's shape and the parameter/optimizer bytes; returns them."""
  import jax
  p_bytes = _tree_bytes(ts.abstract_params)
  p_dev = _per_device_bytes(ts.abstract_params, ts.param_sh)
  opt_dev = _per_device_bytes(ts.abstract_state.opt_state, ts.state_sh.opt_state)
  state_dev = _per_device_bytes(ts.abstract_state, ts.state_sh)
  n_params = sum(int(x.size) for x in jax.tree.leaves(ts.abstract_params))
  print(f"config {config.get('model_name', config.get('model_fn'))}: {n_params / 1e6:.1f}M params, "
        f"global batch {batch} at {hw[0]}x{hw[1]}, mesh {dict(mesh.shape)} on {len(devices)} "
        f"{devices[0].device_kind} devices, dtype {config.model.get('dtype', 'float32')}, "
        f"remat {config.model.get('remat', False)}, "
        f"scan_blocks {config.model.get('scan_blocks', False)}, "
        f"fsdp_gather {config.get('fsdp_gather', 'layer')}, "
        f"grad_accum {config.get('grad_accum', 1)}")
  print(f"  params {_gib(p_bytes)} total, {_gib(p_dev)} per device; optimizer state "
        f"{_gib(opt_dev)} per device (train state {_gib(state_dev)})")
  return {"param_bytes": p_bytes, "param_bytes_per_device": p_dev,
          "state_bytes_per_device": state_dev, "opt_state_bytes_per_device": opt_dev,
          "mesh": dict(mesh.shape), "size": list(hw), "devices": len(devices)}


def print_compiled(r: dict, param_bytes: int):
  from ufm_jax import hlo_stats
  if not r["fits"]:
    print(f"  batch {r['batch']}: does not fit ({r['error']}); compile {r['compile_s']:.1f} s")
  if "_summary" not in r:
    return
  print(f"  XLA memory per device: temp {_gib(r['temp_bytes_per_device'])}, args "
        f"{_gib(r['argument_bytes_per_device'])}, out {_gib(r['output_bytes_per_device'])}, alias "
        f"{_gib(r['alias_bytes_per_device'])}")
  print(f"  trace+lower {r['lower_s']:.1f} s, compile {r['compile_s']:.1f} s")
  total = r["collective_bytes_total"]
  print(f"  collectives per device per step: {_gib(total)} ({total / max(param_bytes, 1):.2f}x the "
        f"parameter bytes)")
  print(hlo_stats.format_summary(r["_summary"]))


def aot(config, batch, hw, hlo_out=None):
  import jax
  from ufm_jax import sharding, trainer
  mesh = sharding.make_mesh(config.mesh)
  ts = trainer.setup(config, mesh, hw, total_steps=1000)
  info = describe(config, ts, mesh, jax.devices(), batch, hw)
  r = compile_step(ts, batch, hw, hlo_out)
  print_compiled(r, info["param_bytes"])
  result = {**info, **_public(r), "batch": batch}
  print(json.dumps(result))
  return result


# ----------------------------------------------------------------------------- TPU planning


def rows_per_epoch(config) -> int:
  """Batch rows of one epoch of the recipe: its quotas, both directions when symmetrized (as
  ufm_jax.data.pipeline counts them, without reading the data)."""
  quotas = sum(int(d.quota) for d in config.input.datasets.values())
  return quotas * (2 if config.input.get("symmetrize", True) else 1)


def recipe_shapes(config):
  """The (H, W) training shapes of the recipe (one drawn per step, uniformly)."""
  from ufm_jax.data import augment
  return augment.training_shapes(int(config.input.longest_side),
                                 tuple(config.input.get("aspect_ratios",
                                                        augment.DEFAULT_ASPECT_RATIOS)))


def _quantum(config) -> int:
  """Rows per chip come in multiples of this: a symmetrized pair's (a, b), (b, a) rows stay on
  one chip, and each of grad_accum microbatches takes whole pairs from every chip."""
  from ufm_jax import accumulation
  return accumulation.pair_rows(config.get("apply_kwargs")) * int(config.get("grad_accum", 1))


def _per_chip_batch(config, args, n: int) -> int:
  """--per_chip_batch, or --batch (else the recipe's) split over `n` chips."""
  quantum = _quantum(config)
  if args.per_chip_batch:
    per_chip = args.per_chip_batch
  elif args.batch:
    if args.batch % n:
      raise SystemExit(f"--batch {args.batch} does not split over {n} chips")
    per_chip = args.batch // n
  else:
    per_chip = int(config.input.batch_size) // n
    if per_chip * n != int(config.input.batch_size) or per_chip < quantum:
      print(f"  the recipe's batch {config.input.batch_size} does not split over {n} chips: "
            f"{quantum} per chip instead")
      per_chip = quantum
  if per_chip % quantum:
    raise SystemExit(f"{per_chip} rows per chip: need a multiple of {quantum} (a symmetrized "
                     f"pair's two rows on one chip, times grad_accum "
                     f"{config.get('grad_accum', 1)} microbatches)")
  return per_chip


def _shapes_and_size(config, args):
  """(the recipe's training shapes, the (H, W) to compile at: --size, else the largest of them,
  which needs the most memory)."""
  shapes = recipe_shapes(config) if "longest_side" in config.input else []
  if not args.size and not shapes:
    raise SystemExit("the config's input has no longest_side: pass --size HxW")
  hw = parse_size(args.size) if args.size else max(shapes, key=lambda s: s[0] * s[1])
  return shapes or [hw], hw


def plan(config, args):
  """--topology: the step compiled for a TPU slice from this host (libtpu, no TPU)."""
  from ufm_jax import sharding, topologies, trainer
  slc = topologies.get(args.topology)
  chip = topologies.CHIPS[slc.chip]
  devices = topologies.devices(args.topology)
  config.mesh = args.mesh or "data:1,fsdp:-1"
  mesh = sharding.make_mesh(config.mesh, devices)
  shapes, hw = _shapes_and_size(config, args)
  n = sharding.batch_divisor(mesh)
  quantum = _quantum(config)
  per_chip = _per_chip_batch(config, args, n)
  ts = trainer.setup(config, mesh, hw, total_steps=1000)
  info = describe(config, ts, mesh, devices, per_chip * n, hw)
  print(f"  {args.topology}: {slc.chips} chips ({slc.topology}, {slc.chip_config}), "
        f"{_gib(chip.hbm_bytes)} HBM per chip, bf16 peak {chip.peak_bf16_flops / 1e12:.0f} TFLOP/s",
        flush=True)

  def probe(b):
    r = compile_step(ts, b * n, hw)
    if r["fits"] and r["hbm_bytes_per_chip"] > chip.hbm_bytes:
      # XLA:TPU refuses some programs that cannot fit, but not all (a v5p-8 step needing
      # 122 GiB of the chip's 95.74 compiled): the memory analysis decides.
      r["fits"] = False
      r["error"] = (f"compiled, but needs {_gib(r['hbm_bytes_per_chip'])} of "
                    f"{_gib(chip.hbm_bytes)} per chip")
    state = f"{_gib(r['hbm_bytes_per_chip'])} per chip" if "hbm_bytes_per_chip" in r else ""
    state += "" if r["fits"] else (" - " if state else "") + "does not fit"
    print(f"  probe {b} per chip ({b * n} global): {state}, compile {r['compile_s']:.0f} s",
          flush=True)
    return r

  probes, best, exact = {}, None, None
  if args.fit:
    best, fails, probes = topologies.fit_search(probe, per_chip, quantum, chip.hbm_bytes,
                                                args.max_probes)
    listed = ", ".join(f"{b} {'fits' if r['fits'] else 'no'}" for b, r in sorted(probes.items()))
    exact = fails is not None and fails - best <= quantum
    print(f"  largest per-chip batch that fits: {best or 'none'}"
          f"{'' if exact else f' or more ({args.max_probes} probes ran out)'} (probes: {listed})")
    per_chip = best or per_chip
  r = probes.get(per_chip) or probe(per_chip)
  if args.hlo_out and "_text" in r:
    pathlib.Path(args.hlo_out).write_text(r["_text"])
  print_compiled(r, info["param_bytes"])
  batch = per_chip * n
  result = {"topology": args.topology, "chips": slc.chips, "device_kind": devices[0].device_kind,
            "hbm_capacity_bytes": chip.hbm_bytes, "per_chip_batch": per_chip,
            "global_batch": batch, **info, **_public(r)}
  if args.fit:
    result.update(max_per_chip_batch=best, max_per_chip_batch_exact=exact, probes={
        b: {"fits": p["fits"], "hbm_bytes_per_chip": p.get("hbm_bytes_per_chip"),
            "compile_s": p["compile_s"]} for b, p in sorted(probes.items())})
  if "hbm_bytes_per_chip" in r:
    print(f"  HBM per chip: {_gib(r['hbm_bytes_per_chip'])} of {_gib(chip.hbm_bytes)} "
          f"({100 * r['hbm_bytes_per_chip'] / chip.hbm_bytes:.0f}%)"
          f"{'' if r['fits'] else ': does not fit'}")
  if args.mfu > 0:
    per_row = flops_per_row(config, set(shapes) | {hw}, quantum)
    executed = flops_per_row(config, [hw], quantum, remat=config.model.get("remat"))[hw] * batch
    result["executed_flops_per_step"] = executed
    result.update(estimate_time(config, per_row, hw, batch, slc.chips, chip, args.mfu,
                                executed=executed))
  print(json.dumps(result))
  return result


def time_only(config, args):
  """--time_only: step time and recipe days for each of the --topology slices (a comma list,
  GPU nodes too), from the FLOP count alone: no compile, no libtpu."""
  from ufm_jax import topologies
  shapes, hw = _shapes_and_size(config, args)
  quantum = _quantum(config)
  print(f"config {config.get('model_name')}: FLOPs per row at {len(set(shapes) | {hw})} shapes "
        f"(unrolled count on the host CPU)", flush=True)
  per_row = flops_per_row(config, set(shapes) | {hw}, quantum)
  rows = []
  for name in args.topology.split(","):
    slc = topologies.get(name)
    print(f"{name}: {slc.chips} x {topologies.CHIPS[slc.chip].device_kind}")
    batch = _per_chip_batch(config, args, slc.chips) * slc.chips
    rows.append({"topology": name, "chips": slc.chips, "global_batch": batch,
                 **estimate_time(config, per_row, hw, batch, slc.chips,
                                 topologies.CHIPS[slc.chip], args.mfu)})
  print(json.dumps(rows))
  return rows


def _public(r: dict) -> dict:
  return {k: v for k, v in r.items() if not k.startswith("_")}


def flops_per_row(config, shapes, quantum: int, remat: bool = False) -> dict:
  """{(H, W): FLOPs of the train step per batch row} (ufm_jax.hlo_stats.train_step_flops, the
  unrolled count), without remat's recomputation unless `remat`: model FLOPs, as MFU counts them.
  Counted at `quantum` rows: a step's FLOPs are linear in its rows but for the optimizer update,
  counted once per step (UFM-Base: ~20 FLOPs per parameter, under 0.1% of a 2-row step)."""
  import copy
  from ufm_jax import hlo_stats
  config = copy.deepcopy(config)
  config.model.remat = bool(remat)
  return {s: hlo_stats.train_step_flops(config, s, quantum) / quantum for s in shapes}


def estimate_time(config, per_row, hw, batch, chips, chip, mfu, executed=None) -> dict:
  """The step time at `hw` and the duration of the recipe's epochs (each step draws one of its
  shapes uniformly: the mean over them) at `mfu` of the chips' bf16 peak."""
  import math
  peak = chips * chip.peak_bf16_flops
  step_flops = per_row[hw] * batch
  step_s = step_flops / (peak * mfu)
  print(f"  FLOPs per step at {hw[0]}x{hw[1]}: {step_flops / 1e12:.4g} TFLOP "
        f"({per_row[hw] / 1e9:.0f} GFLOP per row" +
        (f"; with remat's recomputation {executed / 1e12:.4g} TFLOP)" if executed else ")"))
  print(f"  at {100 * mfu:.0f}% MFU (assumed) of {chips} x {chip.peak_bf16_flops / 1e12:.0f} "
        f"TFLOP/s: {step_s:.3g} s per step of {batch} rows, {batch / step_s:.0f} rows/s" +
        (f" (hardware utilisation with remat {100 * executed / (peak * step_s):.0f}%)"
         if executed else ""))
  out = {"flops_per_step": step_flops, "mfu_assumed": mfu, "step_s_estimate": step_s}
  if config.get("num_epochs") and "datasets" in config.input:
    shapes = recipe_shapes(config)
    mean_row = sum(per_row[s] for s in shapes) / len(shapes)
    rows = config.num_epochs * rows_per_epoch(config)
    steps = math.ceil(rows / batch)
    days = steps * mean_row * batch / (peak * mfu) / 86400
    print(f"  recipe: {config.num_epochs} epochs x {rows_per_epoch(config)} rows = {steps} steps "
          f"of {batch}; {mean_row / 1e9:.0f} GFLOP per row on average over "
          f"{', '.join(f'{h}x{w}' for h, w in shapes)}: {days:.1f} days at {100 * mfu:.0f}% MFU")
    out.update(recipe_steps=steps, mean_flops_per_row=mean_row, days_estimate=days)
  return out


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
  ap.add_argument("--fsdp_gather", choices=("layer", "step"), default=None,
                  help="config.fsdp_gather: scanned blocks gathered per layer, or all at the start")
  ap.add_argument("--grad_accum", type=int, default=None,
                  help="config.grad_accum: microbatches per step (per-chip batches count the "
                  "step's rows; with --fit they come in multiples of 2 x grad_accum)")
  tpu = ap.add_argument_group("TPU planning (needs libtpu: pip install 'ufm_jax[tpu]')")
  tpu.add_argument("--topology", default=None,
                   help="compile for this TPU slice (ufm_jax.topologies: v5e-8, v5p-128, ...)")
  tpu.add_argument("--per_chip_batch", type=int, default=None,
                   help="rows per chip (default: the recipe's batch over the chips)")
  tpu.add_argument("--fit", action="store_true",
                   help="search the largest per-chip batch that fits (one compile per probe), "
                   "starting from the per-chip batch")
  tpu.add_argument("--max_probes", type=int, default=6)
  tpu.add_argument("--mfu", type=float, default=0.4,
                   help="assumed model FLOPs utilisation for the step time (0: no FLOP count)")
  tpu.add_argument("--time_only", action="store_true",
                   help="no compile: step time and days for each of --topology A,B,... (GPU "
                   "nodes too: h100-8, h200-8, a100-8) from the FLOP count")
  args = ap.parse_args()
  if args.topology:
    # The TPU is only compiled for; jax itself runs on the host CPU.
    if "jax" in sys.modules:
      raise SystemExit("--topology must be set before jax is imported")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
  if args.devices:
    if "jax" in sys.modules:
      raise SystemExit("--devices must be set before jax is imported")
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               f" --xla_force_host_platform_device_count={args.devices}")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
  config, batch, hw = load(args)
  if args.topology and args.time_only:
    time_only(config, args)
  elif args.topology:
    plan(config, args)
  elif args.aot:
    aot(config, batch, hw, args.hlo_out)
  elif args.estimate_only:
    estimate(config, batch, hw)
  else:
    time_steps(config, batch, hw, args.steps)


if __name__ == "__main__":
  main()
