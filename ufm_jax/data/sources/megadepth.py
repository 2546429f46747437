"""MegaDepth v1 (raw release): depth h5 + COLMAP poses, depth-derived flow and covisibility.

Layout under root (the official MegaDepth_v1 + MegaDepth_SfM_v1 downloads merged, see
data/megadepth/README.md):
  <scene 4 digits>/dense<N>/imgs/<name>.jpg           undistorted images
  <scene>/dense<N>/depths/<stem>.h5                    key 'depth', float32 z-depth, 0 = invalid
  <scene>/sparse/manhattan/<N>/cameras.txt, images.txt COLMAP text (images.txt poses are w2c)
A scene id in pair lists is `<scene>/<N>` and frames are image file names (with extension).
Intrinsics of the undistorted `imgs` are not shipped; as DUSt3R's preprocessing does, they are
K_post = cv2.getOptimalNewCameraMatrix(K_colmap, dist, size_colmap, alpha=0,
newImgSize=size_img, centerPrincipalPoint=True), taken as OpenCV-convention intrinsics.
Split: by default the official one, as the official-layout reader (MegaDepthProcessed) and the
official class: `split` selects no scenes, so "train" holds the val scenes 0015 and 0022 too;
`select_scenes=True` applies the intended (DUSt3R) split: val = scenes 0015 and 0022 (the
MegaDepth-1500 test scenes), train = the rest. Both readers take the same option.
Pairs: `<root>/pairs_<split>.txt`, else DUSt3R's `megadepth_pairs.npz` at root, else run
data/mine_pairs.py (mutual covisibility > 25%).
"""

from __future__ import annotations

import functools
import os

import cv2
import h5py
import numpy as np

from ufm_jax.data.registry import register
from ufm_jax.data import io
from ufm_jax.data.sources import _official, posed

_VAL_SCENES = ("0015", "0022")
_DIST = {"SIMPLE_PINHOLE": 0, "PINHOLE": 0, "SIMPLE_RADIAL": 1, "RADIAL": 2, "OPENCV": 4}


def _selected(scene, split, select_scenes: bool) -> bool:
  """Whether `scene` belongs to `split`: always by default (the official quirk), by the
  intended split with select_scenes."""
  return not select_scenes or _in_split(scene, split)


def _in_split(scene, split):
  if split in (None, "all"):
    return True
  is_val = scene.startswith(_VAL_SCENES)
  return is_val if split == "val" else not is_val


def read_depth_h5(path):
  posed.require_file(path, "a MegaDepth depth .h5 with dataset 'depth'")
  try:
    with h5py.File(path, "r") as f:
      if "depth" not in f:
        raise ValueError(f"{path}: no 'depth' dataset (keys: {list(f.keys())})")
      return np.asarray(f["depth"], np.float32)
  except OSError as e:
    raise ValueError(f"{path}: not a readable HDF5 file ({e})") from e


def undistorted_K(cam: dict, img_size_wh, where: str) -> np.ndarray:
  """DUSt3R's intrinsics for MegaDepth's undistorted images (see module docstring)."""
  K = posed.colmap_K(cam, where)
  if cam["model"] not in _DIST:
    raise ValueError(f"{where}: unsupported camera model {cam['model']} for MegaDepth")
  dist = np.zeros(4)
  n = _DIST[cam["model"]]
  dist[:min(n, 2)] = cam["params"][3:3 + min(n, 2)] if cam["model"] != "OPENCV" else \
      cam["params"][4:6]
  if cam["model"] == "OPENCV":
    dist[2:] = cam["params"][6:8]
  K_post, _ = cv2.getOptimalNewCameraMatrix(K, dist, (cam["width"], cam["height"]), 0,
                                            tuple(int(x) for x in img_size_wh),
                                            centerPrincipalPoint=True)
  return K_post


@register("megadepth")
class MegaDepth(posed.PosedPairSource):
  name = "megadepth"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="train", pairs=None, thresholds=None, select_scenes=False):
    super().__init__(root, split, pairs, thresholds)
    # False: the official choice (every scene in every split, as MegaDepthProcessed); True: the
    # intended split (val = 0015, 0022). A pair list named pairs_<split>.txt is read as given.
    self.select_scenes = bool(select_scenes)

  def scenes(self):
    out = []
    for s in sorted(os.listdir(self.root)):
      d = os.path.join(self.root, s)
      if not (os.path.isdir(d) and _selected(s, self.split, self.select_scenes)):
        continue
      for sub in sorted(os.listdir(d)):
        if sub.startswith("dense") and sub[5:].isdigit():
          out.append(f"{s}/{sub[5:]}")
    return out

  def frames(self, scene):
    s, n = scene.split("/")
    d = posed.require_dir(os.path.join(self.root, s, f"dense{n}", "imgs"), "dense<N>/imgs/")
    return sorted(os.listdir(d))

  def default_pairs(self):
    npz = os.path.join(self.root, "megadepth_pairs.npz")
    if not os.path.isfile(npz):
      yield from super().default_pairs()
      return
    data = np.load(npz, allow_pickle=True)
    scenes, images = data["scenes"], data["images"]
    for scene_id, im1, im2, _ in data["pairs"]:
      s, n = str(scenes[int(scene_id)]).split()
      if _selected(s, self.split, self.select_scenes):
        yield f"{s}/{n}", str(images[int(im1)]), str(images[int(im2)])

  @functools.lru_cache(maxsize=64)
  def _sfm(self, scene):
    s, n = scene.split("/")
    d = os.path.join(self.root, s, "sparse", "manhattan", n)
    cams_path = os.path.join(d, "cameras.txt")
    return cams_path, posed.read_colmap_cameras(cams_path), posed.read_colmap_images(
        os.path.join(d, "images.txt"))

  def load_view(self, scene, frame):
    s, n = scene.split("/")
    dense = os.path.join(self.root, s, f"dense{n}")
    image = io.read_image(os.path.join(dense, "imgs", frame))
    depth = posed.sanitize_depth(read_depth_h5(
        os.path.join(dense, "depths", os.path.splitext(frame)[0] + ".h5")))
    cams_path, cams, images = self._sfm(scene)
    if frame not in images:
      raise KeyError(f"{cams_path[:-11]}images.txt: no image named {frame!r}")
    entry = images[frame]
    if entry["camera_id"] not in cams:
      raise KeyError(f"{cams_path}: no camera {entry['camera_id']} (used by {frame})")
    K = undistorted_K(cams[entry["camera_id"]], image.shape[1::-1], cams_path)
    return posed.View(image, depth, K, np.linalg.inv(entry["w2c"]))


# ------------------------------------------------------------------------ official processed layout

@register("megadepth_official")
class MegaDepthProcessed(_official.OfficialPosed, posed.PosedPairSource):
  """MegaDepth as DUSt3R's preprocessing leaves it, read like the official
  `uniflowmatch.datasets.MegaDepth`:
    <root>/<scene>/<subscene>/<image>.jpg, <image>.exr (float32 z-depth), <image>.npz
    (intrinsics 3x3 OpenCV, cam2world 4x4; both read as float32)
    pairs: dust3r_data_pairs/megadepth_pairs.npz with `scenes` ("<scene> <subscene>"), `images`
    (names without extension) and `pairs` (fields scene_id, im1_id, im2_id, score)
  Split: the official class reads every pair of the file whatever `split` says: its `split`
  keyword never reaches the base class (megadepth.py:19-35), so the `select_scene` that would
  keep val = scenes 0015 and 0022 and train = the others never runs (val scenes train too).
  `select_scenes=True` applies that intended split instead (the raw-layout reader MegaDepth
  takes the same option with the same default)."""

  name = "megadepth"
  has_backward = False
  static_scene = True

  pairs_file = "megadepth_pairs.npz"

  def __init__(self, root, split="train", pairs=None, thresholds=None, pair_metadata_path=None,
               select_scenes=False):
    super().__init__(root, split, pairs, thresholds, pair_metadata_path)
    self.select_scenes = bool(select_scenes)

  def _official_pairs(self):
    data = _official.load_npz(self.pairs_path, ("scenes", "images", "pairs"), allow_pickle=True)
    scenes, images, pairs = data["scenes"], data["images"], data["pairs"]
    names = pairs.dtype.names or ()
    if names and not {"scene_id", "im1_id", "im2_id"} <= set(names):
      raise ValueError(f"{self.pairs_path}: 'pairs' lacks fields scene_id, im1_id, im2_id "
                       f"(has {names})")
    cols = ([pairs[f] for f in ("scene_id", "im1_id", "im2_id")] if names else
            [pairs[:, 0], pairs[:, 1], pairs[:, 2]])
    scene_names = [str(s).split() for s in scenes]
    is_val = np.array([s[0].startswith(_VAL_SCENES) for s in scene_names])
    sid = cols[0].astype(np.int64)
    keep = np.ones(len(sid), bool) if self.split in (None, "all") or not self.select_scenes else (
        is_val[sid] if self.split == "val" else ~is_val[sid])
    out = []
    for s, a, b in zip(sid[keep], cols[1][keep].astype(np.int64), cols[2][keep].astype(np.int64)):
      scene, sub = scene_names[s]
      out.append((f"{scene}/{sub}", _stem(images[a]), _stem(images[b])))
    return out

  def scenes(self):
    return sorted(f"{s}/{sub}" for s in os.listdir(self.root)
                  if _selected(s, self.split, self.select_scenes)
                  and os.path.isdir(os.path.join(self.root, s))
                  for sub in os.listdir(os.path.join(self.root, s)))

  def frames(self, scene):
    d = posed.require_dir(os.path.join(self.root, scene), "a processed MegaDepth subscene")
    return sorted(f[:-4] for f in os.listdir(d) if f.endswith(".npz"))

  def load_view(self, scene, frame):
    return _official.processed_view(os.path.join(self.root, scene, frame),
                                    (("intrinsics",), ("cam2world",)))


def _stem(name) -> str:
  name = str(name)
  return name[:-4] if name.lower().endswith(".jpg") else name
