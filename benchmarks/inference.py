"""Inference speed of the UFM forward pass, next to a matmul peak measured on the same machine.

  python benchmarks/inference.py --config fixture_small --size 168x224 --batch 1
  python benchmarks/inference.py --config ufm_base --size 420x560 --batch 1 --runs 5 --breakdown
  python benchmarks/inference.py --config ufm_base --size 420x560 --set attention_impl=xla
  python benchmarks/inference.py --config ufm_base --size 420x560 --compile_only \
      --set scan_blocks=true          # compile time only (abstract params, nothing runs)
  python benchmarks/inference.py --config ufm_base --size 420x560 --batch 8 --frames [DIR]
      # also end to end: frames read from DIR (default: random PNGs in a temp dir), predicted
      # and written as .flo through ufm_jax.tools.sequence, the path of `infer --frames`
  python benchmarks/inference.py --snapshot SNAP --size 420x560 --runs 5 \
      --set dtype=bfloat16,head_dtype=bfloat16 --official ~/UFM --pair a.png b.png
      # the official PyTorch code on the same snapshot and pair, alternating with ours
      # (torch.autocast("cpu", bfloat16) when dtype is bfloat16; benchmarks/official_torch.py)

Prints: latency (median and min of --runs timed calls after --warmup untimed ones), pairs/s, the
model's FLOPs per pair from XLA's cost analysis of the compiled forward (of a loop-free float32
twin: the cost analysis counts the body of the CPU attention and bf16 convolution loops once),
achieved GFLOP/s, and the
f32 matmul peak: the best of >= 2 x --runs samples of a square --matmul_n dot and of a dot at the
model's encoder-MLP shape, sampled between the model runs, and the same for the bf16 x bf16 ->
f32 dot (`preferred_element_type=float32`, the form XLA:CPU runs on its bf16 units). The share of
peak is min(model) against best(peak) of the model's dtype, printed with the load average and
thread count, so a loaded machine shows as a low peak sample rather than a flattering share.
--breakdown times each stage on its own, with its share of both peaks (and the official model's
time in each stage with --official).
--official times the official PyTorch model (benchmarks/official_torch.py: the user's clone,
"not available" and why when it does not import) on the same snapshot (--snapshot, or the random
params written as one to a temp dir) and the same pair (--pair, resized to --size; default
random pixels), one official run after each of ours, and prints the ratio JAX / official of the
medians and of the minima, the torch matmul peaks, and how far the two outputs differ.
--frames adds end-to-end pairs/s (reading, resizing, forward, unmapping, writing) next to the
model-only figure, the model run at --size as its inference resolution.
Params are random (`trainer.random_params`) unless --snapshot gives an official snapshot. Figures
are printed, never asserted; the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np


def _times(fn, runs: int, warmup: int = 0) -> list[float]:
  for _ in range(warmup):
    jax.block_until_ready(fn())
  times = []
  for _ in range(runs):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return times


def make_matmul(m: int, k: int, n: int, dtype=jnp.float32):
  """A jitted [m, k] x [k, n] jnp.dot (2 m k n flops) on random inputs; bf16 operands accumulate
  and return float32 (XLA:CPU's fast bf16 form; a bf16-out dot runs as a float32 one)."""
  ka, kb = jax.random.split(jax.random.PRNGKey(0))
  a = jax.random.normal(ka, (m, k), dtype)
  b = jax.random.normal(kb, (k, n), dtype)
  dot = jax.jit(functools.partial(
      jnp.dot, preferred_element_type=jnp.float32 if dtype == jnp.bfloat16 else None))
  return lambda: dot(a, b)


class Peak:
  """The practical matmul peak of one dtype (float32, or bf16 x bf16 -> f32): the best GFLOP/s
  over every sample of a few matmuls, one of them at the model's own shapes ([tokens, dim] x
  [dim, 4 dim], the encoder MLP). `sample()` is called between model runs, so a busy minute on a
  shared machine cannot make the peak look low while the model runs in a quiet one: the share
  printed is min(model) against best(peak)."""

  def __init__(self, shapes, dtype=jnp.float32):
    self.shapes = [tuple(s) for s in shapes]
    self.fns = [make_matmul(*s, dtype=dtype) for s in self.shapes]
    self.samples: list[float] = []
    for f in self.fns:
      _times(f, 0, warmup=2)

  def sample(self, repeats: int = 2):
    for (m, k, n), f in zip(self.shapes, self.fns):
      self.samples += [2 * m * k * n / t / 1e9 for t in _times(f, repeats)]

  @property
  def best(self) -> float:
    return max(self.samples)

  @property
  def median(self) -> float:
    return statistics.median(self.samples)


def machine() -> dict:
  """Load average and thread count: context every printed speed figure needs."""
  return {"load_avg_1m": round(os.getloadavg()[0], 2), "cpu_count": os.cpu_count(),
          "threads": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None}


def cost_flops(compiled) -> float:
  """FLOPs of a compiled XLA executable (cost_analysis returns a dict, or a list of them)."""
  cost = compiled.cost_analysis()
  if isinstance(cost, (list, tuple)):
    cost = cost[0] if cost else {}
  return float(cost.get("flops", float("nan"))) if cost else float("nan")


def counted_flops(fn, *args) -> float:
  """FLOPs of jit(fn)(*args) from XLA's cost analysis of its compiled module."""
  return cost_flops(jax.jit(fn).lower(*args).compile())


def loop_free(module):
  """`module` computing the same arithmetic without loops, for counting its FLOPs: XLA's
  cost analysis counts a loop body once, and on CPU the attention (layers.cpu_attention) and the
  bf16 convolutions (layers.conv_as_dots) are loops. The twin uses XLA's one-shot attention and
  float32 (XLA's convolutions); the FLOPs do not depend on the dtype."""
  import dataclasses  # pylint: disable=g-import-not-at-top
  from ufm_jax.models import layers  # pylint: disable=g-import-not-at-top
  if isinstance(module, layers.Attention):
    return module.clone(implementation="xla", dtype=None)
  config = getattr(module, "config", None)
  if config is not None and dataclasses.is_dataclass(config) and hasattr(config, "attention_impl"):
    return module.clone(config=config.replace(attention_impl="xla", dtype="float32",
                                              head_dtype="float32"))
  fields = {f: jnp.float32 for f in ("dtype", "unet_dtype", "head_dtype") if hasattr(module, f)}
  return module.clone(**fields) if fields else module


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


def read_pair_image(path: str, size_hw) -> np.ndarray:
  """An RGB uint8 image resized to size_hw (torch's bilinear antialias resize, as `predict`)."""
  from ufm_jax.data import io
  from ufm_jax.runtime.inference import resize_bilinear_aa
  img = io.read_image(path)
  if img.shape[:2] != tuple(size_hw):
    img = np.clip(np.rint(resize_bilinear_aa(img.astype(np.float32), size_hw)), 0, 255)
  return img.astype(np.uint8)


def load_official_torch(model, params, args, bf16: bool):
  """(official_torch.Official, None) on the snapshot of --snapshot, or on `params` written as
  one to a temporary folder (kept: it is as large as the model); (None, reason) when the official
  code is not available."""
  import tempfile

  import official_torch  # benchmarks/official_torch.py, beside this script
  from ufm_jax.models import refine

  clone = args.official or os.environ.get("UFM_OFFICIAL") or None
  why = official_torch.why_unavailable(clone, args.official_hub)
  if why:
    return None, why
  snapshot = args.snapshot  # --set only changes compute options (dtype, attention), not weights
  if snapshot is None:
    import ufm_jax
    snapshot = os.path.join(tempfile.mkdtemp(prefix="ufm_bench_snapshot_"), "snapshot")
    plain = model.clone(config=model.config.replace(dtype="float32", head_dtype="float32"))
    ufm_jax.save_official(plain, params, snapshot)
  threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
  return official_torch.load(snapshot, args.official_hub,
                             refine=isinstance(model, refine.UFMRefine), bf16=bf16,
                             threads=threads)


def official_peaks(official, shapes) -> dict:
  import official_torch  # benchmarks/official_torch.py
  return official_torch.matmul_peaks(official.torch, shapes, runs=1)


def report_official(official, why_not, lat_official, lat, torch_peaks, bf16, official_out,
                    ours) -> dict:
  """Prints (and returns) the official model's times next to ours and how far outputs differ."""
  if official is None:
    print(f"  official PyTorch code: not available ({why_not})")
    return {"official": "not available", "official_reason": why_not}
  med, fast = statistics.median(lat_official), min(lat_official)
  ours_med, ours_fast = statistics.median(lat), min(lat)
  flow_o, covis_o = official_out
  flow_j = np.asarray(ours["flow"], np.float32)
  covis_j = np.asarray(ours["covisibility"], np.float32)
  d_flow = np.abs(flow_j - flow_o)
  d_cov = np.abs(covis_j - covis_o)
  print(f"  official PyTorch ({official.version}, "
        f"{'torch.autocast(cpu, bfloat16)' if bf16 else 'float32'}) over {len(lat_official)} runs "
        f"alternating with ours: median {med * 1e3:.1f} ms, min {fast * 1e3:.1f} ms")
  print(f"  JAX / official: {ours_med / med:.2f}x (medians), {ours_fast / fast:.2f}x (minima)")
  print("  torch matmul peaks (best GFLOP/s at the same shapes): "
        + ", ".join(f"{k} {v:.0f}" for k, v in torch_peaks.items()))
  print(f"  outputs, JAX - official: flow |d| mean {d_flow.mean():.3g} px, max {d_flow.max():.3g} "
        f"px (flow |mean| {np.abs(flow_o).mean():.3g} px); covisibility |d| mean "
        f"{d_cov.mean():.3g}, max {d_cov.max():.3g}")
  return {"official": official.version, "official_latency_ms": med * 1e3,
          "official_latency_min_ms": fast * 1e3, "ratio_median": ours_med / med,
          "ratio_min": ours_fast / fast, "torch_peaks_gflops": torch_peaks,
          "flow_diff_mean_px": float(d_flow.mean()), "flow_diff_max_px": float(d_flow.max()),
          "covisibility_diff_mean": float(d_cov.mean())}


def main(argv=None) -> dict:
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--config", default="fixture_small", help="model variant name (ufm_jax.models.variants)")
  ap.add_argument("--snapshot", default=None, help="official HF snapshot instead of a config")
  ap.add_argument("--size", type=parse_size, default=None, help="HxW (multiples of 14)")
  ap.add_argument("--batch", type=int, default=1)
  ap.add_argument("--runs", type=int, default=5)
  ap.add_argument("--warmup", type=int, default=2)
  ap.add_argument("--matmul_n", type=int, default=2048, help="side of the square peak matmul")
  ap.add_argument("--breakdown", action="store_true",
                  help="also time each stage (patch embed, attention, MLPs, DPT heads, refiner) "
                       "as its own jitted function on the forward's shapes")
  ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
  ap.add_argument("--set", type=parse_overrides, default={}, metavar="K=V[,K=V]",
                  help="UFMConfig overrides, e.g. scan_blocks=true,dtype=bfloat16")
  ap.add_argument("--compile_only", action="store_true",
                  help="only lower and compile the forward (abstract params) and print the times")
  ap.add_argument("--grad", action="store_true",
                  help="with --compile_only: compile forward + gradient w.r.t. the params (a "
                       "one-device stand-in for the train step; --set remat=true to match it)")
  ap.add_argument("--frames", nargs="?", const="", default=None, metavar="DIR",
                  help="also time `infer --frames` end to end (ufm_jax.tools.sequence) on the frames in "
                       "DIR, or on --frames_pairs + 1 random PNGs in a temp dir when DIR is omitted")
  ap.add_argument("--frames_pairs", type=int, default=16,
                  help="pairs of the generated frames folder (consecutive frames)")
  ap.add_argument("--pair", nargs=2, default=None, metavar=("SOURCE", "TARGET"),
                  help="an image pair to run (resized to --size) instead of random pixels")
  ap.add_argument("--official", nargs="?", const="", default=None, metavar="DIR",
                  help="also time the official PyTorch code (a clone of UniFlowMatch/UFM with its "
                       "UniCeption submodule; default $UFM_OFFICIAL, else the installed package)")
  ap.add_argument("--official_hub", default=os.environ.get("UFM_DINOV2_HUB"), metavar="DIR",
                  help="local facebookresearch/dinov2 checkout for the official encoder (offline; "
                       "default $UFM_DINOV2_HUB, else torch.hub downloads it)")
  args = ap.parse_args(argv)
  if args.official is not None and argv is None:
    import official_torch  # benchmarks/official_torch.py, beside this script
    official_torch.rerun_with_clone(args.official or os.environ.get("UFM_OFFICIAL"))
  if args.frames is not None and args.compile_only:
    ap.error("--frames runs the model; it does not combine with --compile_only")

  if args.snapshot:
    import ufm_jax
    from ufm_jax.models import scan
    model, variables = ufm_jax.load_official(args.snapshot)
    params = variables["params"]   # the released models keep no BatchNorm statistics
    if args.set:
      model = model.clone(config=model.config.replace(**args.set))
      params = scan.to_layout(params, model.config)
    name = args.snapshot
  else:
    model, params, name = build_model(args.config, **args.set), None, args.config
  if args.compile_only:
    return compile_only(model, name, args)
  if args.size is None:
    from ufm_jax.runtime.inference import inference_resolutions
    args.size = inference_resolutions(model)[0]
  h, w = args.size
  if args.pair:
    src, tgt = (jnp.asarray(np.repeat(read_pair_image(p, (h, w))[None], args.batch, 0))
                for p in args.pair)
  else:
    rng = np.random.default_rng(0)
    src = jnp.asarray(rng.integers(0, 256, (args.batch, h, w, 3), dtype=np.uint8))
    tgt = jnp.asarray(rng.integers(0, 256, (args.batch, h, w, 3), dtype=np.uint8))

  t0 = time.perf_counter()
  if params is None:
    from ufm_jax.training import trainer  # pylint: disable=g-import-not-at-top
    params = jax.block_until_ready(trainer.random_params(model))
  t_init = time.perf_counter() - t0
  n_params = sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(params))

  fwd = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t))
  t0 = time.perf_counter()
  compiled = fwd.lower(params, src, tgt).compile()
  t_compile = time.perf_counter() - t0
  twin = loop_free(model)
  flops = counted_flops(lambda p, s, t: twin.apply({"params": p}, s, t), params, src, tgt)
  run_model = lambda: compiled(params, src, tgt)  # noqa: E731
  tokens = 2 * args.batch * (h // model.config.encoder.patch_size) * (w // model.config.encoder.patch_size)
  dim = model.config.encoder.embed_dim
  shapes = [(args.matmul_n,) * 3, (tokens, dim, 4 * dim)]
  peak, peak16 = Peak(shapes), Peak(shapes, jnp.bfloat16)
  bf16 = model.config.dtype == "bfloat16"
  official, why_not, torch_peaks = None, None, {}
  if args.official is not None:
    official, why_not = load_official_torch(model, params, args, bf16)
    if official is not None:
      views = official.inputs(np.asarray(src), np.asarray(tgt))
      run_official = lambda: official(views)  # noqa: E731
      run_official()
  _times(run_model, 0, warmup=args.warmup)
  # Model runs, official runs and peak samples alternate, so load from other processes hits
  # all of them alike.
  lat, lat_official = [], []
  for _ in range(args.runs):
    lat += _times(run_model, 1)
    if official is not None:
      t0 = time.perf_counter()
      official_out = run_official()
      lat_official.append(time.perf_counter() - t0)
      for k, v in official_peaks(official, shapes).items():
        torch_peaks[k] = max(torch_peaks.get(k, 0.0), v)
    peak.sample()
    peak16.sample()
  latency, fastest = statistics.median(lat), min(lat)
  env = machine()
  main_peak = peak16 if bf16 else peak

  res = {
      "config": name, "size_hw": [h, w], "batch": args.batch, "params": n_params,
      "overrides": args.set, "devices": f"{jax.devices()[0].platform} x{jax.device_count()}",
      "init_s": round(t_init, 2), "compile_s": round(t_compile, 2),
      "latency_ms": latency * 1e3, "latency_min_ms": fastest * 1e3,
      "pairs_per_s": args.batch / fastest, "gflop_per_pair": flops / args.batch / 1e9,
      "achieved_gflops": flops / fastest / 1e9, "matmul_peak_gflops": peak.best,
      "matmul_peak_median_gflops": peak.median,
      "bf16_dot_peak_gflops": peak16.best, "bf16_dot_peak_median_gflops": peak16.median,
      "fraction_of_peak": flops / fastest / 1e9 / main_peak.best,
      **env,
  }
  print(f"config {name} {args.set or ''} size {h}x{w}  batch {args.batch}  params "
        f"{n_params / 1e6:.2f}M  on {res['devices']}  (XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r})")
  print(f"  load average {env['load_avg_1m']} on {env['cpu_count']} CPUs, {env['threads']} threads")
  print(f"  init {t_init:.1f} s   compile {t_compile:.1f} s")
  print(f"  latency over {args.runs} runs: median {latency * 1e3:.1f} ms, min {fastest * 1e3:.1f} ms"
        f"   {res['pairs_per_s']:.3f} pairs/s (min)")
  print(f"  FLOPs/pair (XLA cost analysis of the loop-free float32 twin)  {res['gflop_per_pair']:.2f} GFLOP")
  print(f"  achieved {res['achieved_gflops']:.1f} GFLOP/s at min(model); peaks over "
        f"{len(peak.samples)} samples each of {' and '.join('x'.join(map(str, s)) for s in shapes)}"
        f" interleaved with the model: f32 matmul best {peak.best:.1f} (median "
        f"{peak.median:.1f}), bf16 x bf16 -> f32 dot best {peak16.best:.1f} (median "
        f"{peak16.median:.1f}) GFLOP/s -> {100 * res['fraction_of_peak']:.0f}% of the "
        f"{'bf16 dot' if bf16 else 'f32 matmul'} peak (min(model) vs best(peak))")
  if bf16 and model.config.head_dtype != "bfloat16":
    print("  (the DPT heads run in float32: head_dtype=bfloat16 runs them in bf16, as the official "
          "code does under CPU autocast)")
  if args.official is not None:
    res.update(report_official(official, why_not, lat_official, lat, torch_peaks, bf16,
                               official_out if official is not None else None,
                               compiled(params, src, tgt)))
  if args.breakdown:
    official_ms = (official.stage_ms(views, args.runs) if official is not None else None)
    res["stages"] = breakdown(model, params, src, tgt, peak, args.runs, t_model=fastest,
                              peak16=peak16, official_ms=official_ms)
  if args.frames is not None:
    res.update(end_to_end(model, params, (h, w), args.batch, args.frames, args.frames_pairs))
    print(f"  end to end ({res['frames_pairs']} pairs of {res['frames_dir']}: read, predict, write "
          f".flo, through ufm_jax.tools.sequence): {res['end_to_end_pairs_per_s']:.3f} pairs/s, "
          f"{100 * res['end_to_end_pairs_per_s'] / res['pairs_per_s']:.0f}% of the model-only "
          f"{res['pairs_per_s']:.3f} pairs/s (min)")
  print(json.dumps(res))
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
  return res


def end_to_end(model, params, size_hw, batch: int, frames: str, n_pairs: int) -> dict:
  """Pairs/s of `python -m ufm_jax infer --frames` (ufm_jax.tools.sequence.run: thread-pool reads,
  batched predict, .flo writes) on `frames` (empty: n_pairs + 1 random PNGs written to a temp dir),
  with the model's inference resolution set to size_hw. A first run over one batch compiles;
  the timed run rewrites everything (overwrite)."""
  import tempfile

  from ufm_jax.tools import sequence
  from ufm_jax.data import io

  model = model.clone(config=model.config.replace(inference_resolution=tuple(size_hw)))
  label = frames or f"{n_pairs + 1} random {size_hw[0]}x{size_hw[1]} PNGs"
  from ufm_jax.data.sources import frames as frame_source
  with tempfile.TemporaryDirectory(prefix="ufm_bench_frames_") as tmp:
    if not frames:
      frames = os.path.join(tmp, "frames")
      os.makedirs(frames)
      rng = np.random.default_rng(0)
      for i in range(n_pairs + 1):
        io.write_image(os.path.join(frames, f"{i:06d}.png"),
                       rng.integers(0, 256, (*size_hw, 3), dtype=np.uint8))
    elif not os.path.isdir(frames):
      raise SystemExit(f"--frames {frames}: folder not found")
    pairs = frame_source.frame_pairs(frames)
    sequence.run(model, params, pairs[:batch], os.path.join(tmp, "warmup"), batch=batch,
                 progress=False)
    counts = sequence.run(model, params, pairs, os.path.join(tmp, "out"), batch=batch,
                          overwrite=True, progress=False)
  if counts["failed"]:
    raise SystemExit(f"--frames {frames}: {counts['failed']} pairs had unreadable images")
  return {"frames_dir": label, "frames_pairs": counts["done"],
          "end_to_end_s": round(counts["seconds"], 3),
          "end_to_end_pairs_per_s": counts["done"] / counts["seconds"]}


# Stages of --breakdown: (label, module path pattern, method). The first call of each pattern is
# timed on its own with the real input shapes; the count is how often the forward calls it.
STAGES = (
    ("patch embed", r"encoder/patch_embed", "__call__"),
    ("encoder attention", r"encoder/blocks_\d+/attn", "__call__"),
    ("encoder MLP", r"encoder/blocks_\d+/mlp", "__call__"),
    ("fusion attention", r"info_sharing/self_attention_blocks_\d+/attn", "__call__"),
    ("fusion MLP", r"info_sharing/self_attention_blocks_\d+/mlp", "__call__"),
    ("flow head DPT feature", r"head1_0_0", "__call__"),
    ("flow head regression", r"head1_0_1", "__call__"),
    ("covisibility head DPT feature", r"uncertainty_head_0_0", "__call__"),
    ("covisibility head regression", r"uncertainty_head_0_1", "__call__"),
    # UFMRefine shares the refiner's scope with the root (its params sit at the top level).
    ("refiner U-Net", r"(refiner/)?unet_feature", "__call__"),
    ("refiner classification head", r"(refiner/)?classification_head", "__call__"),
    ("refiner local refinement", r"(refiner)?", "refine"),
)


def breakdown(model, params, src, tgt, peak: Peak, runs: int, t_model: float,
              peak16: Peak | None = None, official_ms: dict | None = None) -> list[dict]:
  """Times each stage of STAGES as its own jitted function on the shapes the forward gives it
  (captured with flax's method interceptor during an abstract forward), with random inputs of
  those shapes and the model's own parameters of that module. Unscanned models only (the
  stages are the per-block modules). Shares against the f32 matmul peak and, with `peak16`, the
  bf16 x bf16 -> f32 dot peak; `official_ms` (official_torch.Official.stage_ms: ms per forward
  in each stage) is printed beside each stage's total."""
  import re

  import flax.linen as nn

  if model.config.scan_blocks:
    raise SystemExit("--breakdown times per-block modules: run it with --set scan_blocks=false")
  found: dict[str, dict] = {}

  def intercept(next_fun, args, kwargs, context):
    mod = context.module
    path = "/".join(mod.scope.path) if mod.scope is not None else ""
    for label, pattern, method in STAGES:
      if context.method_name == method and re.fullmatch(pattern, path):
        if label not in found:
          spec = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype) if hasattr(x, "shape") else x  # noqa: E731
          found[label] = {"module": mod.clone(parent=None), "path": path, "method": method,
                          "args": jax.tree.map(spec, args), "kwargs": jax.tree.map(spec, kwargs),
                          "count": 0}
        found[label]["count"] += 1
    return next_fun(*args, **kwargs)

  with nn.intercept_methods(intercept):
    jax.eval_shape(lambda p, s, t: model.apply({"params": p}, s, t), params, src, tgt)

  rows = []
  rng = np.random.default_rng(0)
  for label, _, _ in STAGES:
    if label not in found:
      continue
    st = found[label]
    sub = params
    for key in filter(None, st["path"].split("/")):
      sub = sub[key]
    make = lambda x: (jnp.asarray(rng.standard_normal(x.shape), x.dtype)  # noqa: E731
                      if isinstance(x, jax.ShapeDtypeStruct) else x)
    # Arrays are the jitted arguments; everything else (sizes, flags) is closed over.
    leaves, tree = jax.tree.flatten((st["args"], st["kwargs"]))
    is_array = [isinstance(x, jax.ShapeDtypeStruct) for x in leaves]
    arrays = [make(x) for x, a in zip(leaves, is_array) if a]
    mod, method = st["module"], st["method"]

    def call(p, arrays, mod=mod, method=method, leaves=leaves, tree=tree, is_array=is_array):
      it = iter(arrays)
      a, kw = jax.tree.unflatten(tree, [next(it) if f else x for x, f in zip(leaves, is_array)])
      return mod.apply({"params": p}, *a, **kw, method=None if method == "__call__" else method)
    compiled = jax.jit(call).lower(sub, arrays).compile()
    flops = counted_flops(functools.partial(call, mod=loop_free(mod)), sub, arrays)
    times = _times(lambda: compiled(sub, arrays), runs, warmup=1)
    peak.sample(1)
    if peak16 is not None:
      peak16.sample(1)
    t = min(times)
    row = {"stage": label, "calls": st["count"], "ms": t * 1e3, "total_ms": t * 1e3 * st["count"],
           "gflop": flops / 1e9, "share_of_peak": flops / t / 1e9 / peak.best}
    if peak16 is not None:
      row["share_of_bf16_peak"] = flops / t / 1e9 / peak16.best
    if official_ms is not None and label in official_ms:
      row["official_total_ms"] = official_ms[label]
    rows.append(row)
  total = sum(r["total_ms"] for r in rows)
  print(f"\n  breakdown (each stage jitted alone on its forward shapes; min of {runs} runs; share "
        f"against the best f32 matmul peak, {peak.best:.1f} GFLOP/s"
        + (f", and the best bf16 x bf16 -> f32 dot peak, {peak16.best:.1f}" if peak16 else "")
        + ("; official: ms per forward in the same modules, forward hooks, min of runs"
           if official_ms is not None else "") + ")")
  print(f"  {'stage':32s} {'calls':>5s} {'ms/call':>9s} {'ms total':>9s} {'GFLOP/call':>10s} "
        f"{'f32 pk':>6s}" + (f" {'bf16 pk':>7s}" if peak16 else "")
        + (f" {'official ms':>11s} {'JAX/off':>7s}" if official_ms is not None else ""))
  for r in rows:
    line = (f"  {r['stage']:32s} {r['calls']:5d} {r['ms']:9.1f} {r['total_ms']:9.1f} "
            f"{r['gflop']:10.2f} {100 * r['share_of_peak']:5.0f}%")
    if peak16 is not None:
      line += f" {100 * r['share_of_bf16_peak']:6.0f}%"
    if "official_total_ms" in r:
      line += f" {r['official_total_ms']:11.1f} {r['total_ms'] / r['official_total_ms']:6.2f}x"
    print(line)
  print(f"  {'sum of stages':32s} {'':5s} {'':9s} {total:9.1f}   (full forward {t_model * 1e3:.1f} ms; "
        f"the rest is norms, residuals, resizes and glue)"
        + (f"; official sum {sum(official_ms.values()):.1f} ms" if official_ms else ""))
  return rows


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
