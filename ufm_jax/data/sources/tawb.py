"""TA-WB (TartanAir V2 wide-baseline pairs, UFM's benchmark / training pairs), extracted layout.

Layout under root (written by data/tawb/prepare.py from the Hugging Face release
`infinity1096/TA-WB-MapAnything`, or by the geometric sampler data/tawb/sample_pairs.py):
  <split>/<Env>/images/{pair:08d}_{view}.png          view in {0, 1}, RGB
  <split>/<Env>/depth/{pair:08d}_{view}.exr           z-depth metres, 0 = invalid (sky masked)
  <split>/<Env>/camera_params/{pair:08d}_{view}.npy   3x3 K (OpenCV)
  <split>/<Env>/poses/{pair:08d}_{view}.npy           4x4 camera-to-world (OpenCV)
Scene = Env, frame = `{pair:08d}_{view}`. Pairs: `<root>/pairs_<split>.txt` when present, else
every pair index with both views (the release's fixed pair list). Thresholds: TartanAir's row of
Table S1. `percentile_cut` (map-anything zeroes depth above the 95th percentile per image to drop
windows; default None = keep) is available for parity with that loader.
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import exr, posed


def _load_npy(path, shape, what):
  posed.require_file(path, what)
  try:
    arr = np.load(path)
  except ValueError as e:
    raise ValueError(f"{path}: not a .npy array ({e})") from e
  if arr.shape != shape:
    raise ValueError(f"{path}: expected shape {shape} ({what}), got {arr.shape}")
  return arr.astype(np.float64)


@register("tawb")
class TAWB(posed.PosedPairSource):
  name = "tawb"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="test", pairs=None, thresholds=None, percentile_cut=None):
    super().__init__(root, split, pairs, thresholds)
    self.base = os.path.join(self.root, split)
    self.percentile_cut = percentile_cut

  def scenes(self):
    posed.require_dir(self.base, f"the TA-WB {self.split}/<Env>/ folders")
    return sorted(e for e in os.listdir(self.base)
                  if os.path.isdir(os.path.join(self.base, e, "images")))

  def frames(self, scene):
    return sorted(f[:-4] for f in os.listdir(os.path.join(self.base, scene, "images"))
                  if f.endswith(".png"))

  def default_pairs(self):
    scenes = self.scenes()
    if not scenes:
      raise FileNotFoundError(f"{self.base}: no TA-WB environments (<Env>/images/)")
    for env in scenes:
      names = set(self.frames(env))
      for n in sorted(names):
        if n.endswith("_0") and n[:-2] + "_1" in names:
          yield env, n, n[:-2] + "_1"

  def load_view(self, scene, frame):
    d = os.path.join(self.base, scene)
    image = io.read_image(os.path.join(d, "images", f"{frame}.png"))
    depth = posed.sanitize_depth(exr.read_exr(os.path.join(d, "depth", f"{frame}.exr")))
    if self.percentile_cut is not None and (depth > 0).any():
      depth[depth > np.percentile(depth[depth > 0], self.percentile_cut)] = 0
    K = _load_npy(os.path.join(d, "camera_params", f"{frame}.npy"), (3, 3), "3x3 intrinsics")
    c2w = _load_npy(os.path.join(d, "poses", f"{frame}.npy"), (4, 4), "4x4 camera-to-world")
    return posed.View(image, depth, K, c2w)
