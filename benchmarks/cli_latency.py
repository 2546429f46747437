"""End-to-end time of `python -m ufm_jax infer` for one pair: process start to files written.

  python benchmarks/cli_latency.py --checkpoint ../shared/fixtures/ufm_reference/base --snapshot
  python benchmarks/cli_latency.py --checkpoint DIR --size 420x560 --runs 2

Runs the CLI as a user would, in fresh processes: once with an empty persistent compilation
cache (cold: the forward is compiled and stored), then --runs times with that cache (warm: the
executable is loaded from disk), and once with `--compile_cache off`. Prints the wall seconds of
each and one JSON line. The images are random (--size HxW, default 420x560); their content does
not change the time. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ufm_jax.data.io import write_image


def run_infer(args, src, tgt, out, cache) -> float:
  cmd = [sys.executable, "-m", "ufm_jax", "infer", str(src), str(tgt), "--checkpoint", args.checkpoint,
         "--out", str(out), "--compile_cache", str(cache)] + (["--snapshot"] if args.snapshot else [])
  env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
  t0 = time.perf_counter()
  r = subprocess.run(cmd, capture_output=True, text=True, env=env)
  dt = time.perf_counter() - t0
  if r.returncode != 0:
    raise SystemExit(f"infer failed ({r.returncode}):\n{r.stderr[-2000:]}")
  return dt


def main(argv=None) -> dict:
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--checkpoint", required=True, help="as for infer: converted checkpoint, workdir or snapshot")
  ap.add_argument("--snapshot", action="store_true", help="--checkpoint is an official HF snapshot")
  ap.add_argument("--size", default="420x560", help="HxW of the random test images")
  ap.add_argument("--runs", type=int, default=2, help="warm runs")
  args = ap.parse_args(argv)
  h, w = (int(v) for v in args.size.lower().split("x"))
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    rng = np.random.default_rng(0)
    src, tgt = tmp / "a.png", tmp / "b.png"
    for p in (src, tgt):
      write_image(p, rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    cache = tmp / "cache"
    cold = run_infer(args, src, tgt, tmp / "cold", cache)
    warm = [run_infer(args, src, tgt, tmp / f"warm{i}", cache) for i in range(args.runs)]
    off = run_infer(args, src, tgt, tmp / "off", "off")
  res = {"checkpoint": args.checkpoint, "image_hw": [h, w], "cold_s": round(cold, 2),
         "warm_s": round(statistics.median(warm), 2), "warm_runs_s": [round(t, 2) for t in warm],
         "cache_off_s": round(off, 2), "load_avg_1m": round(os.getloadavg()[0], 2)}
  print(f"infer, one {h}x{w} pair, process start to files written ({args.checkpoint}):")
  print(f"  cold (empty cache) {cold:.1f} s   warm (median of {args.runs}) {res['warm_s']:.1f} s   "
        f"cache off {off:.1f} s   (load average {res['load_avg_1m']})")
  print(json.dumps(res))
  return res


if __name__ == "__main__":
  main()
