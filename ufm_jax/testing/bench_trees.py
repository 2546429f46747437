"""Tiny trees in the benchmark datasets' own layouts, for the evaluate.py tests.

Sintel (MPI-Sintel-complete) and KITTI-2015 (data_scene_flow) with random content; the wide-
baseline layouts are in `wide_trees`.
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data import io


def write_sintel(root, h=28, w=42, frames=3, scene="alley_1"):
  rng = np.random.default_rng(0)
  tr = os.path.join(root, "training")
  for sub in ("clean", "final", "flow", "occlusions", "invalid"):
    os.makedirs(os.path.join(tr, sub, scene))
  for k in range(1, frames + 1):
    for p in ("clean", "final"):
      io.write_image(os.path.join(tr, p, scene, f"frame_{k:04d}.png"),
                     rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    if k < frames:
      io.write_flo(os.path.join(tr, "flow", scene, f"frame_{k:04d}.flo"),
                   rng.normal(0, 3, (h, w, 2)).astype(np.float32))
      occ = np.zeros((h, w), bool)
      occ[:, :5] = True
      io.write_mask(os.path.join(tr, "occlusions", scene, f"frame_{k:04d}.png"), occ)
      io.write_mask(os.path.join(tr, "invalid", scene, f"frame_{k:04d}.png"), np.zeros((h, w), bool))


def write_kitti(root, h=30, w=50, n=2):
  rng = np.random.default_rng(1)
  tr = os.path.join(root, "training")
  for sub in ("image_2", "flow_occ", "flow_noc", "obj_map"):
    os.makedirs(os.path.join(tr, sub))
  for i in range(n):
    for f in (10, 11):
      io.write_image(os.path.join(tr, "image_2", f"{i:06d}_{f}.png"),
                     rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    flow = rng.normal(0, 20, (h, w, 2)).astype(np.float32)
    valid = rng.random((h, w)) < 0.6
    io.write_kitti_flow(os.path.join(tr, "flow_occ", f"{i:06d}_10.png"), flow, valid)
    io.write_kitti_flow(os.path.join(tr, "flow_noc", f"{i:06d}_10.png"), flow, valid & (rng.random((h, w)) < 0.8))
    obj = np.zeros((h, w), np.uint8)
    obj[10:20, 10:30] = 1
    io.write_image(os.path.join(tr, "obj_map", f"{i:06d}_10.png"), np.repeat(obj[..., None], 3, -1))
