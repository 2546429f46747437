r"""One script for a machine with one GPU: the figures a user asks for first, in minutes.

  python benchmarks/gpu_check.py                 # on the GPU machine (~5-8 minutes)
  python benchmarks/gpu_check.py --smoke         # CPU, tiny model, seconds (the test suite runs it)

1. UFM-Base inference latency at 560 (420x560) and 980 (742x980), batch 1 and 8, float32 and
   bfloat16, attention "xla" and "cudnn" (fused, bf16 only): median of timed runs after warm-up,
   pairs/s, and XLA's FLOP count per pair.
2. The full UFM-560 train step (ufm_jax.trainer.setup, the exact train.py step) with remat and
   bf16 at the largest batch of --train_batches that compiles and runs: step time, pairs/s, peak
   device memory, MFU (XLA cost-analysis FLOPs / step time / the chip's dense bf16 peak).
Prints a table, then one JSON line with every figure. Asserts nothing about speed.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import sys
import time
import traceback

REPO = pathlib.Path(__file__).resolve().parents[1]
# Dense bf16 peak FLOP/s by device kind (vendor datasheets, no sparsity).
PEAK_BF16 = {"H200": 989e12, "H100": 989e12, "A100": 312e12, "L4": 121e12, "A10": 125e12,
             "TPU v5 lite": 197e12, "TPU v4": 275e12, "TPU v5p": 459e12}


def _peak(device) -> float | None:
  kind = getattr(device, "device_kind", "")
  for name, flops in PEAK_BF16.items():
    if name.lower() in kind.lower():
      return flops
  return None


def _flops(compiled) -> float | None:
  try:
    ca = compiled.cost_analysis()
    ca = ca[0] if isinstance(ca, (list, tuple)) else ca
    return float(ca.get("flops")) if ca and ca.get("flops") else None
  except Exception:  # noqa: BLE001 - not every backend reports a cost analysis
    return None


def _timed(fn, iters):
  import jax
  jax.block_until_ready(fn())  # warm-up
  times = []
  for _ in range(iters):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return statistics.median(times), min(times)


def bench_forward(variant, hw, batch, dtype, attention, iters):
  import jax
  import numpy as np
  from ufm_jax.models import variants
  model = variants.build_model(variant, dtype=dtype, attention_impl=attention)
  h, w = hw
  x = np.random.default_rng(0).integers(0, 256, (batch, h, w, 3), dtype=np.uint8)
  params = jax.jit(model.init)(jax.random.PRNGKey(0), x[:1], x[:1])["params"]
  fwd = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t))
  t0 = time.perf_counter()
  compiled = fwd.lower(params, x, x).compile()
  compile_s = time.perf_counter() - t0
  med, best = _timed(lambda: compiled(params, x, x), iters)
  flops = _flops(compiled)
  return {"kind": "forward", "variant": variant, "size": f"{h}x{w}", "batch": batch,
          "dtype": dtype, "attention": attention, "ms": med * 1e3, "ms_min": best * 1e3,
          "pairs_per_s": batch / med, "gflop_per_pair": flops / batch / 1e9 if flops else None,
          "compile_s": compile_s}


def bench_train(config_spec, model_name, hw, batch, steps):
  import jax
  from ufm_jax import config_lib, sharding, trainer
  config = config_lib.load_config(config_spec)
  config.unlock()
  config.model_name = model_name
  config.mesh = "data:-1,fsdp:1"
  mesh = sharding.make_mesh(config.mesh)
  ts = trainer.setup(config, mesh, hw, total_steps=1000)
  state = ts.init_state()
  b = ts.random_batch(mesh, batch, hw)
  h, w = hw
  t0 = time.perf_counter()
  compiled = ts.train_step.lower(state, b).compile()
  compile_s = time.perf_counter() - t0
  holder = [state]

  def step():
    holder[0], m = compiled(holder[0], b)
    return m

  med, best = _timed(step, steps)
  flops = _flops(compiled)
  peak = _peak(jax.devices()[0])
  stats = jax.devices()[0].memory_stats() or {}
  return {"kind": "train", "config": config_spec.split("/")[-1], "model": model_name,
          "size": f"{h}x{w}", "batch": batch, "dtype": config.model.get("dtype"),
          "remat": config.model.get("remat"), "step_ms": med * 1e3, "step_ms_min": best * 1e3,
          "pairs_per_s": batch / med, "compile_s": compile_s,
          "peak_memory_gib": stats.get("peak_bytes_in_use", 0) / 2**30 or None,
          "tflop_per_step": flops / 1e12 if flops else None,
          "mfu": flops / med / peak if (flops and peak) else None}


def _fmt(v, nd=1):
  if v is None:
    return "-"
  return f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("--smoke", action="store_true", help="tiny model on any device, seconds")
  ap.add_argument("--iters", type=int, default=10)
  ap.add_argument("--train_batches", default="64,48,32,24,16,8",
                  help="global batches to try for the train step, largest first")
  args = ap.parse_args(argv)
  import jax
  dev = jax.devices()[0]
  if args.smoke:
    fwd_cases = [("tiny", (56, 56), 2, "bfloat16", "xla")]
    train_case = (str(REPO / "configs" / "synthetic.py"), "tiny", (56, 56), [2])
    iters = 2
  else:
    fwd_cases = [("ufm_base", hw, b, d, a) for hw in ((420, 560), (742, 980)) for b in (1, 8)
                 for d in ("float32", "bfloat16") for a in ("xla", "cudnn")
                 if not (a == "cudnn" and d == "float32")]  # the fused kernel takes bf16/f16
    train_case = (str(REPO / "configs" / "ufm560.py"), "ufm_base", (420, 560),
                  [int(x) for x in args.train_batches.split(",")])
    iters = args.iters
  rows, failures = [], []
  for case in fwd_cases:
    try:
      rows.append(bench_forward(*case, iters))
    except Exception as e:  # noqa: BLE001 - a case that does not fit or is unsupported is reported
      failures.append({"case": list(map(str, case)), "error": f"{type(e).__name__}: {e}"[:300]})
  spec, model_name, hw, batches = train_case
  for batch in batches:
    try:
      rows.append(bench_train(spec, model_name, hw, batch, max(iters // 2, 2)))
      break
    except Exception as e:  # noqa: BLE001 - out of memory: try the next smaller batch
      failures.append({"case": ["train", str(batch)], "error": f"{type(e).__name__}: {e}"[:300]})
      if "RESOURCE_EXHAUSTED" not in str(e) and "out of memory" not in str(e).lower():
        traceback.print_exc()
        break
  print(f"device: {dev.device_kind} ({dev.platform}), jax {jax.__version__}, peak bf16 "
        f"{_fmt((_peak(dev) or 0) / 1e12 or None, 0)} TFLOP/s")
  print("| what | size | batch | dtype | attention | ms | pairs/s | GFLOP/pair | peak GiB | MFU |")
  print("|---|---|---|---|---|---|---|---|---|---|")
  for r in rows:
    if r["kind"] == "forward":
      print(f"| forward {r['variant']} | {r['size']} | {r['batch']} | {r['dtype']} | "
            f"{r['attention']} | {_fmt(r['ms'])} | {_fmt(r['pairs_per_s'])} | "
            f"{_fmt(r['gflop_per_pair'], 0)} | - | - |")
    else:
      print(f"| train step {r['model']} (remat={r['remat']}) | {r['size']} | {r['batch']} | "
            f"{r['dtype']} | - | {_fmt(r['step_ms'])} | {_fmt(r['pairs_per_s'])} | - | {_fmt(r['peak_memory_gib'])} | "
            f"{_fmt(r['mfu'], 3)} |")
  for f in failures:
    print(f"not run: {' '.join(f['case'])}: {f['error']}")
  print(json.dumps({"device": dev.device_kind, "platform": dev.platform, "jax": jax.__version__,
                    "results": rows, "failures": failures}))
  return 0 if rows else 1


if __name__ == "__main__":
  sys.exit(main())
