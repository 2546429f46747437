"""StaticThings3D (robustmvd release): static FlyingThings-like scenes with depth and poses.

Layout under root (robustmvd's download script unpacked, see data/staticthings/README.md):
  frames_<clean|final>pass/TRAIN/<A|B|C>/<seq>/<left|right>/{%04d}.png
  depths/TRAIN/<A|B|C>/<seq>/<left|right>/{%04d}.float3      z-depth, scene units
  poses/TRAIN/<A|B|C>/<seq>/<left|right>/{%04d}.float3       4x4 world-to-camera
  intrinsics/TRAIN/<A|B|C>/<seq>/{%04d}.float3               3x3
(LMB .float3: 'float', ndim, dims fastest-varying first, raw little-endian float32.)
Scene = `TRAIN/<letter>/<seq>`, frame = `<left|right>/<%04d>`. `split` picks TRAIN or TEST.
Pairs: `<root>/pairs_<split>.txt`, else DUSt3R's `staticthings_pairs.npy` at root (rows scene
letter, seq, cam1, im1, cam2, im2), else all pairs of the (camera, frame) views of a sequence.
`frames_pass` selects clean or final renderings; `max_depth` (DUSt3R's mask_bg uses 200) zeroes
the far background when set.
"""

from __future__ import annotations

import itertools
import os

import numpy as np

from ufm_jax.data.registry import register
from ufm_jax.data import io
from ufm_jax.data.sources import posed

_CAMS = {"l": "left", "r": "right", b"l": "left", b"r": "right"}


@register("staticthings")
class StaticThings(posed.PosedPairSource):
  name = "staticthings"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="train", pairs=None, thresholds=None, frames_pass="final",
               max_depth=None):
    super().__init__(root, split, pairs, thresholds)
    if frames_pass not in ("clean", "final"):
      raise ValueError(f"staticthings: frames_pass must be 'clean' or 'final', got {frames_pass!r}")
    self.frames_pass = frames_pass
    self.max_depth = max_depth
    self.part = "TEST" if split == "test" else "TRAIN"

  def scenes(self):
    base = posed.require_dir(os.path.join(self.root, f"frames_{self.frames_pass}pass", self.part),
                              f"frames_{self.frames_pass}pass/{self.part}/<A|B|C>/<seq>/")
    return [f"{self.part}/{l}/{s}" for l in sorted(os.listdir(base))
            for s in sorted(os.listdir(os.path.join(base, l)))]

  def frames(self, scene):
    out = []
    for cam in ("left", "right"):
      d = os.path.join(self.root, f"frames_{self.frames_pass}pass", scene, cam)
      if os.path.isdir(d):
        out += [f"{cam}/{f[:-4]}" for f in sorted(os.listdir(d)) if f.endswith(".png")]
    return out

  def default_pairs(self):
    npy = os.path.join(self.root, "staticthings_pairs.npy")
    if os.path.isfile(npy):
      for scene, seq, cam1, im1, cam2, im2 in np.load(npy):
        letter = scene.decode() if isinstance(scene, bytes) else str(scene)
        yield (f"{self.part}/{letter}/{int(seq):04d}", f"{_CAMS[cam1]}/{int(im1):04d}",
               f"{_CAMS[cam2]}/{int(im2):04d}")
      return
    for scene in self.scenes():
      for a, b in itertools.combinations(self.frames(scene), 2):
        yield scene, a, b

  def load_view(self, scene, frame):
    cam, idx = frame.split("/")
    image = io.read_image(os.path.join(self.root, f"frames_{self.frames_pass}pass", scene,
                                           cam, f"{idx}.png"))
    depth = posed.sanitize_depth(io.read_float3(
        os.path.join(self.root, "depths", scene, cam, f"{idx}.float3")))
    if self.max_depth is not None:
      depth[depth > self.max_depth] = 0
    w2c = io.read_float3(os.path.join(self.root, "poses", scene, cam, f"{idx}.float3"))
    K = io.read_float3(os.path.join(self.root, "intrinsics", scene, f"{idx}.float3"))
    if w2c.shape != (4, 4) or K.shape != (3, 3):
      raise ValueError(f"{os.path.join(self.root, 'poses', scene, cam, idx)}: expected a 4x4 pose "
                       f"and 3x3 intrinsics, got {w2c.shape} and {K.shape}")
    return posed.View(image, depth, K.astype(np.float64), np.linalg.inv(w2c.astype(np.float64)))
