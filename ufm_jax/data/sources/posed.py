"""Shared machinery for depth + pose datasets (static scenes and the wide-baseline benchmarks).

A posed source lists pairs `(scene, frame0, frame1)` and knows how to load one view as a `View`
(RGB image, z-depth in the dataset's units with 0 = invalid, OpenCV intrinsics with pixel centres
at integer coordinates, camera-to-world pose with OpenCV axes). `pair_sample` turns two views into
the common sample dict via `ufm_jax.geometry.correspondence_from_depth`, with the per-dataset
covisibility thresholds of supplementary Table S1.

Each dataset module converts its own conventions (w2c, OpenGL/NED axes, COLMAP +0.5 principal
point, range depth, millimetres) into a `View` right where it reads the files, so the conversion
is next to the fact it relies on.

Camera and pair-list decoders that several posed datasets share live here too (MVSNet cam.txt,
COLMAP text); array formats (PFM, LMB float3, PNG16) are in `ufm_jax/data/io.py`.

Pair lists: every posed source reads `<root>/pairs_<split>.txt` when present (one pair per line,
`scene frame0 frame1 [score]`, whitespace separated, `#` comments), the format written by
`data/mine_pairs.py`. Without it each dataset falls back to its documented default rule.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Sequence

import numpy as np

from ufm_jax import geometry


@dataclasses.dataclass
class View:
  image: np.ndarray       # [H, W, 3] uint8 RGB
  depth: np.ndarray       # [H, W] float32 z-depth, 0 = invalid
  K: np.ndarray           # [3, 3] OpenCV intrinsics (pixel centres at integers)
  cam2world: np.ndarray   # [4, 4] camera-to-world, OpenCV axes (x right, y down, z forward)


# ----------------------------------------------------------------------------------- file readers

def require_dir(path: str, what: str) -> str:
  if not os.path.isdir(path):
    raise FileNotFoundError(f"{path}: missing directory (expected {what})")
  return path


def require_file(path: str, what: str) -> str:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: missing file (expected {what})")
  return path


def read_mvsnet_cam(path: str) -> tuple[np.ndarray, np.ndarray]:
  """MVSNet `*_cam.txt` -> (w2c [4, 4], K [3, 3])."""
  require_file(path, "an MVSNet camera file (extrinsic / intrinsic blocks)")
  with open(path) as f:
    words = f.read().split()
  try:
    e = words.index("extrinsic")
    i = words.index("intrinsic")
    w2c = np.array(words[e + 1:e + 17], np.float64).reshape(4, 4)
    K = np.array(words[i + 1:i + 10], np.float64).reshape(3, 3)
  except (ValueError, IndexError) as err:
    raise ValueError(f"{path}: malformed MVSNet camera file (expected 'extrinsic' + 16 numbers "
                     "and 'intrinsic' + 9 numbers)") from err
  return w2c, K


def read_mvsnet_pairs(path: str) -> dict[int, list[int]]:
  """MVSNet `pair.txt` -> {reference view: [source views in score order]}."""
  require_file(path, "an MVSNet pair.txt")
  with open(path) as f:
    words = f.read().split()
  try:
    n, pos, out = int(words[0]), 1, {}
    for _ in range(n):
      ref, k = int(words[pos]), int(words[pos + 1])
      out[ref] = [int(words[pos + 2 + 2 * j]) for j in range(k)]
      pos += 2 + 2 * k
  except (ValueError, IndexError) as err:
    raise ValueError(f"{path}: malformed MVSNet pair.txt") from err
  return out


def qvec_to_rotmat(q) -> np.ndarray:
  """Hamilton unit quaternion (w, x, y, z) -> 3x3 rotation."""
  w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
  return np.array([
      [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


_COLMAP_PINHOLE = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5,
                   "OPENCV": 8, "THIN_PRISM_FISHEYE": 12, "OPENCV_FISHEYE": 8, "FULL_OPENCV": 12}


def read_colmap_cameras(path: str) -> dict[int, dict]:
  """COLMAP cameras.txt -> {id: dict(model, width, height, params)}."""
  require_file(path, "a COLMAP cameras.txt")
  cams = {}
  with open(path) as f:
    for n, line in enumerate(f, 1):
      if not line.strip() or line.startswith("#"):
        continue
      w = line.split()
      try:
        cams[int(w[0])] = dict(model=w[1], width=int(w[2]), height=int(w[3]),
                               params=np.array(w[4:], np.float64))
      except (ValueError, IndexError) as err:
        raise ValueError(f"{path}:{n}: malformed camera line (expected 'ID MODEL W H PARAMS')") \
            from err
  return cams


def colmap_K(cam: dict, path: str = "cameras.txt") -> np.ndarray:
  """Pinhole part of a COLMAP camera, still in COLMAP's pixel convention (centre at +0.5)."""
  m, p = cam["model"], cam["params"]
  if m in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
    fx = fy = p[0]
    cx, cy = p[1], p[2]
  elif m in _COLMAP_PINHOLE:
    fx, fy, cx, cy = p[:4]
  else:
    raise ValueError(f"{path}: unsupported COLMAP camera model {m}")
  return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)


def colmap_to_opencv_K(K: np.ndarray) -> np.ndarray:
  """COLMAP puts the centre of the top-left pixel at (0.5, 0.5); OpenCV at (0, 0)."""
  K = K.copy()
  K[0, 2] -= 0.5
  K[1, 2] -= 0.5
  return K


def read_colmap_images(path: str) -> dict[str, dict]:
  """COLMAP images.txt -> {name: dict(camera_id, w2c [4, 4])} (quaternion w first, w2c)."""
  require_file(path, "a COLMAP images.txt")
  with open(path) as f:
    lines = [l.rstrip("\n") for l in f if not l.startswith("#")]
  out = {}
  for i in range(0, len(lines), 2):
    w = lines[i].split()
    if not w:
      continue
    try:
      q, t = np.array(w[1:5], np.float64), np.array(w[5:8], np.float64)
      w2c = np.eye(4)
      w2c[:3, :3] = qvec_to_rotmat(q)
      w2c[:3, 3] = t
      out[" ".join(w[9:])] = dict(camera_id=int(w[8]), w2c=w2c)
    except (ValueError, IndexError) as err:
      raise ValueError(f"{path}: malformed image line {lines[i]!r} (expected 'ID QW QX QY QZ TX "
                       "TY TZ CAMERA_ID NAME')") from err
  return out


def read_pair_list(path: str) -> list[tuple[str, str, str]]:
  require_file(path, "a pair list (scene frame0 frame1 [score] per line)")
  pairs = []
  with open(path) as f:
    for n, line in enumerate(f, 1):
      line = line.split("#", 1)[0].strip()
      if not line:
        continue
      w = line.split()
      if len(w) < 3:
        raise ValueError(f"{path}:{n}: expected 'scene frame0 frame1 [score]', got {line!r}")
      pairs.append((w[0], w[1], w[2]))
  return pairs


def write_pair_list(path: str, pairs: Sequence[Sequence], header: str = "") -> None:
  """Writes a pair list atomically."""
  tmp = f"{path}.tmp{os.getpid()}"
  with open(tmp, "w") as f:
    for line in header.splitlines():
      f.write(f"# {line}\n")
    for p in pairs:
      f.write(" ".join(f"{x:.4f}" if isinstance(x, float) else str(x) for x in p) + "\n")
  os.replace(tmp, path)


def sanitize_depth(depth: np.ndarray, scale: float = 1.0) -> np.ndarray:
  """NaN / inf / negative -> 0 (invalid), then multiply by `scale` (e.g. mm -> m)."""
  depth = np.asarray(depth, np.float32)
  ok = depth > 0  # False for nan and -inf
  ok &= depth < np.inf
  depth = np.where(ok, depth, np.float32(0))  # a new array: the input is never modified
  return depth * np.float32(scale) if scale != 1.0 else depth


def range_to_z(rng: np.ndarray, K: np.ndarray) -> np.ndarray:
  """Euclidean distance to the camera centre -> z-depth, using pixel centres at integers."""
  K = np.asarray(K, np.float64)
  norm = _ray_norms(*rng.shape, float(K[0, 0]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]))
  return (rng / norm).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _ray_norms(h: int, w: int, fx: float, cx: float, fy: float, cy: float) -> np.ndarray:
  """Read-only float64 [H, W] ||(u, v, 1)|| of `range_to_z` (cached: a dataset has few K)."""
  u = (np.arange(w) - cx) / fx
  v = (np.arange(h) - cy) / fy
  norm = np.sqrt(1 + u[None, :] ** 2 + v[:, None] ** 2)
  norm.setflags(write=False)
  return norm


def check_view(v: View, where: str) -> View:
  if v.image.shape[:2] != v.depth.shape:
    raise ValueError(f"{where}: image is {v.image.shape[:2]} but depth is {v.depth.shape}")
  return v


# --------------------------------------------------------------------------------- sample assembly

@dataclasses.dataclass(frozen=True)
class PosedPair:
  """Two posed views of a static scene, labelled on request in either direction and on any grid
  of source pixels. The training pipeline crops the views and labels the crops, or (a posed set
  read as a flow set) labels only the stored pixels its crop reads (ufm_jax.data.augment)."""
  v0: View
  v1: View
  thresholds: tuple[float, float]   # (tau_d, tau_r)

  @property
  def image0(self):
    return self.v0.image

  @property
  def image1(self):
    return self.v1.image

  def labels(self, backward: bool = False, rows=None, cols=None) -> dict:
    """flow, covisibility, flow_valid, covis_valid of (v0 -> v1), or (v1 -> v0) with `backward`,
    at the source pixels rows x cols (default all)."""
    a, b = (self.v1, self.v0) if backward else (self.v0, self.v1)
    corr = geometry.correspondence_from_depth(a.depth, a.K, a.cam2world, b.depth, b.K,
                                              b.cam2world, *self.thresholds, rows=rows, cols=cols)
    return geometry.labels_from_correspondence(corr)

  def training_labels(self, backward: bool, params, rows=None, cols=None) -> dict:
    """The four label arrays by the official training code's rule (`geometry.official_labels`,
    params = covisible_rendering_parameters) at the source pixels rows x cols: what the training
    pipeline uses where a dataset's official pathway labels stored-size views (TartanAir)."""
    a, b = (self.v1, self.v0) if backward else (self.v0, self.v1)
    out = geometry.official_labels(a.depth, a.K, a.cam2world, b.depth, b.K, b.cam2world, params,
                                   rows=rows, cols=cols)
    return {k: out[k] for k in ("flow", "covisibility", "flow_valid", "covis_valid")}


def pair_sample(dataset: str, scene: str, frames: tuple, v0: View, v1: View,
                thresholds: tuple[float, float] | None = None, extra_meta: dict | None = None):
  """Two posed views -> the common sample dict (flow / covisibility from depth reprojection)."""
  thresholds = thresholds if thresholds is not None else geometry.covis_thresholds(dataset)
  return labelled_sample(dataset, scene, frames, v0, v1, PosedPair(v0, v1, thresholds).labels(),
                         extra_meta)


def labelled_sample(dataset, scene, frames, v0: View, v1: View, labels: dict, extra_meta=None):
  """Labels (geometry.labels_from_correspondence: flow_valid = flow geometrically defined, i.e.
  valid source depth, in front of camera 1; the flow loss additionally restricts to
  `covisibility`, paper eq. 3) + the views -> sample dict with the views' meta."""
  meta = dict(dataset=dataset, scene=scene, frame0=str(frames[0]), frame1=str(frames[1]),
              K0=np.asarray(v0.K, np.float32), K1=np.asarray(v1.K, np.float32),
              cam2world0=np.asarray(v0.cam2world, np.float32),
              cam2world1=np.asarray(v1.cam2world, np.float32),
              depth0=v0.depth, depth1=v1.depth)
  if extra_meta:
    meta.update(extra_meta)
  return dict(image0=v0.image, image1=v1.image, meta=meta, **labels)


class PosedPairSource:
  """Random-access pairs of posed views. Subclasses set `name` and implement `load_view` and
  `default_pairs` (and optionally `scenes` / `frames` for pair mining).

  Their own samples (`self[i]`: evaluation, tools, pair mining) carry the supplementary's labels
  (`geometry.correspondence_from_depth`); the training pipeline crops the views of `lazy_pair(i)`
  and labels them by the official training code's rule (`pathway`, ufm_jax.data.augment)."""

  name = "posed"
  pathway = "static"

  def __init__(self, root, split="train", pairs=None, thresholds=None):
    if root is None:
      raise ValueError(f"{self.name}: a dataset root is required (see data/{self.name}/README.md)")
    self.root = os.fspath(root)
    require_dir(self.root, f"the {self.name} dataset root described in data/{self.name}/README.md")
    self.split = split
    self.thresholds = thresholds
    self._pairs_arg = pairs
    self._pairs = None

  # -- pairs
  @property
  def pairs(self) -> list[tuple[str, str, str]]:
    if self._pairs is None:
      if isinstance(self._pairs_arg, (list, tuple)):
        self._pairs = [tuple(map(str, p[:3])) for p in self._pairs_arg]
      else:
        path = self._pairs_arg or os.path.join(self.root, f"pairs_{self.split}.txt")
        if os.path.isfile(path):
          self._pairs = read_pair_list(path)
        elif self._pairs_arg:
          require_file(path, "a pair list")
        else:
          self._pairs = list(self.default_pairs())
      if not self._pairs:
        raise ValueError(f"{self.root}: no {self.name} pairs for split {self.split!r}")
    return self._pairs

  def default_pairs(self):
    raise FileNotFoundError(
        f"{os.path.join(self.root, f'pairs_{self.split}.txt')}: missing pair list; create it with "
        f"`python data/mine_pairs.py --dataset {self.name} --root {self.root} --split {self.split}`")

  # -- views (subclasses)
  def load_view(self, scene: str, frame: str) -> View:
    raise NotImplementedError

  def scenes(self) -> list[str]:
    raise NotImplementedError(f"{self.name}: scene listing not available")

  def frames(self, scene: str) -> list[str]:
    raise NotImplementedError(f"{self.name}: frame listing not available")

  # -- sequence protocol
  def __len__(self):
    return len(self.pairs)

  def __getitem__(self, i):
    scene, f0, f1 = self.pairs[i]
    pair = self.lazy_pair(i)
    return pair_sample(self.name, scene, (f0, f1), pair.v0, pair.v1, pair.thresholds)

  def lazy_pair(self, i) -> PosedPair:
    """Pair i's views, labelled on request (both directions, any pixel grid): what the training
    pipeline reads instead of the full-size labels of `self[i]` (ufm_jax.data.registry)."""
    scene, f0, f1 = self.pairs[i]
    v0 = check_view(self.load_view(scene, f0), f"{self.name}:{scene}/{f0}")
    v1 = check_view(self.load_view(scene, f1), f"{self.name}:{scene}/{f1}")
    return PosedPair(v0, v1, tuple(self.thresholds or geometry.covis_thresholds(self.name)))


# ----------------------------------------------------------------------------------- pair mining

def subsample_view(v: View, stride: int) -> View:
  """Every `stride`-th pixel (no averaging, so depth stays exact); K follows the pixel centres."""
  if stride <= 1:
    return v
  K = v.K.copy()
  K[:2] /= stride
  K[2, 2] = 1.0
  return View(v.image[::stride, ::stride], v.depth[::stride, ::stride], K, v.cam2world)


def mutual_covisibility(v0: View, v1: View, thresholds) -> tuple[float, float]:
  """Fractions of all pixels of view 0 (resp. 1) that are covisible in the other view."""
  f = geometry.correspondence_from_depth(v0.depth, v0.K, v0.cam2world, v1.depth, v1.K,
                                         v1.cam2world, *thresholds)
  b = geometry.correspondence_from_depth(v1.depth, v1.K, v1.cam2world, v0.depth, v0.K,
                                         v0.cam2world, *thresholds)
  return float(f["covisibility"].mean()), float(b["covisibility"].mean())


def mine_pairs(source: "PosedPairSource", scenes=None, min_covis: float = 0.25,
               max_side: int = 128, max_frames: int | None = None, progress: bool = True):
  """All frame pairs of each scene whose mutual covisibility (min of both directions, fraction of
  all pixels, at `max_side` resolution) exceeds `min_covis`. -> [(scene, f0, f1, score)].
  Unreadable views are skipped and reported."""
  import itertools
  import tqdm
  thresholds = source.thresholds or geometry.covis_thresholds(source.name)
  out, skipped = [], []
  for scene in tqdm.tqdm(scenes if scenes is not None else source.scenes(), desc="scenes",
                         disable=not progress):
    views = {}
    for f in source.frames(scene)[:max_frames]:
      try:
        v = source.load_view(scene, f)
      except (OSError, ValueError, KeyError) as e:
        skipped.append(f"{scene}/{f}: {e}")
        continue
      stride = max(1, -(-max(v.depth.shape) // max_side))
      views[f] = subsample_view(v, stride)
    pairs = list(itertools.combinations(sorted(views), 2))
    for a, b in tqdm.tqdm(pairs, desc=scene, leave=False, disable=not progress):
      score = min(mutual_covisibility(views[a], views[b], thresholds))
      if score > min_covis:
        out.append((scene, a, b, round(score, 4)))
  return out, skipped
