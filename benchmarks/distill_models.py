"""The distillation students beside UFM-Base, in one process on one machine (docs/distillation.md).

  python benchmarks/distill_models.py --models ufm_base,ufm_small,ufm_tiny --size 420x560
  python benchmarks/distill_models.py --models ufm_small,ufm_tiny --runs 3 --no_onnx   # quicker
  python benchmarks/distill_models.py --candidates     # FLOPs and params of the sizes weighed
  python benchmarks/distill_models.py --step_flops --models ufm_small --teacher variant:ufm_base
      # FLOPs of the distillation train step against the same student's step without a teacher

Per model: parameters; GFLOP per pair at --size (XLA's cost analysis of the lowered loop-free
float32 twin, benchmarks/inference.py's counter; the FLOPs do not depend on the dtype); CPU
latency per pair at batch 1 in float32 and in bfloat16 (dtype and head_dtype bfloat16, as the
official code under CPU autocast), the min and median of --runs timed calls after a warm-up,
the models' runs interleaved round by round so that load from other processes falls on all of
them alike; and the size of the ONNX file `python -m ufm_jax export --format onnx --size SIZE`
writes for a converted checkpoint of the model (random weights; the size depends on the
structure only) and the seconds that command takes. Also at each model's own inference
resolution where it differs from --size (ufm_tiny: 294 x 392). Params are random. No GPU
figure: the device scripts are benchmarks/gpu_check.py and benchmarks/inference.py on a GPU host.
The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import inference as bench   # benchmarks/inference.py, beside this script

REPO = pathlib.Path(__file__).resolve().parents[1]


def candidates() -> dict:
  """The structures weighed against ufm_small and ufm_tiny: each changes one part of ufm_small."""
  import dataclasses
  from ufm_jax.models import variants
  s = variants.ufm_small()
  heads = lambda dim, dims, f: dict(flow_head=variants._dpt(384, dim, 2, dims, f),  # noqa: E731
                                    covisibility_head=variants._dpt(384, dim, 1, dims, f))
  fusion = lambda dim, depth, n, taps: dataclasses.replace(  # noqa: E731
      s.info_sharing, dim=dim, depth=depth, num_heads=n, indices=taps)
  return {
      "ufm_small": s,
      "ufm_small with UFM-Base's DPT widths (96..768, 256)": s.replace(
          **heads(384, (96, 192, 384, 768), 256)),
      "ufm_small with quarter DPT widths (24..192, 64)": s.replace(
          **heads(384, (24, 48, 96, 192), 64)),
      "ufm_small with a 12 x 384 fusion": s.replace(info_sharing=fusion(384, 12, 6, (5, 8))),
      "ufm_small with a 4 x 256 fusion": s.replace(info_sharing=fusion(256, 4, 4, (1, 2)),
                                                   **heads(256, (48, 96, 192, 384), 128)),
      "ufm_tiny": variants.ufm_tiny(),
  }


def step_flops(students, teacher: str, hw, batch: int) -> dict:
  """{student: GFLOP per row of the distillation step and of the plain 560-recipe step}."""
  from ufm_jax.planning import flops
  from ufm_jax.training import config_lib
  out = {}
  for student in students:
    distill = config_lib.load_config(f"{REPO}/configs/distill.py:teacher={teacher},"
                                     f"student={student},data=synthetic,recipe=560")
    plain = config_lib.load_config(f"{REPO}/configs/ufm560.py:model={student}")
    plain.loss.groups = 1   # few rows: the recipe's 8 loss groups need 16 (no model FLOPs there)
    rows = {k: flops.model_flops(c, hw, batch).flops / batch / 1e9
            for k, c in (("distill", distill), ("plain", plain))}
    rows["teacher_share"] = 1 - rows["plain"] / rows["distill"]
    out[student] = rows
    print(f"{student} taught by {teacher} at {hw[0]}x{hw[1]}, {batch} rows: "
          f"{rows['distill']:.0f} GFLOP per row with the teacher, {rows['plain']:.0f} without "
          f"(the teacher's forward {100 * rows['teacher_share']:.0f}% of the step)", flush=True)
  print(json.dumps(out))
  return out


def gflop_per_pair(model, params, hw) -> float:
  from ufm_jax.planning import hlo_stats
  twin = bench.loop_free(model)
  x = jax.ShapeDtypeStruct((1, *hw, 3), jnp.uint8)
  lowered = jax.jit(lambda p, s, t: twin.apply({"params": p}, s, t)).lower(params, x, x)
  return hlo_stats.flops(lowered) / 1e9


def onnx_export(model, params, hw, workdir) -> tuple[float, float]:
  """(MB of the ONNX file the CLI exports for a converted checkpoint of (model, params), seconds
  the export command took as a whole: start, load, conversion, write)."""
  from ufm_jax.runtime import model_io
  ckpt = pathlib.Path(workdir) / "ckpt"
  model_io.save(ckpt, model, {"params": params})
  out = pathlib.Path(workdir) / "model.onnx"
  cmd = [sys.executable, "-m", "ufm_jax", "export", "--checkpoint", str(ckpt), "--size",
         f"{hw[0]}x{hw[1]}", "--format", "onnx", "--out", str(out)]
  t0 = time.perf_counter()
  r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
  seconds = time.perf_counter() - t0
  if r.returncode:
    raise SystemExit(f"export failed:\n{r.stderr[-3000:]}")
  size = sum(p.stat().st_size for p in out.parent.glob(out.name + "*")
             if p.suffix != ".json")   # the graph and any external-data file, not the sidecar
  return size / 1e6, seconds


def main(argv=None) -> dict:
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--models", default="ufm_base,ufm_small,ufm_tiny")
  ap.add_argument("--size", type=bench.parse_size, default=(420, 560))
  ap.add_argument("--runs", type=int, default=5)
  ap.add_argument("--no_onnx", action="store_true")
  ap.add_argument("--json", default=None)
  ap.add_argument("--step_flops", action="store_true",
                  help="FLOPs of configs/distill.py's train step (teacher --teacher, the student "
                       "each of --models) at --size and --batch rows, beside the same student's "
                       "step in the 560 recipe without a teacher (ufm_jax.planning.flops.model_flops: the "
                       "step's jaxpr, remat left out)")
  ap.add_argument("--teacher", default="variant:ufm_base")
  ap.add_argument("--batch", type=int, default=2, help="rows of the --step_flops step")
  ap.add_argument("--candidates", action="store_true",
                  help="only params and GFLOP at --size of `candidates()` (no weights, no runs)")
  args = ap.parse_args(argv)

  from ufm_jax.runtime import inference
  from ufm_jax.training import optim, trainer
  from ufm_jax.models import ufm, variants
  if args.step_flops:
    return step_flops([n for n in args.models.split(",") if n], args.teacher, tuple(args.size),
                      args.batch)
  if args.candidates:
    out = {}
    for label, cfg in candidates().items():
      model = ufm.model_from_config(cfg)
      shapes = ufm.param_shapes(model)
      out[label] = {"params": optim.count_params(shapes)["total"],
                    "gflop_per_pair": gflop_per_pair(model, shapes, tuple(args.size))}
      print(f"{label}: {out[label]['params'] / 1e6:.1f}M parameters, "
            f"{out[label]['gflop_per_pair']:.1f} GFLOP at {args.size[0]}x{args.size[1]}",
            flush=True)
    print(json.dumps(out))
    return out
  names = [n for n in args.models.split(",") if n]
  rng = np.random.default_rng(0)
  rows, timed, weights = {}, [], {}
  for name in names:
    model = variants.build_model(name)
    params = weights[name] = trainer.random_params(model)
    n = optim.count_params(params)["total"]
    sizes = [tuple(args.size)]
    own = tuple(inference.inference_resolutions(model)[0])
    if own != sizes[0]:
      sizes.append(own)
    rows[name] = {"params": n, "gflop_per_pair": {f"{h}x{w}": gflop_per_pair(model, params, (h, w))
                                                  for h, w in sizes}}
    for dtype in ("float32", "bfloat16"):
      m = variants.build_model(name, dtype=dtype, head_dtype=dtype)
      for hw in sizes:
        src = jnp.asarray(rng.integers(0, 256, (1, *hw, 3), dtype=np.uint8))
        tgt = jnp.asarray(rng.integers(0, 256, (1, *hw, 3), dtype=np.uint8))
        fwd = jax.jit(lambda p, s, t, m=m: m.apply({"params": p}, s, t))
        t0 = time.perf_counter()
        compiled = fwd.lower(params, src, tgt).compile()
        compile_s = time.perf_counter() - t0
        run = lambda c=compiled, s=src, t=tgt, p=params: c(p, s, t)   # noqa: E731
        bench._times(run, 0, warmup=1)
        timed.append({"model": name, "dtype": dtype, "size": f"{hw[0]}x{hw[1]}", "run": run,
                      "times": [], "compile_s": compile_s})
    print(f"{name}: {n:,} parameters, "
          + ", ".join(f"{k} {v:.1f} GFLOP" for k, v in rows[name]["gflop_per_pair"].items()),
          flush=True)
  for _ in range(args.runs):   # round by round: every model under the same load
    for t in timed:
      t["times"] += bench._times(t["run"], 1)
  for t in timed:
    rows[t["model"]].setdefault("cpu_ms", {})[f"{t['dtype']} {t['size']}"] = {
        "min": min(t["times"]) * 1e3, "median": statistics.median(t["times"]) * 1e3,
        "compile_s": round(t["compile_s"], 1)}
  env = bench.machine()
  report(rows, args, env)
  if not args.no_onnx:
    for name in sorted(names, key=lambda n: rows[n]["params"]):   # the largest export last
      with tempfile.TemporaryDirectory(prefix="ufm_distill_onnx_") as tmp:
        try:
          rows[name]["onnx_mb"], rows[name]["onnx_export_s"] = onnx_export(
              variants.build_model(name), weights[name], tuple(args.size), tmp)
        except SystemExit as e:   # one model's failed export does not lose the other figures
          rows[name]["onnx_error"] = str(e)[-500:]
          print(f"{name}: ONNX export failed: {str(e)[-500:]}", flush=True)
          continue
      print(f"{name}: ONNX {rows[name]['onnx_mb']:.1f} MB at {args.size[0]}x{args.size[1]}, "
            f"exported in {rows[name]['onnx_export_s']:.0f} s", flush=True)
  res = {"size": list(args.size), "models": rows, **env}
  print(json.dumps(res))
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(res, indent=1))
  return res


def report(rows, args, env) -> None:
  print(f"\nload average {env['load_avg_1m']} on {env['cpu_count']} CPUs, {env['threads']} "
        f"threads; {args.runs} interleaved runs, batch 1; {jax.devices()[0].platform}")
  base = rows.get("ufm_base")
  for name, r in rows.items():
    ms = " | ".join(f"{k}: {v['min']:.0f} (median {v['median']:.0f}) ms"
                    for k, v in r["cpu_ms"].items())
    rel = ""
    if base and name != "ufm_base":
      key = f"float32 {args.size[0]}x{args.size[1]}"
      rel = (f"  [{base['params'] / r['params']:.1f}x fewer params, "
             f"{base['cpu_ms'][key]['min'] / r['cpu_ms'][key]['min']:.1f}x faster f32]")
    print(f"{name:10s} {r['params'] / 1e6:7.1f}M  {ms}{rel}", flush=True)


if __name__ == "__main__":
  main()
