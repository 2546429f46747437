"""Inference speed of the UFM forward pass, next to a matmul peak measured on the same machine.

  python benchmarks/inference.py --config fixture_small --size 168x224 --batch 1
  python benchmarks/inference.py --config ufm_base --size 420x560 --batch 1 --runs 3

Prints: latency (median of --runs timed calls after --warmup untimed ones), pairs/s, the model's
FLOPs per pair from XLA's cost analysis of the compiled forward, achieved GFLOP/s, and the f32
matmul peak (median GFLOP/s of a large jnp.dot) with the fraction of it the model reaches.
Params are random (`jax.jit(model.init)`) unless --snapshot gives an official snapshot. Figures
are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np


def _median_time(fn, runs: int, warmup: int) -> float:
  for _ in range(warmup):
    jax.block_until_ready(fn())
  times = []
  for _ in range(runs):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return statistics.median(times)


def make_matmul(n: int = 2048, dtype=jnp.float32):
  """A jitted n x n x n f32 jnp.dot (2 n^3 flops) on random inputs: the practical matmul peak."""
  ka, kb = jax.random.split(jax.random.PRNGKey(0))
  a = jax.random.normal(ka, (n, n), dtype)
  b = jax.random.normal(kb, (n, n), dtype)
  dot = jax.jit(jnp.dot)
  return lambda: dot(a, b)


def matmul_peak(n: int = 2048, runs: int = 5) -> float:
  """Median GFLOP/s of `make_matmul(n)` after warm-up."""
  return 2 * n**3 / _median_time(make_matmul(n), runs, warmup=2) / 1e9


def cost_flops(compiled) -> float:
  """FLOPs of a compiled XLA executable (cost_analysis returns a dict, or a list of them)."""
  cost = compiled.cost_analysis()
  if isinstance(cost, (list, tuple)):
    cost = cost[0] if cost else {}
  return float(cost.get("flops", float("nan"))) if cost else float("nan")


def build_model(config_name: str):
  """A model of ufm_jax.models.variants by name (e.g. fixture_small, ufm_base)."""
  from ufm_jax.models import variants
  return variants.build_model(config_name)


def parse_size(text: str) -> tuple[int, int]:
  try:
    h, w = (int(v) for v in text.lower().split("x"))
  except ValueError:
    raise argparse.ArgumentTypeError(f"--size must be HxW (e.g. 420x560), got {text!r}") from None
  return h, w


def main(argv=None) -> dict:
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--config", default="fixture_small", help="model variant name (ufm_jax.models.variants)")
  ap.add_argument("--snapshot", default=None, help="official HF snapshot instead of a config")
  ap.add_argument("--size", type=parse_size, default=None, help="HxW (multiples of 14)")
  ap.add_argument("--batch", type=int, default=1)
  ap.add_argument("--runs", type=int, default=5)
  ap.add_argument("--warmup", type=int, default=2)
  ap.add_argument("--matmul_n", type=int, default=2048)
  ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
  args = ap.parse_args(argv)

  if args.snapshot:
    import ufm_jax
    model, params = ufm_jax.load_official(args.snapshot)
    name = args.snapshot
  else:
    model, params, name = build_model(args.config), None, args.config
  if args.size is None:
    from ufm_jax.inference import inference_resolutions
    args.size = inference_resolutions(model)[0]
  h, w = args.size
  rng = np.random.default_rng(0)
  src = jnp.asarray(rng.integers(0, 256, (args.batch, h, w, 3), dtype=np.uint8))
  tgt = jnp.asarray(rng.integers(0, 256, (args.batch, h, w, 3), dtype=np.uint8))

  t0 = time.perf_counter()
  if params is None:
    # parameter shapes do not depend on the image size: initialise on a small input
    tiny = jnp.zeros((1, 28, 28, 3), jnp.uint8)
    params = jax.jit(model.init)(jax.random.PRNGKey(0), tiny, tiny)["params"]
    jax.block_until_ready(params)
  t_init = time.perf_counter() - t0
  n_params = sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(params))

  fwd = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t))
  t0 = time.perf_counter()
  compiled = fwd.lower(params, src, tgt).compile()
  t_compile = time.perf_counter() - t0
  flops = cost_flops(compiled)
  run_model = lambda: compiled(params, src, tgt)  # noqa: E731
  run_dot = make_matmul(args.matmul_n)
  for _ in range(args.warmup):
    jax.block_until_ready(run_model())
    jax.block_until_ready(run_dot())
  # Interleave model and matmul timings round by round, so that load from other processes on a
  # shared machine hits both alike; the fraction of peak is the median of per-round ratios.
  lat, peaks, fracs = [], [], []
  for _ in range(args.runs):
    t_model = _median_time(run_model, 1, 0)
    t_dot = _median_time(run_dot, 3, 0)
    lat.append(t_model)
    peaks.append(2 * args.matmul_n**3 / t_dot / 1e9)
    fracs.append((flops / t_model / 1e9) / peaks[-1])
  latency, peak = statistics.median(lat), statistics.median(peaks)

  res = {
      "config": name, "size_hw": [h, w], "batch": args.batch, "params": n_params,
      "devices": f"{jax.devices()[0].platform} x{jax.device_count()}",
      "init_s": round(t_init, 2), "compile_s": round(t_compile, 2),
      "latency_ms": latency * 1e3, "pairs_per_s": args.batch / latency,
      "gflop_per_pair": flops / args.batch / 1e9, "achieved_gflops": flops / latency / 1e9,
      "matmul_peak_gflops": peak,
  }
  res["fraction_of_peak"] = statistics.median(fracs)
  print(f"config {name}  size {h}x{w}  batch {args.batch}  params {n_params / 1e6:.2f}M  "
        f"on {res['devices']}  (XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r})")
  print(f"  init {t_init:.1f} s   compile {t_compile:.1f} s")
  print(f"  latency (median of {args.runs})  {res['latency_ms']:.1f} ms   {res['pairs_per_s']:.3f} pairs/s")
  print(f"  FLOPs/pair (XLA cost analysis)  {res['gflop_per_pair']:.2f} GFLOP")
  print(f"  achieved  {res['achieved_gflops']:.1f} GFLOP/s   f32 matmul peak "
        f"({args.matmul_n}^3 jnp.dot)  {peak:.1f} GFLOP/s   -> {100 * res['fraction_of_peak']:.0f}% "
        "of peak (median of per-round ratios; model and matmul timed alternately)")
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
  return res


if __name__ == "__main__":
  main()
