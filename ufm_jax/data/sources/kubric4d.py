"""Kubric-4D (GCD release): dynamic scenes of rigid objects, 16 static cameras, 60 frames.

Pairs span viewpoint and time; correspondence and covisibility follow the rigid-posed-objects
rule (supplementary "Computing Covisibility Mask"): a source pixel's 3D point moves with the pose
of the object it belongs to (segmentation id), then is projected into the target camera and
checked against the target depth. The dataset's precomputed flow is not used.

Layout under root (the GCD download, see data/kubric4d/README.md):
  scn{%05d}/scn{%05d}_p0_v{v}.json                  Kubric metadata of view v: scene.resolution
                                                   (W, H), scene.num_frames, camera.K (normalised,
                                                   sign-flipped), camera.positions / quaternions
                                                   (w, x, y, z; camera-to-world, OpenGL/Blender
                                                   axes), instances[k-1].positions / quaternions
                                                   (object-to-world pose of segmentation id k)
  scn{%05d}/frames_p0_v{v}/rgba_{t:05d}.png        RGBA
  scn{%05d}/frames_p0_v{v}/depth_{t:05d}.tiff      float32 Euclidean range (not z-depth)
  scn{%05d}/frames_p0_v{v}/segmentation_{t:05d}.png  object id per pixel (palette or grey PNG),
                                                   0 = static background
Conventions: K = |camera.K| * (W, H) is in Kubric's corner-origin frame (pixel i centred at
i + 0.5), so the OpenCV principal point is that minus 0.5 (`principal_point_shift=True`). The
official training code means to subtract it but subtracts it from a copy it then discards
(uniflowmatch/datasets/kubric4d.py:55-60), so its labels use the corner-origin value: the default
here (`principal_point_shift=False`) for its training labels. The camera pose's y and z columns
are negated for OpenCV axes; range is converted to z-depth with the same K.
Scene = `scn{%05d}`, frame = `{view}/{time}`. Split: scenes 0-2799 train, 2800-2899 val, the rest
test. Pairs: `<root>/pairs_<split>.txt` written by `python data/kubric4d/sample_pairs.py`
(the supplementary sampler, `sample_scene_pairs` below).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import struct
import zlib

import cv2
import numpy as np

from ufm_jax.data.registry import register
from ufm_jax.data import io
from ufm_jax.data.sources import _official, posed

SPLITS = {"train": (0, 2800), "val": (2800, 2900), "test": (2900, 10 ** 9)}


# --------------------------------------------------------------------------------- file decoding

def read_index_png(path: str) -> np.ndarray:
  """Segmentation PNG -> [H, W] int32 ids: palette indices for palette PNGs (recovered through the
  PLTE chunk), the grey value otherwise."""
  posed.require_file(path, "a Kubric segmentation PNG")
  raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
  if raw is None:
    raise ValueError(f"{path}: not a decodable PNG")
  if raw.ndim == 2:
    return raw.astype(np.int32)
  with open(path, "rb") as f:
    buf = f.read()
  pos, palette = 8, None
  while pos + 8 <= len(buf):
    n, kind = struct.unpack(">I4s", buf[pos:pos + 8])
    if kind == b"PLTE":
      palette = np.frombuffer(buf[pos + 8:pos + 8 + n], np.uint8).reshape(-1, 3)
      break
    pos += 12 + n
  if palette is None or not len(palette):
    raise ValueError(f"{path}: colour segmentation without a palette (expected a palette or "
                     "grey PNG of object ids)")
  table = _palette_hash(palette.tobytes()) if raw.dtype == np.uint8 and raw.shape[2] in (3, 4) \
      else None
  if table is not None:
    mult, shift, keys, index = table
    bgr = cv2.cvtColor(raw, cv2.COLOR_BGRA2BGR) if raw.shape[2] == 4 else raw
    codes = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA).view("<u4")[..., 0]  # B | G, R, 255 << 8, 16, 24
    slot = np.right_shift(np.multiply(codes, mult), shift).astype(np.intp)
    missing = np.take(keys, slot) != codes
    if missing.any():
      raise ValueError(f"{path}: pixel colour {int(codes[missing][0]) & 0xFFFFFF} not in the PNG "
                       "palette")
    return np.take(index, slot)
  codes = raw[..., 2].astype(np.int32) << 16  # BGR(A): R << 16 | G << 8 | B
  codes |= raw[..., 1].astype(np.int32) << 8
  codes |= raw[..., 0]
  pcodes = (palette[:, 0].astype(np.int32) << 16) | (palette[:, 1].astype(np.int32) << 8) | \
      palette[:, 2]
  # Sorted unique palette colours, each with its first palette index (first wins for duplicates).
  sorted_codes, first = np.unique(pcodes, return_index=True)
  pos = np.searchsorted(sorted_codes, codes)
  np.minimum(pos, len(sorted_codes) - 1, out=pos)
  missing = sorted_codes[pos] != codes
  if missing.any():
    raise ValueError(f"{path}: pixel colour {int(codes[missing][0])} not in the PNG palette")
  return first.astype(np.int32)[pos]


@functools.lru_cache(maxsize=64)
def _palette_hash(palette: bytes):
  """Perfect multiplicative hash of a PNG palette's colours (bytes of [N, 3] RGB) for
  `read_index_png`: (mult, shift, keys, index) with slot = (code * mult mod 2^32) >> shift,
  keys[slot] = the colour code B | G << 8 | R << 16 | 255 << 24 there (0, never a pixel's code,
  in empty slots) and index[slot] its first palette index. None if no multiplier was found (the
  caller then falls back to a sorted search). A hash lookup is ~5x faster than searchsorted."""
  rgb = np.frombuffer(palette, np.uint8).reshape(-1, 3).astype(np.uint32)
  codes = rgb[:, 2] | (rgb[:, 1] << 8) | (rgb[:, 0] << 16) | np.uint32(0xFF000000)
  uniq, first = np.unique(codes, return_index=True)
  mults = np.random.default_rng(0).integers(1 << 30, 1 << 32, 64, dtype=np.uint64) | 1
  for bits in range(max(4, 2 * int(len(uniq)).bit_length()), 21):
    for mult in mults.astype(np.uint32):
      slots = (uniq * mult) >> np.uint32(32 - bits)
      if len(np.unique(slots)) == len(uniq):
        keys = np.zeros(1 << bits, np.uint32)
        index = np.zeros(1 << bits, np.int32)
        keys[slots], index[slots] = uniq, first
        return mult, np.uint32(32 - bits), keys, index
  return None


def write_index_png(path: str, ids: np.ndarray, palette: np.ndarray) -> None:
  """8-bit palette PNG writer (for tests and tools; cv2 cannot write palette PNGs)."""
  ids = np.asarray(ids, np.uint8)
  h, w = ids.shape
  raw = b"".join(b"\0" + ids[r].tobytes() for r in range(h))

  def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

  png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 3, 0, 0, 0))
         + chunk(b"PLTE", np.asarray(palette, np.uint8).tobytes())
         + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
  tmp = f"{path}.tmp{os.getpid()}"
  with open(tmp, "wb") as f:
    f.write(png)
  os.replace(tmp, path)


def read_metadata(path: str, principal_point_shift: bool = True) -> dict:
  """Kubric metadata json -> K (OpenCV, see the module docstring for `principal_point_shift`),
  cam2world per frame, object poses, frame count, (H, W)."""
  posed.require_file(path, "a Kubric metadata json (scn*_p0_v*.json)")
  try:
    with open(path) as f:
      m = json.load(f)
    W, H = m["scene"]["resolution"]
    Kn = np.abs(np.array(m["camera"]["K"], np.float64))
    pos = np.array(m["camera"]["positions"], np.float64)
    quat = np.array(m["camera"]["quaternions"], np.float64)
    inst = [(np.array(o["positions"], np.float64), np.array(o["quaternions"], np.float64))
            for o in m.get("instances", [])]
  except (ValueError, KeyError, TypeError) as e:
    raise ValueError(f"{path}: malformed Kubric metadata (expected scene.resolution, camera.K/"
                     f"positions/quaternions, instances): {e}") from e
  K = Kn.copy()
  K[0] *= W
  K[1] *= H
  if principal_point_shift:
    K[0, 2] -= 0.5  # corner-origin -> pixel centres at integers
    K[1, 2] -= 0.5
  c2w = np.tile(np.eye(4), (len(pos), 1, 1))
  for t in range(len(pos)):
    c2w[t, :3, :3] = posed.qvec_to_rotmat(quat[t]) @ np.diag([1.0, -1.0, -1.0])
    c2w[t, :3, 3] = pos[t]
  return dict(K=K, cam2world=c2w, instances=inst, num_frames=len(pos), size=(H, W))


def object_poses(meta: dict, t: int) -> dict:
  """{segmentation id: object-to-world 4x4} at time t; id 0 (background) is static."""
  out = {0: np.eye(4)}
  for k, (pos, quat) in enumerate(meta["instances"], 1):
    T = np.eye(4)
    T[:3, :3] = posed.qvec_to_rotmat(quat[t])
    T[:3, 3] = pos[t]
    out[k] = T
  return out


# ----------------------------------------------------------------------------------- the sampler

def camera_pair_weight(alpha: np.ndarray) -> np.ndarray:
  """Supplementary w(alpha): 1 + alpha below pi/3, 1 + pi/3 up to pi/2, 0 from pi/2 on."""
  alpha = np.asarray(alpha, np.float64)
  return np.where(alpha < np.pi / 3, 1 + alpha, np.where(alpha < np.pi / 2, 1 + np.pi / 3, 0.0))


def frame_difference_probs(max_diff: int = 40) -> np.ndarray:
  """P(d) for d = 0..max_diff rising linearly so that P(max_diff) = 2 P(0)."""
  p = 1 + np.arange(max_diff + 1) / max_diff
  return p / p.sum()


def sample_scene_pairs(cam2world: np.ndarray, num_frames: int, num_pairs: int, rng,
                       max_diff: int = 40):
  """Kubric-4D pair sampler: camera pair by w(rotation angle) (pairs of distinct cameras, either
  order), frame difference d by `frame_difference_probs`, then a uniform valid start frame; the
  two frames are assigned to the two cameras in random order. Returns [(v0, t0, v1, t1)]."""
  n = len(cam2world)
  R = cam2world[:, :3, :3]
  cosang = (np.einsum("aij,bij->ab", R, R) - 1) / 2  # trace(Ra^T Rb) = sum(Ra * Rb)
  alpha = np.arccos(np.clip(cosang, -1, 1))
  w = camera_pair_weight(alpha)
  np.fill_diagonal(w, 0)
  if w.sum() <= 0:
    raise ValueError("no camera pair with a rotation below pi/2")
  flat = w.ravel() / w.sum()
  max_diff = min(max_diff, num_frames - 1)
  pd = frame_difference_probs(max_diff)
  cams = rng.choice(n * n, size=num_pairs, p=flat)
  diffs = rng.choice(max_diff + 1, size=num_pairs, p=pd)
  out = []
  for c, d in zip(cams, diffs):
    t0 = int(rng.integers(0, num_frames - d))
    t1 = t0 + int(d)
    if rng.random() < 0.5:
      t0, t1 = t1, t0
    out.append((int(c // n), t0, int(c % n), t1))
  return out


# ----------------------------------------------------------------------------------------- source

@register("kubric4d")
class Kubric4D(posed.PosedPairSource):
  name = "kubric4d"
  has_backward = True
  static_scene = False  # objects move: backward labels come from `backward`
  pathway = "kubric"    # the official Kubric pathway of ufm_jax.data.augment

  def __init__(self, root, split="train", pairs=None, thresholds=None,
               principal_point_shift: bool = False):
    """principal_point_shift: False (official quirk): K's principal point as Kubric writes it
    (corner origin), half a pixel off the pixel-centre convention; True: shifted by -0.5."""
    super().__init__(root, split, pairs, thresholds)
    self.principal_point_shift = bool(principal_point_shift)

  def scenes(self):
    lo, hi = SPLITS.get(self.split, (0, 10 ** 9))
    return sorted(s for s in os.listdir(self.root)
                  if s.startswith("scn") and s[3:].isdigit() and lo <= int(s[3:]) < hi
                  and os.path.isdir(os.path.join(self.root, s)))

  def views(self, scene):
    d = os.path.join(self.root, scene)
    return sorted(int(f[len(scene) + 5:-5]) for f in os.listdir(d)
                  if f.startswith(f"{scene}_p0_v") and f.endswith(".json"))

  def default_pairs(self):
    raise FileNotFoundError(
        f"{os.path.join(self.root, f'pairs_{self.split}.txt')}: missing Kubric-4D pair list; "
        f"create it with `python data/kubric4d/sample_pairs.py --root {self.root} "
        f"--split {self.split}`")

  @functools.lru_cache(maxsize=256)
  def metadata(self, scene, view):
    return read_metadata(os.path.join(self.root, scene, f"{scene}_p0_v{view}.json"),
                         self.principal_point_shift)

  def _view(self, scene, frame, with_segmentation=True):
    v, t = (int(x) for x in frame.split("/"))
    meta = self.metadata(scene, v)
    d = os.path.join(self.root, scene, f"frames_p0_v{v}")
    image = io.read_image(os.path.join(d, f"rgba_{t:05d}.png"))
    path = os.path.join(d, f"depth_{t:05d}.tiff")
    posed.require_file(path, "a Kubric float32 range TIFF")
    rng = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if rng is None or rng.ndim != 2:
      raise ValueError(f"{path}: expected a single-channel float32 TIFF")
    if t >= meta["num_frames"]:
      raise ValueError(f"{scene}_p0_v{v}.json: {meta['num_frames']} frames, asked for {t}")
    # Sanitised ranges are 0 or positive and finite, and so are their z-depths (range / ray norm,
    # norm >= 1): one sanitize_depth suffices.
    depth = posed.range_to_z(posed.sanitize_depth(rng), meta["K"])
    seg = read_index_png(os.path.join(d, f"segmentation_{t:05d}.png")) \
        if with_segmentation else None
    view = posed.View(image, depth, meta["K"], meta["cam2world"][t])
    return view, seg, meta, t

  def load_view(self, scene, frame):
    return self._view(scene, frame, with_segmentation=False)[0]

  def __getitem__(self, i):
    scene, f0, f1 = self.pairs[i]
    return self._pair(scene, f0, f1, backward=False).sample(False)

  def backward(self, i):
    """The pair reversed (view 1 at time 1 -> view 0 at time 0), with its own rigid-object labels;
    the pipeline's static-scene reversal from meta would be wrong here (objects move)."""
    scene, f0, f1 = self.pairs[i]
    return self._pair(scene, f1, f0, backward=False).sample(False)

  def both(self, i):
    pair = self.lazy_pair(i)   # every file read once for both directions
    return pair.sample(False), pair.sample(True)

  def lazy_pair(self, i) -> "KubricPair":
    """Pair i's views and segmentations, labelled on request in either direction and on any
    pixel grid (the training pipeline's lazy labels; ufm_jax.data.registry)."""
    scene, f0, f1 = self.pairs[i]
    return self._pair(scene, f0, f1, backward=True)

  def _pair(self, scene, f0, f1, backward: bool) -> "KubricPair":
    from ufm_jax import geometry  # pylint: disable=g-import-not-at-top
    v0, seg0, m0, t0 = self._view(scene, f0)
    # The target's segmentation is read only for backward labels.
    v1, seg1, m1, t1 = self._view(scene, f1, with_segmentation=backward)
    for v, seg, f in ((v0, seg0, f0), (v1, seg1, f1)):
      posed.check_view(v, f"kubric4d:{scene}/{f}")
      if seg is not None and seg.shape != v.depth.shape:
        raise ValueError(f"kubric4d:{scene}/{f}: segmentation {seg.shape} vs depth "
                         f"{v.depth.shape}")
    return KubricPair(v0, v1, tuple(self.thresholds or geometry.covis_thresholds(self.name)),
                      self.name, scene, (f0, f1), (t0, t1), seg0, seg1,
                      *self._object_poses(m0, t0, m1, t1))

  def _object_poses(self, m0, t0, m1, t1):
    """(forward, backward) object poses, each at (source time, target time). Object poses are
    scene properties; every view's metadata carries them (each direction takes its source
    view's)."""
    return ((object_poses(m0, t0), object_poses(m0, t1)),
            (object_poses(m1, t1), object_poses(m1, t0)))


@dataclasses.dataclass(frozen=True)
class KubricPair(posed.PosedPair):
  """Two Kubric views with the source's (and, for backward labels, the target's) segmentation:
  labelled by the rigid-object rule instead of the static one."""
  dataset: str
  scene: str
  frames: tuple
  times: tuple
  seg0: np.ndarray
  seg1: np.ndarray | None
  poses_forward: tuple     # object poses at (time0, time1)
  poses_backward: tuple    # at (time1, time0)

  def labels(self, backward: bool = False, rows=None, cols=None) -> dict:
    """flow, covisibility, flow_valid, covis_valid of (v0 -> v1), or (v1 -> v0) with `backward`,
    by the rigid-object rule at the source pixels rows x cols (default all)."""
    from ufm_jax import geometry
    a, b, seg, (pa, pb) = ((self.v1, self.v0, self.seg1, self.poses_backward) if backward else
                           (self.v0, self.v1, self.seg0, self.poses_forward))
    corr = geometry.correspondence_from_rigid_objects(
        a.depth, a.K, a.cam2world, seg, pa, b.depth, b.K, b.cam2world, pb, *self.thresholds,
        rows=rows, cols=cols)
    return geometry.labels_from_correspondence(corr)

  def training_labels(self, backward: bool, params, rows=None, cols=None) -> dict:
    """The four label arrays by the official Kubric pathway's rule (`official_labels` on the
    rigid-object motion, params = (absolute, temperature, relative); officially the function
    arguments (0.1, 0.1, 0.005), flow_postprocessing.py:308-314)."""
    from ufm_jax import geometry
    a, b, seg, (pa, pb) = ((self.v1, self.v0, self.seg1, self.poses_backward) if backward else
                           (self.v0, self.v1, self.seg0, self.poses_forward))
    out = geometry.correspondence_from_rigid_objects(
        a.depth, a.K, a.cam2world, seg, pa, b.depth, b.K, b.cam2world, pb, *self.thresholds,
        rows=rows, cols=cols, official_params=params)
    # fov_mask (the official view's own key, unused by the recipes' losses) rides along so the
    # crop ANDs it as the official crop does (parity: tests/test_official_data_parity.py).
    return {**{k: out[k] for k in ("flow", "covisibility", "flow_valid", "covis_valid")},
            "fov_mask": out["flow_valid"]}

  def sample(self, backward: bool) -> dict:
    """The full-size sample dict of one direction."""
    a, b = (self.v1, self.v0) if backward else (self.v0, self.v1)
    frames, times = (self.frames[::-1], self.times[::-1]) if backward else (self.frames, self.times)
    return posed.labelled_sample(self.dataset, self.scene, frames, a, b, self.labels(backward),
                                 dict(time0=times[0], time1=times[1]))


# ------------------------------------------------------------------------ official processed layout

@register("kubric4d_official")
class Kubric4DProcessed(Kubric4D):
  """Kubric-4D as the official `uniflowmatch.datasets.Kubric4D` reads it. Root = the official
  `<root_data_dir>/kubric4d` holding
    kubric4d_raw/scn%05d/frames_p0_v<v>/{rgba,depth,segmentation}_%05d.{png,tiff,png}
        the GCD training frames (range depth)
    kubric4d_metadata/sampled_pairs.npz    train_pairs / test_pairs: rows (scene, view0, view1,
                                           frame0, frame1)
    kubric4d_metadata/metadata/scn%05d.npz intrinsics [V, 3, 3] (normalised, Kubric's sign flip),
        extrinsics [V, 4, 4] (camera-to-world, Blender axes), instances_position_scene
        [V, objects, frames, 3], instances_orientation_scene [V, objects, frames, 4] (w, x, y, z)
  The official ROOT, `<root>/kubric4d_raw`, is taken too (its metadata then beside it, or at
  `processed_root`). Conventions as the official: K = intrinsics[v] * (W, H, 1) by rows @ diag(1, -1, -1), with no
  half-pixel shift (its `intrinsics[0, 2] -= 0.5` edits a copy np.load discards, kubric4d.py
  lines 51-56), so the principal point is |K[0, 2]| * W in OpenCV's integer-centre frame; the
  camera pose is extrinsics[v] with its y and z axes negated; object id k's pose at frame t is
  instances_*_scene[v, k - 1, t] of the view that sees it (id 0 = static background)."""

  name = "kubric4d"
  suitable_for_refinement = False

  def __init__(self, root, split="train", pairs=None, thresholds=None, processed_root=None):
    # The official class's ROOT is the frames folder itself (`<root_data_dir>/kubric4d/
    # kubric4d_raw`, configs/dataset/kubric4d/train/default.yaml) with `processed_root` its
    # sibling kubric4d_metadata: that root is taken too.
    root = os.fspath(root) if root is not None else root
    if root is not None and os.path.basename(os.path.normpath(root)) == "kubric4d_raw":
      raw, root = root, os.path.dirname(os.path.normpath(root))
    else:
      raw = None if root is None else os.path.join(root, "kubric4d_raw")
    posed.PosedPairSource.__init__(self, root, split, pairs, thresholds)
    self.raw = posed.require_dir(raw, "kubric4d_raw/scn%05d/ (the GCD frames)")
    self.meta_dir = posed.require_dir(
        processed_root or os.path.join(self.root, "kubric4d_metadata"),
        "kubric4d_metadata/ (sampled_pairs.npz, metadata/)")

  @property
  def pairs(self):
    if self._pairs is None:
      if isinstance(self._pairs_arg, (list, tuple)):
        self._pairs = [tuple(map(str, p[:3])) for p in self._pairs_arg]
      else:
        path = os.path.join(self.meta_dir, "sampled_pairs.npz")
        key = "train_pairs" if self.split == "train" else "test_pairs"
        rows = np.asarray(_official.load_npz(path, (key,))[key])
        if rows.ndim != 2 or rows.shape[1] != 5:
          raise ValueError(f"{path}: {key} must be (N, 5) rows (scene, view0, view1, frame0, "
                           f"frame1), got {rows.shape}")
        self._pairs = [(f"scn{int(s):05d}", f"{int(v0)}/{int(f0)}", f"{int(v1)}/{int(f1)}")
                       for s, v0, v1, f0, f1 in rows]
      if not self._pairs:
        raise ValueError(f"{self.meta_dir}: no Kubric-4D pairs for split {self.split!r}")
    return self._pairs

  def scenes(self):
    return sorted({p[0] for p in self.pairs})

  @functools.lru_cache(maxsize=256)
  def metadata(self, scene, view=None):
    path = os.path.join(self.meta_dir, "metadata", f"{scene}.npz")
    m = _official.load_npz(path, ("intrinsics", "extrinsics", "instances_position_scene",
                                  "instances_orientation_scene"))
    if m["intrinsics"].shape[1:] != (3, 3) or m["extrinsics"].shape[1:] != (4, 4):
      raise ValueError(f"{path}: intrinsics must be [V, 3, 3] and extrinsics [V, 4, 4], got "
                       f"{m['intrinsics'].shape}, {m['extrinsics'].shape}")
    return dict(m, path=path)

  def _view(self, scene, frame, with_segmentation=True):
    v, t = (int(x) for x in frame.split("/"))
    m = self.metadata(scene)
    if v >= len(m["intrinsics"]):
      raise ValueError(f"{m['path']}: no view {v} ({len(m['intrinsics'])} views)")
    d = os.path.join(self.raw, scene, f"frames_p0_v{v}")
    image = io.read_image(os.path.join(d, f"rgba_{t:05d}.png"))
    h, w = image.shape[:2]
    flip = np.diag([1.0, -1.0, -1.0])
    K = (np.asarray(m["intrinsics"][v], np.float64) * np.array([w, h, 1.0])[:, None]) @ flip
    c2w = np.array(m["extrinsics"][v], np.float64)
    c2w[:3, :3] = c2w[:3, :3] @ flip
    path = os.path.join(d, f"depth_{t:05d}.tiff")
    posed.require_file(path, "a Kubric float32 range TIFF")
    rng = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if rng is None or rng.ndim != 2:
      raise ValueError(f"{path}: expected a single-channel float32 TIFF")
    depth = posed.range_to_z(posed.sanitize_depth(rng), K)
    seg = read_index_png(os.path.join(d, f"segmentation_{t:05d}.png")) \
        if with_segmentation else None
    return posed.View(image, depth, K, c2w), seg, (m, v), t

  def _object_poses(self, m0, t0, m1, t1):
    # The official takes each view's object poses from its own view's metadata row.
    p0, p1 = _npz_object_poses(*m0, t0), _npz_object_poses(*m1, t1)
    return (p0, p1), (p1, p0)

  def __getitem__(self, i):
    sample = super().__getitem__(i)
    sample["meta"].update(_official.official_meta(self))
    return sample


def _npz_object_poses(m: dict, view: int, t: int) -> dict:
  """{segmentation id: object-to-world 4x4} at frame t from the official metadata's view row."""
  pos = np.asarray(m["instances_position_scene"][view], np.float64)
  quat = np.asarray(m["instances_orientation_scene"][view], np.float64)
  if not 0 <= t < pos.shape[1]:
    raise ValueError(f"{m['path']}: frame {t} out of range ({pos.shape[1]} frames)")
  out = {0: np.eye(4)}
  for k in range(pos.shape[0]):
    T = np.eye(4)
    T[:3, :3] = posed.qvec_to_rotmat(quat[k, t])
    T[:3, 3] = pos[k, t]
    out[k + 1] = T
  return out
