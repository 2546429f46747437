"""Inference speed of the UFM forward pass, next to a matmul peak measured on the same machine.

  python benchmarks/inference.py --config fixture_small --size 168x224 --batch 1
  python benchmarks/inference.py --config ufm_base --size 420x560 --batch 1 --runs 3
  python benchmarks/inference.py --config ufm_base --size 420x560 --compile_only \
      --set scan_blocks=true          # compile time only (abstract params, nothing runs)

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


def build_model(config_name: str, **overrides):
  """A model of ufm_jax.models.variants by name (e.g. fixture_small, ufm_base), with UFMConfig
  overrides (e.g. scan_blocks=True, dtype="bfloat16")."""
  from ufm_jax.models import variants
  return variants.build_model(config_name, **overrides)


def parse_overrides(text: str | None) -> dict:
  """"k=v,k2=v2" -> {k: v}: values as JSON when they parse (true, 3, null), else strings."""
  out = {}
  for item in filter(None, (text or "").split(",")):
    if "=" not in item:
      raise argparse.ArgumentTypeError(f"--set wants KEY=VALUE[,KEY=VALUE], got {item!r}")
    k, v = item.split("=", 1)
    try:
      out[k] = json.loads(v)
    except json.JSONDecodeError:
      out[k] = v
  return out


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
  ap.add_argument("--set", type=parse_overrides, default={}, metavar="K=V[,K=V]",
                  help="UFMConfig overrides, e.g. scan_blocks=true,dtype=bfloat16")
  ap.add_argument("--compile_only", action="store_true",
                  help="only lower and compile the forward (abstract params) and print the times")
  ap.add_argument("--grad", action="store_true",
                  help="with --compile_only: compile forward + gradient w.r.t. the params (a "
                       "one-device stand-in for the train step; --set remat=true to match it)")
  args = ap.parse_args(argv)

  if args.snapshot:
    import ufm_jax
    from ufm_jax.models import scan
    model, params = ufm_jax.load_official(args.snapshot)
    if args.set:
      model = model.clone(config=model.config.replace(**args.set))
      params = scan.to_layout(params, model.config)
    name = args.snapshot
  else:
    model, params, name = build_model(args.config, **args.set), None, args.config
  if args.compile_only:
    return compile_only(model, name, args)
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


def compile_only(model, name: str, args) -> dict:
  """Lowering and XLA compile time of the jitted forward on abstract inputs (nothing runs)."""
  from ufm_jax.models import ufm
  h, w = args.size or model.config.inference_resolution
  img = jax.ShapeDtypeStruct((args.batch, h, w, 3), jnp.uint8)
  params = ufm.param_shapes(model)
  fwd = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t))
  if args.grad:
    def loss(p, s, t):
      out = model.apply({"params": p}, s, t)
      return jnp.mean(out["flow"] ** 2) + jnp.mean(out["covisibility_logits"])
    fwd = jax.jit(jax.value_and_grad(loss))
  # CPU seconds next to wall seconds: on a shared machine the wall time includes waiting.
  t0, c0 = time.perf_counter(), time.process_time()
  lowered = fwd.lower(params, img, img)
  t_lower, c_lower = time.perf_counter() - t0, time.process_time() - c0
  t0, c0 = time.perf_counter(), time.process_time()
  lowered.compile()
  t_compile, c_compile = time.perf_counter() - t0, time.process_time() - c0
  res = {"config": name, "overrides": args.set, "size_hw": [h, w], "batch": args.batch,
         "what": "forward + grad" if args.grad else "forward",
         "devices": f"{jax.devices()[0].platform} x{jax.device_count()}",
         "lower_s": round(t_lower, 2), "compile_s": round(t_compile, 2),
         "lower_cpu_s": round(c_lower, 2), "compile_cpu_s": round(c_compile, 2),
         "load_avg_1m": round(os.getloadavg()[0], 2), "cpu_count": os.cpu_count()}
  print(f"{res['what']} of {name} {args.set}  size {h}x{w}  batch {args.batch}  on {res['devices']}: "
        f"lower {t_lower:.1f} s ({c_lower:.1f} CPU s)  compile {t_compile:.1f} s ({c_compile:.1f} "
        f"CPU s)  (load average {res['load_avg_1m']} "
        f"on {res['cpu_count']} CPUs)")
  print(json.dumps(res))
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
  return res


if __name__ == "__main__":
  main()
