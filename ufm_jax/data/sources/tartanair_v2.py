"""TartanAir V2 (pinhole cube-face cameras), depth-derived flow and covisibility.

Layout under root (the official per-environment zips unpacked in place, see
data/tartanair_v2/README.md):
  <Env>/Data_<easy|hard>/P<3 digits>/image_<cam>/{%06d}_<cam>.png
  <Env>/Data_<diff>/P<nnn>/depth_<cam>/{%06d}_<cam>_depth.png   float32 metres stored as the 4
                                                                bytes of an RGBA uint8 PNG
  <Env>/Data_<diff>/P<nnn>/pose_<cam>.txt                       `tx ty tz qx qy qz qw` per frame,
                                                                camera-to-world in NED camera axes
with <cam> one of lcam_/rcam_ + front/back/left/right/top/bottom. Intrinsics are fixed by the
renderer: 90 degree FoV, fx = fy = W/2 and the principal point at the image centre. The docs
and tartanairpy write cx = cy = 320 for 640x640; with pixel centres at integers (our convention)
the centre is (W-1)/2 = 319.5, the only value for which six 90-degree faces tile the cube
without gap or overlap (the TA-WB sampler renders across face seams and relies on it), so we read
320 as the corner-origin value. Scene id = `<Env>/Data_<diff>/P<nnn>`, frame id = `<cam>/<index:06d>`.
Pairs: `<root>/pairs_<split>.txt` (e.g. from data/mine_pairs.py), else for every trajectory and
every camera in `cameras` the frames (i, i + s) for s in `strides`.
Sky: TartanAir renders sky as very far depth; `max_depth` (default None) zeroes depth beyond it.
"""

from __future__ import annotations

import functools
import os

import numpy as np

from ufm_jax.data import decode
from ufm_jax.data.registry import register
from ufm_jax.data import io
from ufm_jax.data.sources import posed

CUBE_CAMERAS = ("front", "back", "left", "right", "top", "bottom")
# Columns: OpenCV camera axes written in NED camera axes (x forward, y right, z down).
NED_FROM_OPENCV = np.array([[0.0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def tartanair_K(height: int, width: int) -> np.ndarray:
  return np.array([[width / 2, 0, (width - 1) / 2], [0, height / 2, (height - 1) / 2],
                   [0, 0, 1.0]])


def read_depth_png(path: str) -> np.ndarray:
  posed.require_file(path, "a TartanAir V2 depth PNG (float32 bytes in 4 uint8 channels)")
  raw = decode.imread_unchanged(path)  # OpenCV's BGRA byte order, as TartanAir's tools read it
  if raw is None or raw.dtype != np.uint8 or raw.ndim != 3 or raw.shape[2] != 4:
    raise ValueError(f"{path}: expected a 4-channel uint8 PNG holding float32 depth, got "
                     f"{None if raw is None else (raw.shape, raw.dtype)}")
  return np.ascontiguousarray(raw).view("<f4")[..., 0]


def read_poses_ned(path: str) -> np.ndarray:
  """pose_<cam>.txt -> [N, 4, 4] camera-to-world, OpenCV camera axes."""
  posed.require_file(path, "a TartanAir pose file (tx ty tz qx qy qz qw per line)")
  try:
    rows = np.loadtxt(path, ndmin=2)
  except ValueError as e:
    raise ValueError(f"{path}: malformed pose file ({e})") from e
  if rows.shape[1] != 7:
    raise ValueError(f"{path}: expected 7 numbers per line (tx ty tz qx qy qz qw), got "
                     f"{rows.shape[1]}")
  out = np.tile(np.eye(4), (len(rows), 1, 1))
  for k, (tx, ty, tz, qx, qy, qz, qw) in enumerate(rows):
    out[k, :3, :3] = posed.qvec_to_rotmat((qw, qx, qy, qz))
    out[k, :3, 3] = (tx, ty, tz)
  return out @ NED_FROM_OPENCV


@register("tartanair_v2")
class TartanAirV2(posed.PosedPairSource):
  name = "tartanair_v2"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="train", pairs=None, thresholds=None,
               cameras=("lcam_front",), strides=(1, 2, 4, 8, 16), max_depth=None):
    super().__init__(root, split, pairs, thresholds)
    self.cameras = tuple(cameras)
    self.strides = tuple(strides)
    self.max_depth = max_depth

  def scenes(self):
    out = []
    for env in sorted(os.listdir(self.root)):
      env_dir = os.path.join(self.root, env)
      if not os.path.isdir(env_dir):
        continue
      for diff in sorted(os.listdir(env_dir)):
        if not diff.startswith("Data_") or not os.path.isdir(os.path.join(env_dir, diff)):
          continue
        for traj in sorted(os.listdir(os.path.join(env_dir, diff))):
          if traj.startswith("P") and os.path.isdir(os.path.join(env_dir, diff, traj)):
            out.append(f"{env}/{diff}/{traj}")
    return out

  def frames(self, scene):
    out = []
    for cam in self.cameras:
      d = os.path.join(self.root, scene, f"image_{cam}")
      if os.path.isdir(d):
        out += [f"{cam}/{f[:6]}" for f in sorted(os.listdir(d)) if f.endswith(f"_{cam}.png")]
    return out

  def default_pairs(self):
    scenes = self.scenes()
    if not scenes:
      raise FileNotFoundError(f"{self.root}: no TartanAir V2 trajectories "
                              "(<Env>/Data_<diff>/P<nnn>/)")
    for scene in scenes:
      for cam in self.cameras:
        d = os.path.join(self.root, scene, f"image_{cam}")
        if not os.path.isdir(d):
          continue
        idx = sorted(f[:6] for f in os.listdir(d) if f.endswith(f"_{cam}.png"))
        have = set(idx)
        for a in idx:
          for s in self.strides:
            b = f"{int(a) + s:06d}"
            if b in have:
              yield scene, f"{cam}/{a}", f"{cam}/{b}"

  @functools.lru_cache(maxsize=256)
  def _poses(self, scene, cam):
    return read_poses_ned(os.path.join(self.root, scene, f"pose_{cam}.txt"))

  def load_view(self, scene, frame):
    cam, idx = frame.split("/")
    d = os.path.join(self.root, scene)
    image = io.read_image(os.path.join(d, f"image_{cam}", f"{idx}_{cam}.png"))
    depth = posed.sanitize_depth(read_depth_png(
        os.path.join(d, f"depth_{cam}", f"{idx}_{cam}_depth.png")))
    if self.max_depth is not None:
      depth[depth > self.max_depth] = 0
    poses = self._poses(scene, cam)
    if int(idx) >= len(poses):
      raise ValueError(f"{os.path.join(d, f'pose_{cam}.txt')}: {len(poses)} poses, frame {idx} "
                       "has none")
    return posed.View(image, depth, tartanair_K(*depth.shape), poses[int(idx)])
