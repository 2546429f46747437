r"""One script for a machine with one GPU: the figures a user asks for first, in minutes.

  python benchmarks/gpu_check.py --fixture DIR --out results.jsonl   # the GPU machine, ~5 minutes
  python benchmarks/gpu_check.py --smoke         # CPU, tiny model, seconds (the test suite runs it)
  python benchmarks/gpu_check.py --flops_only    # any machine: the FLOP count of every case

In order of priority; once `--budget_s` seconds have passed no new case starts (each one left is
listed as not run), and every finished case is appended to `--out` at once, so a run cut short by
the machine's time limit still reports what it measured:

1. Parity on this device (`--fixture`: an official snapshot folder holding config.json,
   model.safetensors and the io.npz made by the official PyTorch code, e.g.
   fixtures/ufm_reference/base): max |flow| and |covisibility| difference from the official
   float32 outputs, for float32 at the default matmul precision (TF32 on NVIDIA GPUs), float32 at
   "highest", and bfloat16 with the default (fused cuDNN) attention.
2. UFM-Base / UFM-Refine inference at 420x560 (and 742x980): median and min of `--iters` timed
   runs after a warm-up, pairs/s, compile seconds, XLA's FLOP count and temp memory per call,
   and which attention kernel the compiled HLO holds (cuDNN fused custom calls, or none).
3. The full UFM-560 train step (ufm_jax.training.trainer.setup, the exact train.py step; bf16, remat) at
   `--train_batch`: step time, pairs/s, peak device memory, MFU (the planner's model FLOPs,
   ufm_jax.planning.flops.model_flops, / step time / the chip's dense bf16 peak).
Prints a table, then one JSON line with every figure. Asserts nothing about speed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import pathlib
import re
import statistics
import sys
import time
import traceback

REPO = pathlib.Path(__file__).resolve().parents[1]
BASE, REFINE = "ufm_base", "ufm_refine"
# (variant, (H, W), batch, dtype, attention, head_dtype), most wanted first.
FORWARD_CASES = [
    (BASE, (420, 560), 1, "bfloat16", "auto", "float32"),
    (BASE, (420, 560), 1, "float32", "auto", "float32"),
    (BASE, (420, 560), 1, "bfloat16", "xla", "float32"),
    (BASE, (420, 560), 8, "bfloat16", "auto", "float32"),
    (REFINE, (420, 560), 1, "bfloat16", "auto", "float32"),
    "train",
    (BASE, (420, 560), 8, "bfloat16", "auto", "bfloat16"),
    (BASE, (742, 980), 1, "bfloat16", "auto", "float32"),
    (REFINE, (420, 560), 1, "float32", "auto", "float32"),
    (BASE, (420, 560), 8, "float32", "auto", "float32"),
    (BASE, (742, 980), 8, "bfloat16", "auto", "float32"),
]


def _peak(device) -> float | None:
  """Dense bf16 peak FLOP/s of the device (ufm_jax.planning.topologies.CHIPS), None if unknown."""
  from ufm_jax.planning import topologies
  chip = topologies.chip_of(getattr(device, "device_kind", ""))
  return chip.peak_bf16_flops if chip else None


def _flops(lowered) -> float | None:
  from ufm_jax.planning import hlo_stats
  return hlo_stats.flops(lowered)


def _param_shapes(model):
  """The model's parameter tree as ShapeDtypeStructs (no weights made)."""
  import jax
  from ufm_jax.training import trainer
  hw = (2 * model.config.encoder.patch_size,) * 2
  return jax.eval_shape(lambda: trainer.init_params(model, hw, jax.random.PRNGKey(0)))


def _on_cpu(tree):
  import jax
  cpu = jax.sharding.SingleDeviceSharding(jax.devices("cpu")[0])
  return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=cpu), tree)


def forward_flops(variant, hw, batch, dtype, head_dtype) -> float | None:
  """XLA's FLOP count of the forward as traced, lowered for the host CPU with XLA's attention
  (the same arithmetic as the fused kernel). The GPU cannot say: jax's GPU plugin has no
  cost analysis before compilation, and the compiled program's count leaves out the cuBLAS and
  cuDNN calls (it gave 65 of ~2900 GFLOP per UFM-Base pair on an H200)."""
  import jax
  import jax.numpy as jnp
  from ufm_jax.models import variants
  model = variants.build_model(variant, dtype=dtype, attention_impl="xla", head_dtype=head_dtype,
                               scan_blocks=False)
  params = _param_shapes(model)
  x = jax.ShapeDtypeStruct((batch, *hw, 3), jnp.uint8)
  fwd = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t))
  return _flops(fwd.lower(*_on_cpu((params, x, x))))


def train_flops(config, hw, batch) -> float | None:
  """The train step's model FLOPs, as the planner counts them (ufm_jax.planning.flops.model_flops: matrix
  products and convolutions of the whole step on its jaxpr, every loop by its trip count,
  remat's recomputation left out), for a GPU's branch of platform-dependent code."""
  from ufm_jax.planning import flops
  return flops.model_flops(config, hw, batch, platform="gpu").flops


def _temp_gib(compiled) -> float | None:
  try:
    return compiled.memory_analysis().temp_size_in_bytes / 2**30
  except Exception:  # noqa: BLE001 - not every backend reports a memory analysis
    return None


def attention_kernels(hlo_text: str) -> str:
  """Which attention the compiled program runs: its cuDNN fused-attention custom calls, counted
  by target ("__cudnn$fmha..."), or "none fused" (XLA's dot + softmax + dot)."""
  targets = re.findall(r'custom_call_target="([^"]+)"', hlo_text)
  fused = [t for t in targets if "fmha" in t.lower() or "flash" in t.lower()]
  if not fused:
    return "none fused"
  counts = {t: fused.count(t) for t in sorted(set(fused))}
  return ", ".join(f"{n} x {t}" for t, n in counts.items())


def _timed(fn, iters):
  import jax
  jax.block_until_ready(fn())  # warm-up
  times = []
  for _ in range(iters):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return statistics.median(times), min(times)


def parity(fixture_dir):
  """The official snapshot's forward on this device against the official float32 outputs."""
  import jax
  import numpy as np
  import ufm_jax
  d = pathlib.Path(fixture_dir)
  model, variables = ufm_jax.load_official(d)
  params = variables["params"]   # a base-model fixture: no BatchNorm statistics
  io = dict(np.load(d / "io.npz"))
  rows = []
  for label, dtype, precision in (("float32, default precision", "float32", None),
                                  ("float32, precision highest", "float32", "highest"),
                                  ("bfloat16, default attention", "bfloat16", None)):
    m = model.clone(config=model.config.replace(dtype=dtype))
    ctx = jax.default_matmul_precision(precision) if precision else contextlib.nullcontext()
    with ctx:
      fwd = jax.jit(lambda p, a, b, m=m: m.apply({"params": p}, a, b))
      compiled = fwd.lower(params, io["img1_uint8"], io["img2_uint8"]).compile()
    out = compiled(params, io["img1_uint8"], io["img2_uint8"])
    hlo = compiled.as_text()
    flow = np.asarray(out["flow"], np.float64).transpose(0, 3, 1, 2)
    covis = np.asarray(out["covisibility"], np.float64)[:, None]
    rows.append({"kind": "parity", "case": label, "fixture": d.name,
                 "flow_max_px": float(np.abs(flow - io["flow"]).max()),
                 "flow_mean_px": float(np.abs(flow - io["flow"]).mean()),
                 "covis_max": float(np.abs(covis - io["covisibility_mask"]).max()),
                 "attention_kernels": attention_kernels(hlo)})
  return rows


_PARAMS: dict = {}
_START = time.perf_counter()


def _progress(msg):
  """Where a long case is, on stderr, so a run cut short shows where its time went."""
  print(f"[{time.perf_counter() - _START:6.1f} s] {msg}", file=sys.stderr, flush=True)


def timing_params(model):
  """Random N(0, 0.02) parameters of the model's shapes, drawn on the host. A timing does not
  depend on the values, and the modules' own initializers (`trainer.random_params`) took ~90 s
  per model on an H200, a tenth of a 15-minute device session."""
  import jax
  import numpy as np
  rng = np.random.default_rng(0)
  return jax.tree.map(
      lambda s: jax.device_put((rng.standard_normal(s.shape, np.float32) * 0.02).astype(s.dtype)),
      _param_shapes(model))


def bench_forward(variant, hw, batch, dtype, attention, head_dtype, iters):
  import jax
  import numpy as np
  from ufm_jax.models import variants
  model = variants.build_model(variant, dtype=dtype, attention_impl=attention,
                               head_dtype=head_dtype)
  if variant not in _PARAMS:  # the parameters do not depend on the compute dtype
    _PARAMS[variant] = timing_params(variants.build_model(variant))
    _progress(f"{variant} initialised")
  params = _PARAMS[variant]
  h, w = hw
  x = jax.device_put(np.random.default_rng(0).integers(0, 256, (batch, h, w, 3), dtype=np.uint8))
  fwd = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t))
  t0 = time.perf_counter()
  compiled = fwd.lower(params, x, x).compile()
  compile_s = time.perf_counter() - t0
  _progress(f"compiled in {compile_s:.1f} s")
  med, best = _timed(lambda: compiled(params, x, x), iters)
  flops = forward_flops(variant, hw, batch, dtype, head_dtype)
  return {"kind": "forward", "variant": variant, "size": f"{h}x{w}", "batch": batch,
          "dtype": dtype, "head_dtype": head_dtype, "attention": attention,
          "attention_kernels": attention_kernels(compiled.as_text()),
          "ms": med * 1e3, "ms_min": best * 1e3, "pairs_per_s": batch / med,
          "gflop_per_pair": flops / batch / 1e9 if flops else None,
          "tflop_s": flops / med / 1e12 if flops else None,
          "temp_gib": _temp_gib(compiled), "compile_s": compile_s}


def bench_train(config_spec, model_name, hw, batch, steps):
  import jax
  from ufm_jax.training import config_lib, sharding, trainer
  config = config_lib.load_config(config_spec)
  config.unlock()
  config.model_name = model_name
  config.mesh = "data:-1,fsdp:1"
  mesh = sharding.make_mesh(config.mesh)
  ts = trainer.setup(config, mesh, hw, total_steps=1000)
  state = ts.init_state()
  b = ts.random_batch(mesh, batch, hw)
  h, w = hw
  _progress("train state initialised")
  t0 = time.perf_counter()
  compiled = ts.train_step.lower(state, b).compile()
  compile_s = time.perf_counter() - t0
  _progress(f"compiled in {compile_s:.1f} s")
  holder = [state]

  def step():
    holder[0], m = compiled(holder[0], b)
    return m

  med, best = _timed(step, steps)
  flops = train_flops(config, hw, batch)
  peak = _peak(jax.devices()[0])
  stats = jax.devices()[0].memory_stats() or {}
  return {"kind": "train", "config": config_spec.split("/")[-1], "model": model_name,
          "size": f"{h}x{w}", "batch": batch, "dtype": config.model.get("dtype"),
          "remat": config.model.get("remat"), "step_ms": med * 1e3, "step_ms_min": best * 1e3,
          "pairs_per_s": batch / med, "compile_s": compile_s,
          "peak_memory_gib": stats.get("peak_bytes_in_use", 0) / 2**30 or None,
          "temp_gib": _temp_gib(compiled),
          "tflop_per_step": flops / 1e12 if flops else None,
          "mfu": flops / med / peak if (flops and peak) else None}


def _fmt(v, nd=1):
  if v is None:
    return "-"
  return f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def _table(rows):
  lines = []
  par = [r for r in rows if r["kind"] == "parity"]
  if par:
    lines += ["| parity vs official | max |flow| px | mean |flow| px | max |covis| | attention |",
              "|---|---|---|---|---|"]
    lines += [f"| {r['case']} | {r['flow_max_px']:.2e} | {r['flow_mean_px']:.2e} | "
              f"{r['covis_max']:.2e} | {r['attention_kernels']} |" for r in par]
  lines += ["| what | size | batch | dtype | attention (kernels) | ms (min) | pairs/s | "
            "GFLOP/pair | TFLOP/s | temp GiB | compile s | peak GiB | MFU |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    if r["kind"] == "forward":
      dt = r["dtype"] + (", heads bf16" if r["head_dtype"] == "bfloat16" else "")
      lines.append(f"| forward {r['variant']} | {r['size']} | {r['batch']} | {dt} | "
                   f"{r['attention']} ({r['attention_kernels']}) | {_fmt(r['ms'])} "
                   f"({_fmt(r['ms_min'])}) | {_fmt(r['pairs_per_s'])} | "
                   f"{_fmt(r['gflop_per_pair'], 0 if (r['gflop_per_pair'] or 0) >= 10 else 2)} | {_fmt(r['tflop_s'])} | "
                   f"{_fmt(r['temp_gib'])} | {_fmt(r['compile_s'])} | - | - |")
    elif r["kind"] == "train":
      lines.append(f"| train step {r['model']} (remat={r['remat']}) | {r['size']} | "
                   f"{r['batch']} | {r['dtype']} | - | {_fmt(r['step_ms'])} "
                   f"({_fmt(r['step_ms_min'])}) | {_fmt(r['pairs_per_s'])} | - | "
                   f"{_fmt(r['tflop_per_step'] and r['tflop_per_step'] * 1e3 / r['step_ms'])} | "
                   f"{_fmt(r['temp_gib'])} | {_fmt(r['compile_s'])} | "
                   f"{_fmt(r['peak_memory_gib'])} | {_fmt(r['mfu'], 3)} |")
  return "\n".join(lines)


def print_flops(train_batch):
  """The FLOP counts behind the TFLOP/s and MFU columns, on any machine (no GPU needed)."""
  from ufm_jax.training import config_lib
  for case in FORWARD_CASES:
    if case == "train":
      config = config_lib.load_config(str(REPO / "configs" / "ufm560.py"))
      config.unlock()
      config.model_name = BASE
      tflop = train_flops(config, (420, 560), train_batch) / 1e12
      print(f"train step ufm560 {BASE} 420x560 batch {train_batch}: {tflop:.1f} TFLOP "
            f"({tflop / train_batch * 1e3:.0f} GFLOP per pair)")
      continue
    variant, hw, batch, dtype, _, head_dtype = case
    gflop = forward_flops(variant, hw, batch, dtype, head_dtype) / 1e9
    print(f"forward {variant} {hw[0]}x{hw[1]} batch {batch} {dtype} heads {head_dtype}: "
          f"{gflop / batch:.0f} GFLOP per pair")
  return 0


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("--smoke", action="store_true", help="tiny model on any device, seconds")
  ap.add_argument("--fixture", help="official snapshot folder with io.npz: parity on this device")
  ap.add_argument("--iters", type=int, default=10)
  ap.add_argument("--train_batch", type=int, default=16, help="global batch of the train step")
  ap.add_argument("--budget_s", type=float, default=300.0,
                  help="start no new case after this many seconds")
  ap.add_argument("--out", help="append each finished case here as a JSON line")
  ap.add_argument("--cases", help="comma-separated indices into the case list (0 = first after "
                  "parity), in the order to run them; default all")
  ap.add_argument("--flops_only", action="store_true",
                  help="print XLA's FLOP count of every case (counted on the host CPU) and exit")
  args = ap.parse_args(argv)
  import jax
  if args.flops_only:
    return print_flops(args.train_batch)
  start = time.perf_counter()
  dev = jax.devices()[0]
  if args.smoke:
    cases = [("tiny", (56, 56), 2, "bfloat16", "xla", "float32"), "train"]
    train_case = (str(REPO / "configs" / "synthetic.py"), "tiny", (56, 56), 2)
    iters = 2
  else:
    cases = FORWARD_CASES
    train_case = (str(REPO / "configs" / "ufm560.py"), BASE, (420, 560), args.train_batch)
    iters = args.iters
  print(f"device: {dev.device_kind} ({dev.platform}), jax {jax.__version__}, peak bf16 "
        f"{_fmt((_peak(dev) or 0) / 1e12 or None, 0)} TFLOP/s", flush=True)
  out = open(args.out, "a") if args.out else None  # noqa: SIM115 - closed below
  rows, failures = [], []

  def record(new):
    for r in new:
      rows.append(r)
      print(json.dumps(r), flush=True)
      if out:
        out.write(json.dumps(r) + "\n")
        out.flush()

  if args.cases:
    cases = [cases[int(i)] for i in args.cases.split(",")]
  jobs = ([("parity", args.fixture)] if args.fixture else []) + cases
  for case in jobs:
    label = case if isinstance(case, str) else " ".join(map(str, case))
    if time.perf_counter() - start > args.budget_s:
      failures.append({"case": label, "error": f"not started: past --budget_s {args.budget_s:.0f}"})
      continue
    _progress(f"start {label}")
    try:
      if isinstance(case, tuple) and case[0] == "parity":
        record(parity(case[1]))
      elif case == "train":
        record([bench_train(*train_case, max(iters // 2, 2))])
      else:
        record([bench_forward(*case, iters)])
    except Exception as e:  # noqa: BLE001 - a case that does not fit or is unsupported is reported
      failures.append({"case": label, "error": f"{type(e).__name__}: {e}"[:400]})
      traceback.print_exc()
  print(_table(rows))
  for f in failures:
    print(f"not run: {f['case']}: {f['error']}")
  result = {"device": dev.device_kind, "platform": dev.platform, "jax": jax.__version__,
            "seconds": time.perf_counter() - start, "results": rows, "failures": failures}
  if out:
    out.write(json.dumps({"failures": failures, "seconds": result["seconds"]}) + "\n")
    out.close()
  print(json.dumps(result))
  return 0 if rows else 1


if __name__ == "__main__":
  sys.exit(main())
