"""ETH3D high-res multi-view (training scenes) as a dense-correspondence benchmark.

The official GT depth is aligned with the distorted DSLR images (THIN_PRISM_FISHEYE) and is
6048x4032 raw float32; `python data/eth3d/prepare.py` resamples it into the undistorted PINHOLE
geometry (optionally downscaled) and writes a WAI-style tree, which is what this reader reads:
  <scene>/scene_meta.json   frames with file_path, depth, transform_matrix (c2w, OpenCV), fl_x,
                            fl_y, cx, cy (OpenCV pixel-centre convention)
  <scene>/images/<DSC_xxxx>.jpg, <scene>/depth/<DSC_xxxx>.exr (z-depth, metres, 0 = none)
Pairs: `<root>/pairs_test.txt` (written by the preparation tool: every view pair of a scene with
mutual covisibility above its --min_covis). See data/eth3d/README.md.

`eth3d_official` reads the benchmark branch's own data instead (official download scripts
download_eth3d_processed.sh + download_pairs_eth3d_dtu.sh; uniflowmatch/datasets/eth3d.py):
  <root>/<scene>/undistorted_images/<view>.jpg        600x400 (the tree `eth3d_processed/`)
  <root>/<scene>/undistorted_depths/<view>.npy        z-depth metres, 0 = none
  <root>/<scene>/undistorted_camera_params/<view>.npy fx, fy, cx, cy (used as an OpenCV K)
  <root>/<scene>/poses/<view>.npy                     4x4 world-to-camera
  <root>/../anymap_data_pairs/eth3d_valid_pairs.npz   rows (scene, view0, view1, score)
and scores every third pair on the 560x420 crop with the branch's labels
(widebaseline_datasets.py:112-128; see ufm_jax/data/sources/_benchmark_branch.py).
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _benchmark_branch, posed
from ufm_jax.geometry.benchmark_labels import BRANCH_THRESHOLDS
from ufm_jax.data.sources.scannetpp import WaiScenes, wai_view


@register("eth3d")
class ETH3D(WaiScenes, posed.PosedPairSource):
  name = "eth3d"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="test", pairs=None, thresholds=None):
    super().__init__(root, split, pairs, thresholds)

  def scenes(self):
    return self.wai_scenes()

  def default_pairs(self):
    raise FileNotFoundError(
        f"{os.path.join(self.root, f'pairs_{self.split}.txt')}: missing ETH3D pair list; build the "
        "tree and the list with `python data/eth3d/prepare.py` (see data/eth3d/README.md)")

  def load_view(self, scene, frame):
    m = self._meta(scene)
    if frame not in m["frames"]:
      raise KeyError(f"{os.path.join(self.root, scene, 'scene_meta.json')}: no frame {frame!r}")
    return wai_view(os.path.join(self.root, scene), m["meta"], m["frames"][frame],
                    depth_keys=("depth",))


@register("eth3d_official")
class ETH3DOfficial(_benchmark_branch.BranchPosedPairs):
  """The benchmark branch's ETH3D dense bench (module docstring): `[::3]` of the AnyMap pairs,
  labels with (a, T, r) = (0.1 m, 0.1 m, 0.005): tau = 0.169 m + 0.005 d."""

  name = "eth3d_official"
  pairs_file = "eth3d_valid_pairs.npz"
  stride = 3
  thresholds = BRANCH_THRESHOLDS["eth3d"]

  def load_view(self, scene, view):
    d = os.path.join(self.root, scene)
    image = io.read_image(os.path.join(d, "undistorted_images", view + ".jpg"))
    depth = _benchmark_branch.load_npy(os.path.join(d, "undistorted_depths", view + ".npy"),
                                       "an [H, W] z-depth map", image.shape[:2])
    fx, fy, cx, cy = _benchmark_branch.load_npy(
        os.path.join(d, "undistorted_camera_params", view + ".npy"), "fx, fy, cx, cy", (4,))
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float32)
    w2c = _benchmark_branch.load_npy(os.path.join(d, "poses", view + ".npy"),
                                     "a 4x4 world-to-camera pose", (4, 4))
    return image, depth.astype(np.float32), K, w2c
