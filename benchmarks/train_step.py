r"""Train-step benchmark: the exact train.py step (ufm_jax.training.trainer.setup), timed or compiled only.

  python benchmarks/train_step.py --config synthetic                 # time the tiny config here
  python benchmarks/train_step.py --config ufm560 --model ufm_base --mesh data:2,fsdp:4 \
      --devices 8 --batch 96 --size 420x560 --aot --hlo_out /tmp/ufm560.hlo.txt
  python benchmarks/train_step.py --config ufm560 --mesh data:2,fsdp:4 --devices 8 --batch 96 \
      --size 420x560 --aot --scan false     # compile time with unrolled blocks
  python benchmarks/train_step.py --config ufm560 --estimate_only    # memory of the full config
  python benchmarks/train_step.py --config ufm560 --topology v5e-8 --fit   # plan a TPU slice

--aot and --topology run the planner, ufm_jax.planning.planner.plan: the code path of
`train.py --compile_only`. The step is built from the config as train.py builds it (its mesh,
config.mesh unless --mesh; grad_accum; the largest of the recipe's training shapes unless --size;
the recipe's batch unless --batch / --per_chip_batch) and compiled, never run: on the devices at
hand (--aot; --devices N fake CPU devices, set before jax is imported) or for a TPU slice from
this host (--topology NAME of ufm_jax.planning.topologies: v5e-8, v5p-8, v5e-256, ...; libtpu installed:
`pip install "ufm_jax[tpu]"` in its own virtualenv, no TPU). It prints the parameter and train
state bytes, XLA's memory per chip (HBM = temp + arguments + outputs - aliases) against the
chip's, the collectives of the compiled HLO by kind (ufm_jax.planning.hlo_stats), the model FLOPs of the
whole step (ufm_jax.planning.flops: every loop body, grad_accum's microbatches and the scanned blocks, by
its trip count) and, at --mfu of the chips' bf16 peak (assumed, or `calibrated`: the MFU the
paper's 560 run implies, which every plan prints), the step time, the days of
the recipe's epochs (the mean over its training shapes) and the host CPU that feeding the chips
at that pace needs (rows per second per host x the host ms per row, timed on this host by a short
run of the recipe's input pipeline on stand-in data, ufm_jax.testing.host_feed, with the load
average beside it; --host_ms_per_row instead). The last line is one JSON
object (chips, device_kind, mesh, grad_accum, global_batch, hbm_bytes_per_chip,
hbm_capacity_bytes, flops_per_step, collective_bytes, compile_s, ...). --fit searches the largest
per-chip batch that fits (one compile per probe, minutes each at full size), then compiles the
recipe's own batch with the fewest microbatches that fit, and prints the train.py / sbatch /
JobSet overrides that run that plan. --topology A,B,... --time_only skips the compile (and
libtpu): FLOPs, step time, days and host feed per slice, GPU nodes too (h100-8, h200-8, a100-8).
--flops counts the step's FLOPs on its jaxpr (model FLOPs, and as executed with remat) beside
the count from the model's dimensions (ufm_jax.planning.flops.analytic_step_flops), by part.
--estimate_only traces abstractly (no compile): params, AdamW state, and the activations the
backward pass keeps (JAX's saved residuals) with and without remat at the per-device batch.
Without any of these, random batches go through the compiled step and the step time is printed.
docs/scale.md has the figures.
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


def parse_size(text: str):
  return tuple(int(x) for x in text.lower().split("x"))


def load(args):
  """(config, global batch or None, (H, W) or None): the config with the flags' overrides; the
  batch and size only where the flags give them."""
  from ufm_jax.training import config_lib
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
  return config, args.batch, parse_size(args.size) if args.size else None


def config_spec(args) -> str:
  """The --config value train.py takes for this config (relative to the repository root)."""
  path, _, arg = args.config.partition(":")
  if not pathlib.Path(path).suffix:
    path = f"configs/{path}.py"
  return path + (f":{arg}" if arg else "")


def emit(result: dict, hlo_out=None):
  """The plan in words, then its JSON as the last line (and the compiled HLO to `hlo_out`)."""
  from ufm_jax.planning import planner
  if hlo_out and "_text" in result:
    pathlib.Path(hlo_out).write_text(result["_text"])
  planner.report(result)
  print(planner.to_json(result), flush=True)


def aot(config, batch, hw, args):
  """--aot: the step compiled on the devices at hand (--devices fake CPU ones), as
  `train.py --compile_only` compiles it."""
  from ufm_jax.planning import planner
  from ufm_jax.testing import host_feed
  tgt = planner.target()
  result = planner.plan(config, tgt, batch=batch, image_shape=hw, mfu=args.mfu,
                         host_feed=host_feed.for_plan(config, args.host_ms_per_row))
  emit(result, args.hlo_out)
  return result


# ----------------------------------------------------------------------------- TPU planning


def _per_chip_batch(config, args, n: int) -> int:
  """--per_chip_batch, or --batch (else the recipe's) split over `n` chips."""
  from ufm_jax.planning import planner
  quantum = planner.quantum(config)
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


def plan(config, hw, args):
  """--topology: the step compiled for a TPU slice from this host (libtpu, no TPU); --fit: the
  largest per-chip batch that fits and the plan of the recipe's batch, with the overrides that
  run it."""
  from ufm_jax.planning import planner, topologies
  from ufm_jax.testing import host_feed
  from ufm_jax.training import sharding
  tgt = planner.target(args.topology)
  slc = topologies.get(args.topology)
  n = sharding.batch_divisor(sharding.make_mesh(config.mesh, tgt.devices))
  per_chip = _per_chip_batch(config, args, n)
  print(f"{args.topology}: {slc.chips} chips ({slc.topology}, {slc.chip_config}), "
        f"{_gib(tgt.capacity)} HBM per chip, bf16 peak {tgt.peak_flops / 1e12:.0f} TFLOP/s, "
        f"{tgt.hosts} host(s); mesh {config.mesh}", flush=True)
  feed = host_feed.for_plan(config, args.host_ms_per_row)
  if args.fit:
    result = planner.fit(config, tgt, per_chip, image_shape=hw, max_probes=args.max_probes,
                          mfu=args.mfu, host_feed=feed)
  else:
    result = planner.plan(config, tgt, batch=per_chip * n, image_shape=hw, mfu=args.mfu,
                           host_feed=feed)
  if args.fit:
    print("run this plan (docs/launch.md):")
    for line in planner.launch_lines(result, config_spec(args)):
      print(f"  {line}")
  emit(result, args.hlo_out)
  return result


def time_only(config, hw, args):
  """--time_only: step time, recipe days and host feed for each of the --topology slices (a
  comma list, GPU nodes too), from the FLOP count alone: no compile, no libtpu."""
  from ufm_jax.planning import planner
  from ufm_jax.testing import host_feed
  shapes = planner.training_shapes(config)
  hw = hw or planner.largest_shape(config)
  rows, counted = [], {}
  feed = host_feed.for_plan(config, args.host_ms_per_row)
  if feed["host_ms_per_row"]:
    print(f"host feed: {feed['host_ms_per_row']} ms/row "
          f"({planner.host_feed_source({'host_feed': feed})})")
  mfu = planner.mfu_value(args.mfu)
  for name in args.topology.split(","):
    tgt = planner.target(name, compile=False)
    batch = _per_chip_batch(config, args, tgt.chips) * tgt.chips
    print(f"{name}: {tgt.chips} x {tgt.device_kind}, global batch {batch}", flush=True)
    if batch not in counted:   # slices with the same batch share the count (TPU and GPU alike)
      counted[batch] = planner.model_flops_per_row(config, set(shapes) | {hw}, batch, "tpu")
    per_row = counted[batch]
    est = planner.estimate(config, tgt, per_row, hw, batch, mfu, feed["host_ms_per_row"],
                           calibrated=planner.paper_run()["mfu"])
    row = {"topology": name, "chips": tgt.chips, "hosts": tgt.hosts, "global_batch": batch,
           "grad_accum": int(config.grad_accum), "image_shape": list(hw), **est,
           "host_feed": feed}
    print(f"  {est['flops_per_row'] / 1e12:.3f} TFLOP per row at {hw[0]}x{hw[1]}, "
          f"{est['mean_flops_per_row'] / 1e12:.3f} on average; step {est['mean_step_s_estimate']:.3g}"
          f" s on average at {100 * mfu:.1f}% MFU"
          + (f", {est['recipe_steps']} steps, {est['days_estimate']:.2f} days"
             + (f" ({est['days_at_calibrated_mfu']:.2f} at the paper's run's "
                f"{100 * est['mfu_calibrated']:.1f}% MFU)" if "days_at_calibrated_mfu" in est
                and mfu != est["mfu_calibrated"] else "")
             if "days_estimate" in est else "")
          + (f"; host feed {est['rows_per_s_per_host']:.0f} rows/s per host = "
             f"{est['host_cores_per_host']:.1f} cores of {est['host_vcpus'] or '?'} vCPUs"
             if est.get("host_cores_per_host") else ""))
    rows.append(row)
  print(json.dumps(rows))
  return rows


def count_flops(config, batch, hw):
  """--flops: the step's FLOPs counted on its jaxpr (ufm_jax.planning.flops; model FLOPs without remat,
  and as executed with it) beside the count from the model's dimensions, by part."""
  import copy

  import jax
  from ufm_jax.planning import flops
  from ufm_jax.training import sharding, trainer
  mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
  model_cfg = copy.deepcopy(config)
  if model_cfg.model.get("remat"):
    model_cfg.model.remat = False
  ts = trainer.setup(model_cfg, mesh, hw, total_steps=1000)
  t0 = time.perf_counter()
  counted = flops.step_flops(ts, batch, hw)
  trace_s = time.perf_counter() - t0
  executed = flops.step_flops(trainer.setup(config, mesh, hw, total_steps=1000), batch, hw)
  analytic = flops.analytic_step_flops(config, ts, hw, batch)
  print(f"config {config.get('model_name')}: global batch {batch} at {hw[0]}x{hw[1]}, grad_accum "
        f"{config.get('grad_accum', 1)}")
  print(f"  jaxpr count (model FLOPs): {counted.flops / 1e12:.4f} TFLOP per step, "
        f"{counted.flops / batch / 1e12:.4f} per row (traced in {trace_s:.1f} s"
        f"{f'; {counted.unknown_loops} loops of unknown trip count' if counted.unknown_loops else ''})")
  print(f"  as executed, remat's recomputation included: {executed.flops / 1e12:.4f} TFLOP "
        f"({executed.flops / counted.flops:.3f}x)")
  print(f"  from the model's dimensions: {analytic['total'] / 1e12:.4f} TFLOP "
        f"({100 * (analytic['total'] / counted.flops - 1):+.2f}% of the jaxpr count)")
  for part, v in analytic.items():
    if part != "total":
      print(f"    {part:18s} {v / 1e12:10.4f} TFLOP ({100 * v / analytic['total']:.1f}%)")
  print(json.dumps({"flops_per_step": counted.flops, "executed_flops_per_step": executed.flops,
                    "analytic_flops_per_step": analytic, "global_batch": batch,
                    "image_shape": list(hw), "grad_accum": int(config.get("grad_accum", 1))}))


def time_steps(config, batch, hw, steps):
  import jax
  from ufm_jax.training import sharding, trainer
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
  from ufm_jax.training import sharding, trainer
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
  ap.add_argument("--flops", action="store_true",
                  help="the step's FLOPs on its jaxpr beside the count from the model's dimensions")
  ap.add_argument("--fsdp_gather", choices=("layer", "step"), default=None,
                  help="config.fsdp_gather: scanned blocks gathered per layer, or all at the start")
  ap.add_argument("--grad_accum", type=int, default=None,
                  help="config.grad_accum: microbatches per step (per-chip batches count the "
                  "step's rows; with --fit they come in multiples of 2 x grad_accum)")
  tpu = ap.add_argument_group("TPU planning (needs libtpu: pip install 'ufm_jax[tpu]')")
  tpu.add_argument("--topology", default=None,
                   help="compile for this TPU slice (ufm_jax.planning.topologies: v5e-8, v5p-128, ...)")
  tpu.add_argument("--per_chip_batch", type=int, default=None,
                   help="rows per chip (default: the recipe's batch over the chips)")
  tpu.add_argument("--fit", action="store_true",
                   help="search the largest per-chip batch that fits (one compile per probe), "
                   "starting from the per-chip batch")
  tpu.add_argument("--max_probes", type=int, default=6)
  tpu.add_argument("--mfu", default="0.4",
                   help="model FLOPs utilisation for the step time: a fraction (default 0.4, "
                   "assumed: a goal, not a prediction; 0: no step time), or 'calibrated': the MFU "
                   "the paper's 560 run implies (4 days on 8 H100, planner.paper_run)")
  tpu.add_argument("--host_ms_per_row", type=float, default=None,
                   help="host CPU ms per training row for the host feed (default: timed here, "
                   "a short run of the recipe's input pipeline on stand-in data: "
                   "ufm_jax.testing.host_feed)")
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
    time_only(config, hw, args)
  elif args.topology:
    plan(config, hw, args)
  elif args.aot:
    aot(config, batch, hw, args)
  else:
    from ufm_jax.planning import planner
    batch = batch or int(config.input.batch_size)
    hw = hw or planner.largest_shape(config)
    if args.flops:
      count_flops(config, batch, hw)
    elif args.estimate_only:
      estimate(config, batch, hw)
    else:
      time_steps(config, batch, hw, args.steps)


if __name__ == "__main__":
  main()
