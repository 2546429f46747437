"""ScanNet-1500: check the tree the `scannet1500` source reads, or build its pair list from
LoFTR's copy of the split.

  python data/scannet1500/prepare.py --root /data/scannet1500                 # check only
  python data/scannet1500/prepare.py --root /data/scannet1500 \
      --loftr_npz LoFTR/assets/scannet_test_1500/test.npz \
      --loftr_intrinsics LoFTR/assets/scannet_test_1500/intrinsics.npz         # write the list

The list is SuperGlue's `assets/scannet_test_pairs_with_gt.txt` (copy it to <root>). LoFTR's
`test.npz` holds the same 1500 pairs (`name` = scene id, sub id, frame A, frame B; `rel_pose` =
row-major 3x4 [R|t], camera A -> camera B) and `intrinsics.npz` K per scene at 640x480; the
conversion scales K back to the 1296x968 colour images SuperGlue's list refers to. The check
resolves every image the way the source does and reports the missing ones.

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from ufm_jax import data
from ufm_jax.data.sources import posed, scannet1500


def loftr_to_superglue(npz_path, intr_path, out_path):
  posed.require_file(npz_path, "LoFTR's scannet_test_1500/test.npz")
  posed.require_file(intr_path, "LoFTR's scannet_test_1500/intrinsics.npz")
  z, intr = np.load(npz_path), np.load(intr_path)
  if "name" not in z or "rel_pose" not in z:
    raise ValueError(f"{npz_path}: expected arrays 'name' and 'rel_pose'")
  sx, sy = scannet1500.ORIGINAL_WH[0] / 640, scannet1500.ORIGINAL_WH[1] / 480
  lines = []
  for (sid, sub, fa, fb), rel in zip(z["name"], z["rel_pose"]):
    scene = f"scene{int(sid):04d}_{int(sub):02d}"
    if scene not in intr:
      raise KeyError(f"{intr_path}: no intrinsics for {scene}")
    K = np.array(intr[scene], np.float64).reshape(3, 3).copy()
    K[0] *= sx
    K[1] *= sy
    T = np.eye(4)
    T[:3] = np.asarray(rel, np.float64).reshape(3, 4)
    nums = np.concatenate([K.ravel(), K.ravel(), T.ravel()])
    lines.append(f"{scene}_frame-{int(fa):06d}.jpg {scene}_frame-{int(fb):06d}.jpg 0 0 "
                 + " ".join(f"{x:.8g}" for x in nums))
  tmp = out_path + ".tmp"
  with open(tmp, "w") as f:
    f.write("\n".join(lines) + "\n")
  os.replace(tmp, out_path)
  return len(lines)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--root", required=True)
  p.add_argument("--loftr_npz", default=None)
  p.add_argument("--loftr_intrinsics", default=None)
  args = p.parse_args(argv)
  posed.require_dir(args.root, "the ScanNet-1500 root")
  if args.loftr_npz:
    n = loftr_to_superglue(args.loftr_npz, args.loftr_intrinsics or "",
                           os.path.join(args.root, scannet1500.PAIRS_FILE))
    print(f"wrote {n} pairs to {os.path.join(args.root, scannet1500.PAIRS_FILE)}")
  src = data.get_source("scannet1500", args.root)
  missing = []
  for pr in src.pairs:
    for k in ("name0", "name1"):
      try:
        src._image_path(pr[k])  # pylint: disable=protected-access
      except FileNotFoundError as e:
        missing.append(str(e))
  for m in missing[:20]:
    print(m, file=sys.stderr)
  print(f"{len(src)} pairs, {len(missing)} missing images")
  return len(src), len(missing)


if __name__ == "__main__":
  main()
