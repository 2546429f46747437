"""ScanNet++ v2 DSLR images with depth rendered from the laser-scan mesh (WAI layout).

The raw release ships fisheye DSLR images and a mesh, no depth; rendering depth needs a mesh
renderer, so root is the output of map-anything's WAI pipeline for ScanNet++ v2 (conversion,
undistortion to PINHOLE, mesh depth rendering; see data/scannetpp/README.md):
  <scene>/scene_meta.json   frames: frame_name, file_path (image), transform_matrix (4x4
                            camera-to-world, OpenCV axes), fl_x, fl_y, cx, cy (per frame or at the
                            top level), and the rendered depth path under `rendered_depth`
                            (or `depth`; default `rendered_depth/<frame_name>.exr`)
  <scene>/images/<frame>.jpg, <scene>/rendered_depth/<frame>.exr (z-depth metres, 0 = hole)
Frames are `frame_name`s. Scenes: all folders with a scene_meta.json, or those listed in
`<root>/scenes_<split>.txt` when present.
Pairs: `<root>/pairs_<split>.txt` from `python data/mine_pairs.py --dataset scannetpp` (all DSLR
pairs of a scene, kept when mutual covisibility > 25%, supplementary "Sampling Strategy").
"""

from __future__ import annotations

import functools
import json
import os

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _official, exr, posed


def read_scene_meta(path: str) -> dict:
  posed.require_file(path, "a WAI scene_meta.json")
  try:
    with open(path) as f:
      meta = json.load(f)
    frames = {fr["frame_name"]: fr for fr in meta["frames"]}
  except (ValueError, KeyError, TypeError) as e:
    raise ValueError(f"{path}: malformed scene_meta.json (expected 'frames' with "
                     f"'frame_name' entries): {e}") from e
  return dict(meta=meta, frames=frames)


def wai_view(scene_dir: str, meta: dict, frame: dict, depth_keys=("rendered_depth", "depth")):
  where = os.path.join(scene_dir, "scene_meta.json")
  conv = meta.get("camera_convention", "opencv")
  if conv != "opencv":
    raise ValueError(f"{where}: camera_convention {conv!r}, expected 'opencv'")
  get = lambda k: frame[k] if k in frame else meta[k]
  try:
    K = np.array([[get("fl_x"), 0, get("cx")], [0, get("fl_y"), get("cy")], [0, 0, 1]], np.float64)
    c2w = np.array(frame["transform_matrix"], np.float64)
  except KeyError as e:
    raise ValueError(f"{where}: frame {frame.get('frame_name')} lacks {e}") from e
  image = io.read_image(os.path.join(scene_dir, frame.get("file_path", frame.get("image", ""))))
  rel = next((frame[k] for k in depth_keys if isinstance(frame.get(k), str)), None)
  rel = rel or os.path.join(depth_keys[0], f"{frame['frame_name']}.exr")
  depth = posed.sanitize_depth(exr.read_exr(os.path.join(scene_dir, rel)))
  return posed.View(image, depth, K, c2w)


class WaiScenes:
  """Scenes and frames of a WAI tree (one `scene_meta.json` per scene folder)."""

  def wai_scenes(self):
    return sorted(s for s in os.listdir(self.root)
                  if os.path.isfile(os.path.join(self.root, s, "scene_meta.json")))

  @functools.lru_cache(maxsize=64)
  def _meta(self, scene):
    return read_scene_meta(os.path.join(self.root, scene, "scene_meta.json"))

  def frames(self, scene):
    return list(self._meta(scene)["frames"])


@register("scannetpp")
class ScanNetPP(WaiScenes, posed.PosedPairSource):
  name = "scannetpp"
  has_backward = False
  static_scene = True

  def scenes(self):
    listed = os.path.join(self.root, f"scenes_{self.split}.txt")
    if os.path.isfile(listed):
      with open(listed) as f:
        return [l.strip() for l in f if l.strip()]
    return self.wai_scenes()

  def load_view(self, scene, frame):
    m = self._meta(scene)
    if frame not in m["frames"]:
      raise KeyError(f"{os.path.join(self.root, scene, 'scene_meta.json')}: no frame {frame!r}")
    return wai_view(os.path.join(self.root, scene), m["meta"], m["frames"][frame])


# ------------------------------------------------------------------------ official processed layout

@register("scannetpp_official")
class ScanNetPPProcessed(_official.OfficialPosed, posed.PosedPairSource):
  """ScanNet++ v2 as UFM's `preprocess_datasets/preprocess_scannetpp.py` writes it (AnyMap pairs,
  DSLR images undistorted and rescaled, depth rendered from the mesh), read like the official
  `uniflowmatch.datasets.ScanNetpp`. Root = the folder holding all_metadata.npz
  (`scannetpp_anymap_processed/train` in the official data root):
    all_metadata.npz   scenes, sceneids (per image), images (basenames), intrinsics (per image,
                       3x3 OpenCV), trajectories (per image, 4x4 camera-to-world OpenCV),
                       pairs (N, >= 2) global image indices
    <scene>/images/<basename>.jpg, <scene>/depth/<basename>.png (uint16 millimetres, 0 = none)
  Split as the official: the first int(0.95 N) pairs are train, the rest val. A pair's frames
  are global image indices; scene = the first image's scene."""

  name = "scannetpp"
  has_backward = False
  static_scene = True

  @functools.cached_property
  def metadata(self):
    m = _official.load_npz(os.path.join(self.root, "all_metadata.npz"),
                           ("scenes", "sceneids", "images", "intrinsics", "trajectories", "pairs"))
    n = len(m["images"])
    for k in ("sceneids", "intrinsics", "trajectories"):
      if len(m[k]) != n:
        raise ValueError(f"{self.root}/all_metadata.npz: {k} has {len(m[k])} entries, images {n}")
    return m

  def _official_pairs(self):
    pairs = np.asarray(self.metadata["pairs"])
    if pairs.ndim != 2 or pairs.shape[1] < 2:
      raise ValueError(f"{self.root}/all_metadata.npz: pairs must be (N, >= 2), got {pairs.shape}")
    pairs = pairs[:, :2].astype(np.int64)
    n_train = int(0.95 * len(pairs))
    pairs = pairs[:n_train] if self.split == "train" else pairs[n_train:]
    scenes, sceneids = self.metadata["scenes"], self.metadata["sceneids"]
    return [(str(scenes[sceneids[a]]), str(a), str(b)) for a, b in pairs]

  def scenes(self):
    return [str(s) for s in self.metadata["scenes"]]

  def frames(self, scene):
    m = self.metadata
    return [str(i) for i in np.flatnonzero(m["scenes"][m["sceneids"]] == scene)]

  def load_view(self, scene, frame):
    m, i = self.metadata, int(frame)
    if not 0 <= i < len(m["images"]):
      raise ValueError(f"{self.root}/all_metadata.npz: image index {i} out of range")
    d = os.path.join(self.root, str(m["scenes"][m["sceneids"][i]]))
    base = str(m["images"][i])
    image = io.read_image(os.path.join(d, "images", base + ".jpg"))
    depth = posed.sanitize_depth(io.read_png_depth16(os.path.join(d, "depth", base + ".png"),
                                                     1000.0))
    K = np.asarray(m["intrinsics"][i], np.float32).astype(np.float64)
    c2w = np.asarray(m["trajectories"][i], np.float32).astype(np.float64)
    return posed.check_view(posed.View(image, depth, K, c2w), os.path.join(d, base))
