r"""The mean and range over seeds of evaluate.py's results, the form every demonstration figure
in docs/ takes (issue #53): one row per metric, each seed's value beside them.

  python benchmarks/seed_summary.py results/cov_s0 results/cov_s1 results/cov_s2
  python benchmarks/seed_summary.py results/cov_s{0,1,2} --versus results/nohead_s{0,1,2}
  python benchmarks/seed_summary.py results/student_s{0,1,2} --versus results/teacher

Each argument is an evaluate.py output folder (its results.json) or the file itself. With
`--versus`, the ratio of the two groups' means is printed for every metric both have (for
example the students' EPE over the teacher's). `--ratio NUM:DEN` adds the per-run ratio of two
metrics of the same run, with its mean and range (`--ratio synthetic/ause:synthetic/ause_random`).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys


def load(path: str) -> dict:
  p = pathlib.Path(path)
  if p.is_dir():
    p = p / "results.json"
  try:
    return json.loads(p.read_text())
  except (OSError, json.JSONDecodeError) as e:
    raise SystemExit(f"seed_summary: cannot read {p}: {e}") from None


def summary(runs: list[dict]) -> dict[str, tuple[float, float, float, list[float]]]:
  """metric -> (mean, min, max, values) over the runs that report it as a finite number."""
  out = {}
  keys = sorted({k for r in runs for k in r["metrics"]})
  for k in keys:
    vals = [r["metrics"][k] for r in runs if isinstance(r["metrics"].get(k), (int, float))]
    vals = [float(v) for v in vals if math.isfinite(v)]
    if vals:
      out[k] = (sum(vals) / len(vals), min(vals), max(vals), vals)
  return out


def ratio(runs: list[dict], num: str, den: str) -> tuple[float, float, float, list[float]]:
  vals = [r["metrics"][num] / r["metrics"][den] for r in runs]
  return sum(vals) / len(vals), min(vals), max(vals), vals


def main(argv=None) -> int:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("runs", nargs="+", help="evaluate.py output folders (or results.json files)")
  ap.add_argument("--versus", nargs="+", default=(), help="a second group: ratio of the means")
  ap.add_argument("--ratio", action="append", default=[],
                  help="NUM:DEN, two metric keys of one run, e.g. synthetic/ause:synthetic/ause_random")
  args = ap.parse_args(argv)
  runs = [load(p) for p in args.runs]
  steps = sorted({r.get("step") for r in runs}, key=str)
  print(f"{len(runs)} runs (steps {steps}); mean [min, max] | per run in the order given")
  table = summary(runs)
  other = summary([load(p) for p in args.versus]) if args.versus else {}
  for k, (mean, lo, hi, vals) in table.items():
    line = f"{k:36s} {mean:10.4f} [{lo:.4f}, {hi:.4f}] | " + " ".join(f"{v:.4f}" for v in vals)
    if k in other and other[k][0]:
      line += f"   / versus mean {other[k][0]:.4f} = {mean / other[k][0]:.3f}x"
    print(line)
  for spec in args.ratio:
    num, sep, den = spec.partition(":")
    if not sep:
      print(f"seed_summary: --ratio {spec!r} is not NUM:DEN", file=sys.stderr)
      return 2
    missing = [k for k in (num, den) for r in runs if k not in r["metrics"]]
    if missing:
      print(f"seed_summary: no metric {missing[0]!r} in every run", file=sys.stderr)
      return 2
    mean, lo, hi, vals = ratio(runs, num, den)
    print(f"{num} / {den}: {mean:.3f} [{lo:.3f}, {hi:.3f}] | " + " ".join(f"{v:.3f}" for v in vals))
  return 0


if __name__ == "__main__":
  sys.exit(main())
