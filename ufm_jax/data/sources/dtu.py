"""DTU MVS benchmark (MVSNet/PatchmatchNet full-resolution release) as a dense-correspondence
benchmark: flow and covisibility from the GT depth maps and cameras.

Layout under root (see data/dtu/README.md):
  Rectified/scan<N>/rect_{view+1:03d}_{light}_r5000.png   1600x1200 (view 1-based in the name)
  Cameras/{view:08d}_cam.txt                              MVSNet format (w2c, millimetres)
  Cameras/pair.txt                                        MVSNet view selection
  Depths_raw/scan<N>/depth_map_{view:04d}.pfm             z-depth in millimetres, 0/nan = none
Everything is returned in metres (depth and camera translation / 1000). Images and depth maps
must have the same size (the full-resolution Depths_raw). Scene = `scan<N>`, frame = view index.
Pairs: `<root>/pairs_<split>.txt` (e.g. from data/dtu/prepare.py: every covisible view pair of
the evaluation scans), else for the 22 MVSNet evaluation scans (split 'test') every (reference,
source) entry among the top `num_src` of Cameras/pair.txt. Lighting index `light` (default 3).

`dtu_official` reads the benchmark branch's own data instead (official download scripts
download_dtu_processed.sh + download_pairs_eth3d_dtu.sh; uniflowmatch/datasets/dtu.py), in
millimetres as the branch keeps it:
  <root>/scan<N>/images/<view>.png                    600x450, lighting 3 (`dtu_processed/`)
  <root>/scan<N>/depths/<view>.npy                    z-depth mm, 0 = none
  <root>/scan<N>/camera_params/<view>_intrinsics.npy  3x3 K
  <root>/scan<N>/poses/<view>.npy                     4x4 world-to-camera (mm)
  <root>/../anymap_data_pairs/dtu_valid_pairs.npz     rows (scene, view0, view1, score)
and scores every 50th pair on the 560x420 crop with the branch's labels
(widebaseline_datasets.py:146-170; see ufm_jax/data/sources/_benchmark_branch.py).
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _benchmark_branch, posed
from ufm_jax.geometry.benchmark_labels import BRANCH_THRESHOLDS

EVAL_SCANS = (1, 4, 9, 10, 11, 12, 13, 15, 23, 24, 29, 32, 33, 34, 48, 49, 62, 75, 77, 110, 114,
              118)
VAL_SCANS = (3, 5, 17, 21, 28, 35, 37, 38, 40, 43, 56, 59, 66, 67, 82, 86, 106, 117)


@register("dtu")
class DTU(posed.PosedPairSource):
  name = "dtu"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="test", pairs=None, thresholds=None, light=3, num_src=10):
    super().__init__(root, split, pairs, thresholds)
    self.light = int(light)
    self.num_src = int(num_src)

  def scenes(self):
    base = posed.require_dir(os.path.join(self.root, "Rectified"), "Rectified/scan<N>/")
    present = {s for s in os.listdir(base) if s.startswith("scan")}
    wanted = {"test": EVAL_SCANS, "val": VAL_SCANS}.get(self.split)
    if wanted is None:
      return sorted(present)
    return [f"scan{n}" for n in wanted if f"scan{n}" in present]

  def frames(self, scene):
    d = os.path.join(self.root, "Rectified", scene)
    return sorted({str(int(f[5:8]) - 1) for f in os.listdir(d) if f.startswith("rect_")}, key=int)

  def default_pairs(self):
    scenes = self.scenes()
    if not scenes:
      raise FileNotFoundError(f"{os.path.join(self.root, 'Rectified')}: none of the DTU "
                              f"{self.split} scans present")
    table = posed.read_mvsnet_pairs(os.path.join(self.root, "Cameras", "pair.txt"))
    for scene in scenes:
      for ref, srcs in sorted(table.items()):
        for src in srcs[:self.num_src]:
          yield scene, str(ref), str(src)

  def load_view(self, scene, frame):
    v = int(frame)
    w2c, K = posed.read_mvsnet_cam(os.path.join(self.root, "Cameras", f"{v:08d}_cam.txt"))
    c2w = np.linalg.inv(w2c)
    c2w[:3, 3] /= 1000.0
    image = io.read_image(os.path.join(self.root, "Rectified", scene,
                                           f"rect_{v + 1:03d}_{self.light}_r5000.png"))
    depth = posed.sanitize_depth(io.read_pfm(
        os.path.join(self.root, "Depths_raw", scene, f"depth_map_{v:04d}.pfm")), scale=1e-3)
    return posed.View(image, depth, K, c2w)


@register("dtu_official")
class DTUOfficial(_benchmark_branch.BranchPosedPairs):
  """The benchmark branch's DTU dense bench (module docstring): `[::50]` of the AnyMap pairs,
  labels in millimetres with (a, T, r) = (12, 12, 0.01): tau = 20.318 mm + 0.01 d."""

  name = "dtu_official"
  pairs_file = "dtu_valid_pairs.npz"
  stride = 50
  thresholds = BRANCH_THRESHOLDS["dtu"]

  def load_view(self, scene, view):
    d = os.path.join(self.root, scene)
    image = io.read_image(os.path.join(d, "images", view + ".png"))
    depth = _benchmark_branch.load_npy(os.path.join(d, "depths", view + ".npy"),
                                       "an [H, W] z-depth map (mm)", image.shape[:2])
    K = _benchmark_branch.load_npy(os.path.join(d, "camera_params", view + "_intrinsics.npy"),
                                   "a 3x3 intrinsic matrix", (3, 3))
    w2c = _benchmark_branch.load_npy(os.path.join(d, "poses", view + ".npy"),
                                     "a 4x4 world-to-camera pose (mm)", (4, 4))
    return image, depth.astype(np.float32), K, w2c
