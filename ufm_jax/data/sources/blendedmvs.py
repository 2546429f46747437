"""BlendedMVS (raw low-res release + BlendedMVS+/++), depth-derived flow and covisibility.

Layout under root (as unpacked from the official archives, see data/blendedmvs/README.md):
  <scene: 24 hex chars>/blended_images/{%08d}.jpg      (not the *_masked.jpg)
  <scene>/cams/{%08d}_cam.txt                         MVSNet format, extrinsic = world-to-camera
  <scene>/cams/pair.txt                               MVSNet view selection
  <scene>/rendered_depth_maps/{%08d}.pfm              z-depth, scene units, 0 = invalid
Split (DUSt3R): val = scenes whose last 16 hex digits (seq_low) % 10 == 0, train = the rest.
Pairs: `<root>/pairs_<split>.txt` if present; else DUSt3R's `blendedmvs_pairs.npy` at root
(fields seq_high, seq_low, img1, img2); else every (reference, source) entry of each scene's
cams/pair.txt (MVSNet's top-10 neighbours by SfM score).
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data.registry import register
from ufm_jax.data import io
from ufm_jax.data.sources import _official, posed


def _is_scene(name: str) -> bool:
  return len(name) == 24 and all(c in "0123456789abcdefABCDEF" for c in name)


def _in_split(scene: str, split: str) -> bool:
  if split in (None, "all"):
    return True
  is_val = int(scene[8:], 16) % 10 == 0
  return is_val if split == "val" else not is_val


@register("blendedmvs")
class BlendedMVS(posed.PosedPairSource):
  name = "blendedmvs"
  has_backward = False
  static_scene = True

  def scenes(self):
    return sorted(s for s in os.listdir(self.root)
                  if _is_scene(s) and os.path.isdir(os.path.join(self.root, s))
                  and _in_split(s, self.split))

  def frames(self, scene):
    d = posed.require_dir(os.path.join(self.root, scene, "blended_images"), "blended_images/")
    return sorted(f[:-4] for f in os.listdir(d) if f.endswith(".jpg") and "_masked" not in f)

  def default_pairs(self):
    npy = os.path.join(self.root, "blendedmvs_pairs.npy")
    if os.path.isfile(npy):
      arr = np.load(npy)
      for row in arr:
        scene = f"{int(row['seq_high']):08x}{int(row['seq_low']):016x}"
        if _in_split(scene, self.split):
          yield scene, f"{int(row['img1']):08d}", f"{int(row['img2']):08d}"
      return
    scenes = self.scenes()
    if not scenes:
      raise FileNotFoundError(f"{self.root}: no BlendedMVS scene folders (24 hex characters) for "
                              f"split {self.split!r}")
    for scene in scenes:
      table = posed.read_mvsnet_pairs(os.path.join(self.root, scene, "cams", "pair.txt"))
      for ref, srcs in table.items():
        for src in srcs:
          yield scene, f"{ref:08d}", f"{src:08d}"

  def load_view(self, scene, frame):
    d = os.path.join(self.root, scene)
    w2c, K = posed.read_mvsnet_cam(os.path.join(d, "cams", f"{frame}_cam.txt"))
    depth = posed.sanitize_depth(io.read_pfm(
        os.path.join(d, "rendered_depth_maps", f"{frame}.pfm")))
    image = io.read_image(os.path.join(d, "blended_images", f"{frame}.jpg"))
    return posed.View(image, depth, K, np.linalg.inv(w2c))


# ------------------------------------------------------------------------ official processed layout

# Sequences the official reader leaves out (uniflowmatch/datasets/utils/blendedmvs_module.py:
# `all_sequences` minus `sequences`: wrong or noisy depth); it matches pairs on seq_low only.
EXCLUDED_SEQUENCES = (
    "000000000000000000000000", "00000000000000000000000c", "00000000000000000000001a",
    "5692a4c2adafac1f14201821", "5864a935712e2761469111b4", "58a44463156b87103d3ed45e",
    "59f87d0bfa6280566fb38c9a", "5bf03590d4392319481971dc", "5c2b3ed5e611832e8aed46bf")
PAIRS_FILE = "blendedmvs_pairs.npy"


@register("blendedmvs_official")
class BlendedMVSProcessed(_official.OfficialPosed, posed.PosedPairSource):
  """BlendedMVS as DUSt3R's preprocessing (or the UFM data mirror's `blendedmvs_processed.zip`)
  leaves it, read like the official `uniflowmatch.datasets.BlendedMVS`:
    <root>/<seq>/%08d.jpg   RGB, %08d.exr   float32 z-depth, %08d.npz   intrinsics (3x3, OpenCV),
    R_cam2world, t_cam2world
    pairs: dust3r_data_pairs/blendedmvs_pairs.npy (fields seq_high, seq_low, img1, img2, score)
  Split as DUSt3R: val = seq_low % 10 == 0; the official's excluded sequences are dropped, and so
  (logged) are pairs whose sequence folder is absent. Camera pose is float32 as the official."""

  name = "blendedmvs"
  has_backward = False
  static_scene = True
  suitable_for_refinement = True

  pairs_file = PAIRS_FILE

  def _official_pairs(self):
    arr = _official.load_npy(self.pairs_path)
    names = arr.dtype.names or ()
    missing = [f for f in ("seq_high", "seq_low", "img1", "img2") if f not in names]
    if missing:
      raise ValueError(f"{self.pairs_path}: pair array lacks fields {missing} (has "
                       f"{arr.dtype.names})")
    low = arr["seq_low"].astype(np.uint64)
    keep = np.ones(len(arr), bool) if self.split in (None, "all") else (
        (low % 10 == 0) if self.split == "val" else (low % 10 > 0))
    keep &= ~np.isin(low, [np.uint64(int(s[8:], 16)) for s in EXCLUDED_SEQUENCES])
    present = set(os.listdir(self.root))
    out, absent = [], set()
    for row in arr[keep]:
      scene = f"{int(row['seq_high']):08x}{int(row['seq_low']):016x}"
      if scene in present:
        out.append((scene, f"{int(row['img1']):08d}", f"{int(row['img2']):08d}"))
      else:
        absent.add(scene)
    if absent:
      _official.log.warning(
          "%s: %d sequences of %s are not on disk; their pairs are left out (e.g. %s)", self.root,
          len(absent), self.pairs_path, sorted(absent)[0])
    return out

  def scenes(self):
    return sorted(s for s in os.listdir(self.root) if _is_scene(s) and _in_split(s, self.split))

  def frames(self, scene):
    d = posed.require_dir(os.path.join(self.root, scene), "a processed BlendedMVS sequence")
    return sorted(f[:-4] for f in os.listdir(d) if f.endswith(".npz"))

  def load_view(self, scene, frame):
    stem = os.path.join(self.root, scene, frame)
    return _official.processed_view(stem, (("intrinsics",), ("R_cam2world", "t_cam2world")))
