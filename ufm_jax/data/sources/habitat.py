"""Habitat renderings as produced by DUSt3R's habitat preprocessing (5 views per key).

Layout under root (DUSt3R's `data/habitat_processed`, see data/habitat/README.md):
  <scene path>/<key>_<i>.jpeg                  i = 1..5, 512x512 RGB
  <scene path>/<key>_<i>_depth.exr             float16 z-depth in metres
  <scene path>/<key>_<i>_camera_params.json    camera_intrinsics (3x3, OpenCV), R_cam2world,
                                               t_cam2world (camera-to-world, OpenCV axes)
Scene = the folder path relative to root; frame = `<key>_<i>`. Scenes are the folders holding
`*_1.jpeg`, or those listed in `<root>/scenes_<split>.txt` when present (DUSt3R's
Habitat_*_scenes_<split>.txt lists can be copied there).
Pairs: `<root>/pairs_<split>.txt`, else DUSt3R's rule made exhaustive: view 1 of each key overlaps
all others, so (key_1, key_j) for j = 2..5. Views with non-finite poses are skipped.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _official, exr, posed


def read_camera_params(path):
  posed.require_file(path, "a Habitat camera_params.json")
  try:
    with open(path) as f:
      p = json.load(f)
    K = np.array(p["camera_intrinsics"], np.float64).reshape(3, 3)
    c2w = np.eye(4)
    c2w[:3, :3] = np.array(p["R_cam2world"], np.float64).reshape(3, 3)
    c2w[:3, 3] = np.array(p["t_cam2world"], np.float64).reshape(3)
  except (ValueError, KeyError, TypeError) as e:
    raise ValueError(f"{path}: malformed camera params (expected camera_intrinsics, "
                     f"R_cam2world, t_cam2world): {e}") from e
  return K, c2w


@register("habitat")
class Habitat(posed.PosedPairSource):
  name = "habitat"
  has_backward = False
  static_scene = True

  def scenes(self):
    listed = os.path.join(self.root, f"scenes_{self.split}.txt")
    if os.path.isfile(listed):
      with open(listed) as f:
        return [l.strip() for l in f if l.strip()]
    out = []
    for d, _, files in os.walk(self.root):
      if any(f.endswith("_1.jpeg") for f in files):
        out.append(os.path.relpath(d, self.root))
    return sorted(out)

  def frames(self, scene):
    d = os.path.join(self.root, scene)
    return sorted(f[:-5] for f in os.listdir(d) if f.endswith(".jpeg"))

  def default_pairs(self):
    scenes = self.scenes()
    if not scenes:
      raise FileNotFoundError(f"{self.root}: no Habitat renderings (<key>_1.jpeg files)")
    for scene in scenes:
      d = posed.require_dir(os.path.join(self.root, scene), "a Habitat scene folder")
      files = set(os.listdir(d))
      for f in sorted(files):
        if not f.endswith("_1.jpeg"):
          continue
        key = f[:-len("_1.jpeg")]
        for j in range(2, 6):
          if f"{key}_{j}.jpeg" in files:
            yield scene, f"{key}_1", f"{key}_{j}"

  def load_view(self, scene, frame):
    d = os.path.join(self.root, scene)
    K, c2w = read_camera_params(os.path.join(d, f"{frame}_camera_params.json"))
    if not np.isfinite(c2w).all():
      raise ValueError(f"{os.path.join(d, frame)}_camera_params.json: non-finite pose")
    image = io.read_image(os.path.join(d, f"{frame}.jpeg"))
    depth = posed.sanitize_depth(exr.read_exr(os.path.join(d, f"{frame}_depth.exr")))
    return posed.View(image, depth, K, c2w)


# ------------------------------------------------------------------------ official processed layout

@register("habitat_official")
class HabitatProcessed(_official.OfficialPosed, posed.PosedPairSource):
  """Habitat as the official `uniflowmatch.datasets.Habitat` reads it: DUSt3R's Habitat renders of
  ReplicaCAD only, root `habitat_processed/replica_cad_baked_lighting` holding
    Habitat_<size>_scenes_<split>.txt   one `<dir>/<key>` per line (size 35000 for train)
    <dir>/<key>_<i>.jpeg, <key>_<i>_depth.exr, <key>_<i>_camera_params.json, i = 1..5
  The official pairs view 1 of a key with one of views 2..5 drawn at random; here each of the four
  is its own pair (key-major), so a uniform draw sees each with the official probability. The
  principal point is the official's: camera_intrinsics with 0.5 subtracted from cx, cy (DUSt3R
  renders store it in the corner-origin pixel frame)."""

  name = "habitat"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="train", pairs=None, thresholds=None, size=35000,
               views=(2, 3, 4, 5)):
    super().__init__(root, split, pairs, thresholds)
    self.size, self.views = size, tuple(views)

  def _official_pairs(self):
    path = posed.require_file(
        os.path.join(self.root, f"Habitat_{self.size}_scenes_{self.split}.txt"),
        "the official Habitat scene list (`<dir>/<key>` per line)")
    with open(path) as f:
      keys = [l.strip() for l in f if l.strip()]
    for line in keys:
      scene, key = os.path.split(line)
      for j in self.views:
        yield scene, f"{key}_1", f"{key}_{j}"

  def load_view(self, scene, frame):
    d = os.path.join(self.root, scene)
    K, c2w = read_camera_params(os.path.join(d, f"{frame}_camera_params.json"))
    if not np.isfinite(c2w).all():
      raise ValueError(f"{os.path.join(d, frame)}_camera_params.json: non-finite pose")
    K = K.astype(np.float32)
    K[:2, 2] -= 0.5
    image = io.read_image(os.path.join(d, f"{frame}.jpeg"))
    depth = posed.sanitize_depth(exr.read_exr(os.path.join(d, f"{frame}_depth.exr")))
    return posed.check_view(posed.View(image, depth, K.astype(np.float64),
                                       c2w.astype(np.float32).astype(np.float64)),
                            os.path.join(d, frame))
