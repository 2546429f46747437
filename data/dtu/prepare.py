"""DTU benchmark pair list: every covisible view pair of the evaluation scans.

  python data/dtu/prepare.py --root /data/dtu [--min_covis 0.25] [--light 3]

Checks the layout the `dtu` source reads (Rectified/, Cameras/, Depths_raw/; see README.md) and
writes `<root>/pairs_test.txt`: for each of the 22 MVSNet evaluation scans present, every pair of
its 49 views whose mutual covisibility (depth reprojection, fraction of all pixels, at --max_side
resolution) exceeds --min_covis. Without this file the source falls back to MVSNet's pair.txt
neighbours.

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import os
import sys

from ufm_jax import data
from ufm_jax.data.sources import posed


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--root", required=True)
  p.add_argument("--split", default="test", choices=("test", "val", "all"))
  p.add_argument("--min_covis", type=float, default=0.25)
  p.add_argument("--max_side", type=int, default=160)
  p.add_argument("--light", type=int, default=3)
  p.add_argument("--no_progress", action="store_true")
  args = p.parse_args(argv)
  for sub in ("Rectified", "Cameras", "Depths_raw"):
    posed.require_dir(os.path.join(args.root, sub), f"DTU {sub}/ (see data/dtu/README.md)")
  src = data.get_source("dtu", args.root, split=args.split, light=args.light)
  scenes = src.scenes()
  if not scenes:
    raise SystemExit(f"{args.root}/Rectified: none of the DTU {args.split} scans")
  pairs, skipped = posed.mine_pairs(src, scenes, args.min_covis, args.max_side,
                                     progress=not args.no_progress)
  out = os.path.join(args.root, f"pairs_{args.split}.txt")
  posed.write_pair_list(out, pairs, header=(
      f"DTU {args.split}: view pairs with mutual covisibility > {args.min_covis} (light "
      f"{args.light})\nscene view0 view1 score"))
  for s in skipped:
    print(f"skipped {s}", file=sys.stderr)
  print(f"{len(scenes)} scans, {len(pairs)} pairs -> {out}")
  return out


if __name__ == "__main__":
  main()
