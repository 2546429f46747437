"""Kubric-4D pair lists: the supplementary "Sampling Strategy" sampler, per scene.

  python data/kubric4d/sample_pairs.py --root /data/Kubric-4D/data --split train

For every scene of the split: camera pairs are drawn with weight w(alpha) on their relative
rotation angle alpha (1 + alpha below pi/3, 1 + pi/3 up to pi/2, 0 beyond; distinct cameras),
frame differences 0..40 with probability rising linearly (40 twice as likely as 0), a uniform
valid start frame, the two times assigned to the two cameras in random order; 3600 pairs per
scene by default. Deterministic: scene k uses the random stream (seed, k). Writes
`<root>/pairs_<split>.txt` with lines `scn%05d view0/time0 view1/time1`.

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from ufm_jax import data
from ufm_jax.data.sources import posed, kubric4d


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--root", required=True)
  p.add_argument("--split", default="train", choices=sorted(kubric4d.SPLITS))
  p.add_argument("--pairs_per_scene", type=int, default=3600)
  p.add_argument("--max_frame_difference", type=int, default=40)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", default=None, help="default: <root>/pairs_<split>.txt")
  p.add_argument("--no_progress", action="store_true")
  args = p.parse_args(argv)
  import tqdm
  src = data.get_source("kubric4d", args.root, split=args.split)
  scenes = src.scenes()
  if not scenes:
    raise SystemExit(f"{args.root}: no scn* folders for split {args.split}")
  lines, skipped = [], []
  for scene in tqdm.tqdm(scenes, desc="scenes", disable=args.no_progress):
    try:
      views = src.views(scene)
      metas = [src.metadata(scene, v) for v in views]
    except (OSError, ValueError) as e:
      skipped.append(f"{scene}: {e}")
      continue
    if not views:
      skipped.append(f"{scene}: no scn*_p0_v*.json metadata")
      continue
    c2w = np.stack([m["cam2world"][0] for m in metas])  # GCD's cameras are static
    rng = np.random.default_rng([args.seed, int(scene[3:])])
    n_frames = min(m["num_frames"] for m in metas)
    for v0, t0, v1, t1 in kubric4d.sample_scene_pairs(c2w, n_frames, args.pairs_per_scene, rng,
                                                      args.max_frame_difference):
      lines.append((scene, f"{views[v0]}/{t0}", f"{views[v1]}/{t1}"))
  out = args.out or os.path.join(args.root, f"pairs_{args.split}.txt")
  posed.write_pair_list(out, lines, header=(
      f"Kubric-4D {args.split}: {args.pairs_per_scene} pairs per scene, seed {args.seed}\n"
      "scene view0/time0 view1/time1"))
  for s in skipped:
    print(f"skipped {s}", file=sys.stderr)
  print(f"wrote {len(lines)} pairs to {out} ({len(skipped)} scenes skipped)")
  return out


if __name__ == "__main__":
  main()
