"""Time metrics.sample_matches (ufm_jax.match, `python -m ufm_jax match`, the demo) per match count.

  python benchmarks/sample_matches.py                       # grid KDE (the default path)
  python benchmarks/sample_matches.py --nums 2000,5000 --exact   # also the exact pairwise KDE

The input is a dense flow at --size (a smooth warp that squeezes part of the image, so the KDE
balancing has clusters to flatten) with a graded covisibility; each count is drawn --runs times
(fresh seeds) and the median and min seconds are printed with the load average. Figures are
printed, never asserted.
"""

import argparse
import os
import statistics
import time

import numpy as np

from ufm_jax.evaluators import metrics


def scene(h: int, w: int):
  ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
  x1 = np.where(xs < w / 2, 0.3 * xs, xs) + 8 * np.sin(ys / 60)
  flow = np.stack([np.clip(x1, 0, w - 1) - xs, 6 * np.cos(xs / 80)], -1).astype(np.float32)
  covis = np.clip(0.6 + 0.5 * np.sin(xs / 30) * np.cos(ys / 40), 0, 1).astype(np.float32)
  return flow, covis


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--size", default="420x560", help="HxW of the flow")
  ap.add_argument("--nums", default="2000,5000,20000", help="match counts")
  ap.add_argument("--runs", type=int, default=3)
  ap.add_argument("--exact", action="store_true",
                  help="also time kde='exact' (the pairwise sum; minutes at 20000)")
  args = ap.parse_args(argv)
  h, w = (int(v) for v in args.size.split("x"))
  flow, covis = scene(h, w)
  methods = ["auto"] + (["exact"] if args.exact else [])
  print(f"sample_matches on a {h}x{w} flow, load average {os.getloadavg()[0]:.2f} on "
        f"{os.cpu_count()} CPUs; seconds per call over {args.runs} runs")
  for num in (int(v) for v in args.nums.split(",")):
    for method in methods:
      times = []
      for seed in range(args.runs):
        t0 = time.perf_counter()
        k0, _ = metrics.sample_matches(flow, covis, num, np.random.default_rng(seed), kde=method)
        times.append(time.perf_counter() - t0)
      kind = method if method != "auto" else (
          "exact" if 4 * num <= metrics.KDE_EXACT_MAX else "grid")
      print(f"  {num:6d} matches ({4 * num} candidates, kde {kind:5s}): median "
            f"{statistics.median(times):7.2f} s, min {min(times):7.2f} s  ({len(k0)} drawn)")


if __name__ == "__main__":
  main()
