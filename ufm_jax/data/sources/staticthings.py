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
from ufm_jax.data.sources import _official, exr, posed

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


# ------------------------------------------------------------------------ official processed layout

PASSES = ("clean", "final")


@register("staticthings_official")
class StaticThingsProcessed(_official.OfficialPosed, posed.PosedPairSource):
  """StaticThings3D as DUSt3R's preprocessing leaves it (`staticthings3d_processed`), read like
  the official `uniflowmatch.datasets.StaticThings3D`:
    <root>/staticthings_pairs.npy   rows (scene letter, seq, cam1 l|r, im1, cam2 l|r, im2)
    <root>/TRAIN/<A|B|C>/<seq %04d>/<left|right>/%04d_clean.jpg, %04d_final.jpg,
      %04d.exr (float32 z-depth), %04d.npz (intrinsics, cam2world)
  The official draws the clean or the final rendering at random for each view; here every
  combination is its own pair (index = 4 * pair + 2 * pass0 + pass1 over `passes`), and
  `variants` (4) tells the training pipeline that those consecutive indices are one official
  sample, of which each draw takes one at random (`input.draw_variants`). `passes=("final",)`
  keeps one.
  `max_depth` (the official mask_bg, off in the recipes) zeroes depth beyond it."""

  name = "staticthings"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="train", pairs=None, thresholds=None, passes=PASSES,
               max_depth=None):
    super().__init__(root, split, pairs, thresholds)
    bad = [p for p in passes if p not in PASSES]
    if bad or not passes:
      raise ValueError(f"staticthings_official: passes must be a non-empty subset of {PASSES}, "
                       f"got {passes!r}")
    self.passes, self.max_depth = tuple(passes), max_depth

  @property
  def variants(self) -> int:
    """Consecutive indices that are renderings of one official sample (a given `pairs` list
    has none)."""
    return 1 if isinstance(self._pairs_arg, (list, tuple)) else len(self.passes) ** 2

  def _official_pairs(self):
    path = posed.require_file(os.path.join(self.root, "staticthings_pairs.npy"),
                              "DUSt3R's staticthings_pairs.npy")
    for scene, seq, cam1, im1, cam2, im2 in _official.load_npy(path):
      letter = scene.decode() if isinstance(scene, bytes) else str(scene)
      for p0 in self.passes:
        for p1 in self.passes:
          yield (f"TRAIN/{letter}/{int(seq):04d}", f"{_CAMS[cam1]}/{int(im1):04d}_{p0}",
                 f"{_CAMS[cam2]}/{int(im2):04d}_{p1}")

  def load_view(self, scene, frame):
    cam, name = frame.split("/")
    num, dpass = name.split("_")
    d = os.path.join(self.root, scene, cam)
    cam_params = _official.load_npz(os.path.join(d, num + ".npz"), ("intrinsics", "cam2world"))
    image = io.read_image(os.path.join(d, f"{num}_{dpass}.jpg"))
    depth = posed.sanitize_depth(exr.read_exr(os.path.join(d, num + ".exr")))
    if self.max_depth is not None:
      depth[depth > self.max_depth] = 0
    K = np.asarray(cam_params["intrinsics"], np.float64)
    c2w = np.asarray(cam_params["cam2world"], np.float64)
    if K.shape != (3, 3) or c2w.shape != (4, 4):
      raise ValueError(f"{os.path.join(d, num)}.npz: expected 3x3 intrinsics and a 4x4 "
                       f"cam2world, got {K.shape} and {c2w.shape}")
    return posed.check_view(posed.View(image, depth, K, c2w), os.path.join(d, name))
