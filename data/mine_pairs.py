"""Mines training / benchmark pairs of a posed dataset by mutual covisibility.

  python data/mine_pairs.py --dataset scannetpp --root /data/scannetpp_wai --split train
  python data/mine_pairs.py --dataset dtu --root /data/dtu --split test --min_covis 0.1

For every scene, every pair of frames is scored by its mutual covisibility: the smaller of the
two directions' covisible-pixel fractions (depth reprojection with the dataset's Table S1
thresholds, computed on depth subsampled to `--max_side` pixels). Pairs above `--min_covis`
(default 0.25, the supplementary's ScanNet++ rule) are written to `<root>/pairs_<split>.txt`
(`scene frame0 frame1 score`), which every posed source reads. Dataset options go through
`--option key=value` (e.g. `--option cameras='["lcam_front"]'` for tartanair_v2).

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from ufm_jax import data
from ufm_jax.data.sources import posed


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--dataset", required=True)
  p.add_argument("--root", required=True)
  p.add_argument("--split", default="train")
  p.add_argument("--min_covis", type=float, default=0.25)
  p.add_argument("--max_side", type=int, default=128)
  p.add_argument("--max_frames", type=int, default=None, help="first N frames per scene only")
  p.add_argument("--scenes", nargs="*", default=None)
  p.add_argument("--out", default=None, help="default: <root>/pairs_<split>.txt")
  p.add_argument("--option", action="append", default=[], help="dataset option key=value (JSON)")
  args = p.parse_args(argv)
  options = {}
  for kv in args.option:
    k, v = kv.split("=", 1)
    try:
      options[k] = json.loads(v)
    except json.JSONDecodeError:
      options[k] = v
  src = data.get_source(args.dataset, args.root, split=args.split, **options)
  if not hasattr(src, "frames"):
    raise SystemExit(f"{args.dataset}: not a posed dataset (no frame listing); nothing to mine")
  pairs, skipped = posed.mine_pairs(src, args.scenes, args.min_covis, args.max_side,
                                     args.max_frames)
  out = args.out or os.path.join(args.root, f"pairs_{args.split}.txt")
  posed.write_pair_list(out, pairs, header=(
      f"{args.dataset} {args.split}: frame pairs with mutual covisibility > {args.min_covis}\n"
      f"(min over both directions, fraction of all pixels, depth at {args.max_side} px)\n"
      "scene frame0 frame1 score"))
  for s in skipped:
    print(f"skipped {s}", file=sys.stderr)
  print(f"wrote {len(pairs)} pairs to {out} ({len(skipped)} unreadable views skipped)")
  return out


if __name__ == "__main__":
  main()
