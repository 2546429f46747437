"""The embedded posed-scene dataset: procedural textured 3D scenes seen by two pinhole cameras.

Numpy only and deterministic by seed. A scene is a textured room (the inside of a box, so every
ray hits something) holding a few boxes and spheres; one of them optionally moves rigidly between
the two shots. Images are ray cast at pixel centres with z-depth; flow, covisibility and the
supervision masks come from `ufm_jax.geometry` (static: `correspondence_from_depth`, moving
object: `correspondence_from_rigid_objects`), exactly as for the posed real datasets.

Pair types: "flow" (small camera motion, optical-flow-like), "wide" (the camera orbits the scene
centre by 10..90 degrees of view change), "mixed" (either, half and half), "pan" (the camera
pans/tilts by `pan_angle_deg` with a small translation: a larger, mostly global image motion),
"shift" (no 3D scene: a smooth random texture and the same texture translated by an integer
(dx, dy) with |dx|, |dy| <= `max_shift`: the easiest matching task, for probing whether a model
trained from scratch learns to match at all; see configs/synthetic.py and
benchmarks/synthetic_learning.py), "layers" (a shift pair with a rectangle of another texture
drawn over it in both views, moving by its own integer shift: piecewise-constant flow with motion
boundaries, and background pixels the rectangle covers in the other view not covisible; the
flow's errors then differ pixel by pixel, which a flow uncertainty can rank, docs/uncertainty.md).

Textures are smooth solid textures (sums of random 3D sinusoids) evaluated in each object's own
frame, with the shading baked in the object frame, so a surface point looks the same in both
views and under the object's motion: warping image1 by the flow reproduces image0 on covisible
pixels up to interpolation error.

CLI (writes the pair-folder format read by the `pairs_folder` source, see data/pairs_folder/README.md):
  python -m ufm_jax.data.synthetic --out DIR --pairs N --seed S [--size HxW] [--pair-type mixed]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys

import numpy as np

from ufm_jax import geometry as geo
from ufm_jax.data import io

PAIR_TYPES = ("flow", "wide", "mixed", "pan", "shift", "layers")
_SPLITS = {"train": 0, "val": 1, "test": 2}
_EPS = 1e-6


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
  size: tuple[int, int] = (112, 112)      # (H, W)
  pair_type: str = "mixed"
  moving_object_prob: float = 0.5
  max_view_angle_deg: float = 90.0        # wide pairs: view change drawn in [10, this]
  min_view_angle_deg: float = 10.0
  pan_angle_deg: tuple[float, float] = (4.0, 10.0)  # pan pairs: rotation drawn in this range
  num_objects: tuple[int, int] = (3, 6)   # inclusive range
  max_shift: int = 10                     # shift/layers pairs: |dx|, |dy| <= this (pixels)
  # Shift pairs: this fraction moves by multiples of `aligned_shift_step` px (up to 2 steps), so a
  # token of a ViT with that patch size finds an identical token in the other view. A curriculum:
  # 0.5 shortened a minimal two-view ViT's plateau before it matches from ~1800 to ~1100 steps.
  aligned_shift_frac: float = 0.0
  aligned_shift_step: int = 7
  # 0 = the paper's covisibility rule; 0.5 removes most of its silhouette/grazing-angle false
  # negatives (see ufm_jax.geometry.covisibility_from_points).
  subpixel_search: float = 0.0

  def __post_init__(self):
    if self.pair_type not in PAIR_TYPES:
      raise ValueError(f"pair_type must be one of {PAIR_TYPES}, got {self.pair_type!r}")
    if len(self.size) != 2 or min(self.size) < 2:
      raise ValueError(f"size must be (H, W) with both >= 2, got {self.size!r}")
    if self.max_shift < 0 or not 0.0 <= self.aligned_shift_frac <= 1.0:
      raise ValueError(f"need max_shift >= 0 and aligned_shift_frac in [0, 1], got "
                       f"{self.max_shift}, {self.aligned_shift_frac}")


def parse_size(size) -> tuple[int, int]:
  """112 | (H, W) | "HxW" -> (H, W)."""
  if isinstance(size, str):
    parts = size.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
      raise ValueError(f"size must look like HxW (e.g. 112x112), got {size!r}")
    return int(parts[0]), int(parts[1])
  if isinstance(size, (int, np.integer)):
    return int(size), int(size)
  h, w = size
  return int(h), int(w)


# ----------------------------------------------------------------------------------------------
# Scene description


@dataclasses.dataclass
class Primitive:
  kind: str                 # "room" (seen from inside), "box", "sphere"
  pose0: np.ndarray         # object-to-world at time 0
  pose1: np.ndarray         # object-to-world at time 1 (== pose0 unless it moves)
  extent: np.ndarray        # box/room half sizes [3] or sphere radius [1]
  freqs: np.ndarray         # [n, 3] cycles per unit, solid texture
  phases: np.ndarray        # [n]
  amps: np.ndarray          # [n, 3] per colour channel
  base: np.ndarray          # [3]
  light: np.ndarray         # [3] unit light direction in the object frame (baked shading)
  blob_centers: np.ndarray  # [m, 3] on the surface: aperiodic landmarks for wide baselines
  blob_sigmas: np.ndarray   # [m]
  blob_colors: np.ndarray   # [m, 3]
  object_id: int            # 0 = static, 1 = the moving object


@dataclasses.dataclass
class Scene:
  primitives: list
  K0: np.ndarray
  K1: np.ndarray
  cam2world0: np.ndarray
  cam2world1: np.ndarray
  size: tuple
  pair_type: str
  moving: bool


def _rotation(rng, max_angle):
  axis = rng.normal(size=3)
  return geo.axis_angle_to_rotation(axis, rng.uniform(-max_angle, max_angle))


def _surface_points(rng, kind, extent, m):
  if kind == "sphere":
    d = rng.normal(size=(m, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * extent[0]
  p = rng.uniform(-1, 1, (m, 3)) * extent
  axis = rng.integers(0, 3, m)
  p[np.arange(m), axis] = rng.choice([-1.0, 1.0], m) * extent[axis]
  return p


def _texture(rng, scale, kind, extent, n_blobs):
  """Smooth solid texture: random 3D sinusoids (fine detail) + Gaussian colour blobs on the
  surface (aperiodic landmarks, so repeated sinusoid patterns are not ambiguous)."""
  n = 10
  direction = rng.normal(size=(n, 3))
  direction /= np.linalg.norm(direction, axis=1, keepdims=True)
  freqs = direction * rng.uniform(0.3, 2.4, size=(n, 1)) / scale
  amps = rng.uniform(-1, 1, size=(n, 3)) * rng.uniform(20, 70) / np.sqrt(n)
  amps += rng.uniform(-1, 1, size=(n, 1)) * 40 / np.sqrt(n)  # shared: luminance texture
  light = rng.normal(size=3)
  return dict(freqs=freqs, phases=rng.uniform(0, 2 * np.pi, n), amps=amps,
              base=rng.uniform(60, 200, 3), light=light / np.linalg.norm(light),
              blob_centers=_surface_points(rng, kind, extent, n_blobs),
              blob_sigmas=scale * rng.uniform(0.3, 0.9, n_blobs),
              blob_colors=rng.uniform(-90, 90, (n_blobs, 3)))


def _camera_K(rng, h, w):
  hfov = np.deg2rad(rng.uniform(50, 70))
  f = (w / 2) / np.tan(hfov / 2)
  cx = (w - 1) / 2 + rng.uniform(-0.03, 0.03) * w
  cy = (h - 1) / 2 + rng.uniform(-0.03, 0.03) * h
  return geo.intrinsics(f, f, cx, cy)


def _orbit_eye(target, dist, azim, elev):
  # World y points down (so look_at's default up = -y): positive elevation = camera above.
  return target + dist * np.array([np.cos(elev) * np.sin(azim), -np.sin(elev),
                                   np.cos(elev) * np.cos(azim)])


def _roll(c2w, angle):
  out = c2w.copy()
  out[:3, :3] = c2w[:3, :3] @ geo.axis_angle_to_rotation([0, 0, 1], angle)
  return out


def _bounding_radius(prim: Primitive) -> float:
  return float(np.linalg.norm(prim.extent)) if prim.kind == "box" else float(prim.extent[0])


def _clear_of(prims, eye, margin=0.3) -> bool:
  """The camera centre is at least `margin` outside every object's bounding sphere at both times."""
  for prim in prims:
    if prim.kind == "room":
      if (np.abs(eye) > prim.extent - margin).any():
        return False
      continue
    for pose in (prim.pose0, prim.pose1):
      if np.linalg.norm(eye - pose[:3, 3]) < _bounding_radius(prim) + margin:
        return False
  return True


def _cameras(rng, pair_type, config):
  target = rng.uniform(-0.5, 0.5, 3)
  dist, azim = rng.uniform(5, 7), rng.uniform(0, 2 * np.pi)
  elev = np.deg2rad(rng.uniform(-10, 40))
  c2w0 = _roll(geo.look_at(_orbit_eye(target, dist, azim, elev), target),
               np.deg2rad(rng.uniform(-10, 10)))
  if pair_type == "flow":
    eye1 = c2w0[:3, 3] + rng.normal(0, 0.12, 3)
    c2w1 = geo.pose_from_rt(c2w0[:3, :3] @ _rotation(rng, np.deg2rad(3)), eye1)
  elif pair_type == "pan":
    eye1 = c2w0[:3, 3] + rng.normal(0, 0.05, 3)
    # Axis in the camera's x-y plane (pan/tilt, no roll): the flow is close to a global shift.
    phi = rng.uniform(0, 2 * np.pi)
    angle = np.deg2rad(rng.uniform(*config.pan_angle_deg))
    rot = geo.axis_angle_to_rotation([np.cos(phi), np.sin(phi), 0.0], angle)
    c2w1 = geo.pose_from_rt(c2w0[:3, :3] @ rot, eye1)
  else:
    angle = np.deg2rad(rng.uniform(config.min_view_angle_deg, config.max_view_angle_deg))
    azim1 = azim + angle * rng.choice([-1, 1]) * rng.uniform(0.7, 1.0)
    elev1 = np.clip(elev + rng.uniform(-0.3, 0.3) * angle, np.deg2rad(-15), np.deg2rad(60))
    target1 = target + rng.uniform(-0.3, 0.3, 3)
    eye1 = _orbit_eye(target1, rng.uniform(5, 7), azim1, elev1)
    c2w1 = _roll(geo.look_at(eye1, target1), np.deg2rad(rng.uniform(-10, 10)))
  return c2w0, c2w1


def make_scene(seed, config: SyntheticConfig = SyntheticConfig()) -> Scene:
  """Draws a scene and a camera pair from `seed` (an int or a np.random.SeedSequence)."""
  rng = np.random.default_rng(seed)
  h, w = config.size
  half_room = rng.uniform(9, 12, 3)
  prims = [Primitive("room", np.eye(4), np.eye(4), half_room, object_id=0,
                     **_texture(rng, 2.0, "room", half_room, 32))]
  n_obj = int(rng.integers(config.num_objects[0], config.num_objects[1] + 1))
  for _ in range(n_obj):
    pos = rng.uniform(-1, 1, 3)
    pos *= rng.uniform(0, 2.0) / max(np.linalg.norm(pos), _EPS)
    pose = geo.pose_from_rt(_rotation(rng, np.pi), pos)
    kind = "box" if rng.uniform() < 0.6 else "sphere"
    extent = rng.uniform(0.3, 0.9, 3 if kind == "box" else 1)
    prims.append(Primitive(kind, pose, pose, extent, object_id=0,
                           **_texture(rng, 0.6 if kind == "box" else 0.5, kind, extent, 6)))
  pair_type = config.pair_type
  if pair_type == "mixed":
    pair_type = "wide" if rng.uniform() < 0.5 else "flow"
  moving = bool(rng.uniform() < config.moving_object_prob)
  if moving:
    obj = prims[1 + int(rng.integers(n_obj))]
    obj.object_id = 1
    shift = rng.normal(size=3)
    shift *= rng.uniform(0.05, 0.45) / np.linalg.norm(shift)
    motion = geo.pose_from_rt(_rotation(rng, np.deg2rad(20)), np.zeros(3))
    obj.pose1 = motion @ obj.pose0  # rotate about its centre, then shift
    obj.pose1[:3, 3] = obj.pose0[:3, 3] + shift

  for _ in range(100):  # redraw cameras that would sit inside (or touch) an object
    c2w0, c2w1 = _cameras(rng, pair_type, config)
    if all(_clear_of(prims, T[:3, 3]) for T in (c2w0, c2w1)):
      break
  else:
    raise RuntimeError(f"synthetic: no camera pair clear of the objects for seed {seed}")
  return Scene(prims, _camera_K(rng, h, w), _camera_K(rng, h, w), c2w0, c2w1, (h, w),
               pair_type, moving)


# ----------------------------------------------------------------------------------------------
# Ray casting


def _local_rays(pose, origin, dirs):
  R, tvec = pose[:3, :3], pose[:3, 3]
  return R.T @ (origin - tvec), dirs @ R  # d_local = R^T d


def _intersect(prim: Primitive, pose, origin, dirs):
  """Ray parameter t [N] of the first hit (inf = miss). dirs have camera z = 1, so t is the
  camera z-depth of the hit."""
  o, d = _local_rays(pose, origin, dirs)
  if prim.kind == "sphere":
    r = prim.extent[0]
    a = np.einsum("ij,ij->i", d, d)
    b = d @ o
    disc = b * b - a * (o @ o - r * r)
    ok = disc >= 0
    t = np.where(ok, (-b - np.sqrt(np.where(ok, disc, 0))) / a, np.inf)
    return np.where(t > _EPS, t, np.inf)
  inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
  t1, t2 = (-prim.extent - o) * inv, (prim.extent - o) * inv
  if prim.kind == "room":  # the camera is inside: the exit face
    return np.maximum(t1, t2).min(axis=1)
  tlo, thi = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
  return np.where((tlo <= thi) & (tlo > _EPS), tlo, np.inf)


def _surface(prim: Primitive, pose, origin, dirs, t):
  """Local hit points and local unit normals of the rays that hit `prim` at t."""
  o, d = _local_rays(pose, origin, dirs)
  p = o + t[:, None] * d
  if prim.kind == "sphere":
    return p, p / prim.extent[0]
  # The face hit is the axis where |p| reaches the half size (relative to the size).
  axis = np.argmax(np.abs(p) / prim.extent, axis=1)
  normal = np.zeros_like(p)
  rows = np.arange(len(p))
  side = np.sign(p[rows, axis])
  normal[rows, axis] = -side if prim.kind == "room" else side
  return p, normal


def _shade(prim: Primitive, p, normal):
  # float32 is plenty for a colour and halves the cost of the [N, waves] and [N, blobs] maps.
  f32 = lambda a: np.asarray(a, np.float32)
  p = f32(p)
  phase = f32(2 * np.pi) * (p @ f32(prim.freqs).T) + f32(prim.phases)
  color = f32(prim.base) + np.sin(phase) @ f32(prim.amps)
  c = f32(prim.blob_centers)
  d2 = (p * p).sum(1)[:, None] - 2 * p @ c.T + (c * c).sum(1)[None]
  color += np.exp(np.minimum(d2, 1e4) * f32(-0.5 / prim.blob_sigmas ** 2)) @ f32(prim.blob_colors)
  lambert = np.clip(f32(normal) @ f32(prim.light), 0, 1)
  return color * (0.6 + 0.4 * lambert)[:, None]


def render(scene: Scene, view: int):
  """Ray casts camera `view` (0 or 1) at time `view` -> (rgb uint8 [H,W,3], z-depth float64 [H,W],
  object id int32 [H,W] (0 static, 1 moving))."""
  h, w = scene.size
  K, c2w = (scene.K0, scene.cam2world0) if view == 0 else (scene.K1, scene.cam2world1)
  dirs = geo.rays(geo.pixel_grid(h, w), K).reshape(-1, 3) @ c2w[:3, :3].T
  origin = c2w[:3, 3]
  best = np.full(h * w, np.inf)
  which = np.zeros(h * w, np.int64)
  unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
  for i, prim in enumerate(scene.primitives):
    pose = prim.pose0 if view == 0 else prim.pose1
    rows = slice(None)
    if prim.kind != "room":  # only rays inside the cone of the bounding sphere can hit
      to_centre = pose[:3, 3] - origin
      dist, radius = np.linalg.norm(to_centre), _bounding_radius(prim)
      if dist > radius:
        cos_max = np.sqrt(1 - (radius / dist) ** 2)
        rows = np.flatnonzero(unit @ (to_centre / dist) >= cos_max - 1e-9)
    t = _intersect(prim, pose, origin, dirs[rows])
    closer = t < best[rows]
    best[rows] = np.where(closer, t, best[rows])
    which[rows] = np.where(closer, i, which[rows])
  rgb = np.zeros((h * w, 3))
  obj = np.zeros(h * w, np.int32)
  for i, prim in enumerate(scene.primitives):
    sel = np.flatnonzero(which == i)
    if len(sel):
      pose = prim.pose0 if view == 0 else prim.pose1
      p, normal = _surface(prim, pose, origin, dirs[sel], best[sel])
      rgb[sel] = _shade(prim, p, normal)
      obj[sel] = prim.object_id
  rgb = np.clip(np.round(rgb), 0, 255).astype(np.uint8).reshape(h, w, 3)
  return rgb, best.reshape(h, w), obj.reshape(h, w)


# ----------------------------------------------------------------------------------------------
# Labels


def _object_poses(scene: Scene, time: int) -> dict:
  poses = {0: np.eye(4)}
  for prim in scene.primitives:
    if prim.object_id == 1:
      poses[1] = prim.pose0 if time == 0 else prim.pose1
  return poses


def _direction(scene, views, src, tau, search):
  """Sample dict for view `src` -> view 1 - src."""
  dst = 1 - src
  (img_s, depth_s, seg_s), (img_d, depth_d, _) = views[src], views[dst]
  K = (scene.K0, scene.K1)
  c2w = (scene.cam2world0, scene.cam2world1)
  if scene.moving:
    corr = geo.correspondence_from_rigid_objects(
        depth_s, K[src], c2w[src], seg_s, _object_poses(scene, src),
        depth_d, K[dst], c2w[dst], _object_poses(scene, dst), *tau, subpixel_search=search)
  else:
    corr = geo.correspondence_from_depth(depth_s, K[src], c2w[src], depth_d, K[dst], c2w[dst],
                                         *tau, subpixel_search=search)
  labels = geo.labels_from_correspondence(corr)
  rel = c2w[src][:3, :3].T @ c2w[dst][:3, :3]
  meta = dict(dataset="synthetic", pair_type=scene.pair_type, moving_object=scene.moving,
              frame0=src, frame1=dst, K0=K[src], K1=K[dst], cam2world0=c2w[src],
              cam2world1=c2w[dst], depth0=depth_s.astype(np.float32),
              depth1=depth_d.astype(np.float32), segmentation0=seg_s,
              view_angle_deg=float(np.rad2deg(geo.rotation_angle(rel))))
  return dict(image0=img_s, image1=img_d, **labels, meta=meta)


def _smooth_texture(rng, h, w):
  """uint8 [h, w, 3]: blurred noise at three scales (fine detail, blobs, shading)."""
  import cv2
  tex = np.zeros((h, w, 3), np.float32)
  for sigma, amp in ((1.5, 30.0), (4.0, 50.0), (10.0, 60.0)):
    noise = cv2.GaussianBlur(rng.normal(size=(h, w, 3)).astype(np.float32), (0, 0), sigma)
    tex += amp * noise / (noise.std() + 1e-6)
  return np.clip(128 + tex, 0, 255).astype(np.uint8)


def _shift_pair(seed, config: SyntheticConfig, directions):
  """Shift pairs (see the module docstring): image1(p + d) = image0(p) exactly, flow = d, and a
  pixel is covisible where p + d stays inside the image."""
  rng = np.random.default_rng(seed)
  h, w = config.size
  step = config.aligned_shift_step
  pad = max(config.max_shift, 2 * step if config.aligned_shift_frac else 0) + 1
  tex = _smooth_texture(rng, h + 2 * pad, w + 2 * pad)
  d = rng.integers(-config.max_shift, config.max_shift + 1, 2)
  if config.aligned_shift_frac and rng.uniform() < config.aligned_shift_frac:
    d = rng.integers(-2, 3, 2) * step
  views = (tex[pad:pad + h, pad:pad + w], tex[pad - d[1]:pad - d[1] + h, pad - d[0]:pad - d[0] + w])
  v, u = np.mgrid[0:h, 0:w]
  out = []
  for src in directions:
    dd = d if src == 0 else -d
    covis = (u + dd[0] >= 0) & (u + dd[0] < w) & (v + dd[1] >= 0) & (v + dd[1] < h)
    meta = dict(dataset="synthetic", pair_type="shift", moving_object=False, frame0=src,
                frame1=1 - src, shift=dd.tolist())
    out.append(dict(image0=views[src], image1=views[1 - src], covisibility=covis,
                    flow=np.broadcast_to(dd.astype(np.float32), (h, w, 2)).copy(),
                    flow_valid=np.ones((h, w), bool), covis_valid=np.ones((h, w), bool),
                    meta=meta))
  return tuple(out)


def _layers_pair(seed, config: SyntheticConfig, directions):
  """Layers pairs (see the module docstring): a background texture shifted by d0 and, on top of
  it in both views, a rectangle of another texture at R in view 0 and R + d1 in view 1. A pixel
  of the rectangle moves by d1 and is covisible where it stays in the image; a background pixel
  moves by d0 and is covisible where it lands in the image outside the other view's rectangle."""
  rng = np.random.default_rng(seed)
  h, w = config.size
  m = config.max_shift
  pad = m + 1
  background = _smooth_texture(rng, h + 2 * pad, w + 2 * pad)
  d0 = rng.integers(-m, m + 1, 2)
  d1 = rng.integers(-m, m + 1, 2)
  rh, rw = int(rng.integers(h // 4, h // 2 + 1)), int(rng.integers(w // 4, w // 2 + 1))
  top, left = int(rng.integers(0, h - rh + 1)), int(rng.integers(0, w - rw + 1))
  patch = _smooth_texture(rng, h, w)[:rh, :rw]  # the background's statistics, not a small blur's
  rects = ((top, left), (top + int(d1[1]), left + int(d1[0])))  # (top, left) in view 0, view 1

  def inside(view, x, y):
    t, l = rects[view]
    return (x >= l) & (x < l + rw) & (y >= t) & (y < t + rh)

  v, u = np.mgrid[0:h, 0:w]
  views = []
  for view, d in ((0, np.zeros(2, int)), (1, d0)):
    img = background[pad - d[1]:pad - d[1] + h, pad - d[0]:pad - d[0] + w].copy()
    on = inside(view, u, v)
    t, l = rects[view]
    img[on] = patch[v[on] - t, u[on] - l]
    views.append(img)
  out = []
  for src in directions:
    sign = 1 if src == 0 else -1
    front = inside(src, u, v)
    flow = np.where(front[..., None], sign * d1, sign * d0).astype(np.float32)
    x, y = u + flow[..., 0].astype(int), v + flow[..., 1].astype(int)
    in_view = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    covis = in_view & (front | ~inside(1 - src, x, y))
    meta = dict(dataset="synthetic", pair_type="layers", moving_object=True, frame0=src,
                frame1=1 - src, shift=(sign * d0).tolist(), layer_shift=(sign * d1).tolist(),
                layer_rect=[rects[src][0], rects[src][1], rh, rw])
    out.append(dict(image0=views[src], image1=views[1 - src], covisibility=covis, flow=flow,
                    flow_valid=np.ones((h, w), bool), covis_valid=np.ones((h, w), bool),
                    meta=meta))
  return tuple(out)


def generate_pair(seed, config: SyntheticConfig = SyntheticConfig(), directions=(0, 1)):
  """Renders the pair drawn by `seed` -> one sample dict per entry of `directions`
  (0: view 0 -> view 1, the forward pair; 1: view 1 -> view 0, the backward pair)."""
  if config.pair_type == "shift":
    return _shift_pair(seed, config, directions)
  if config.pair_type == "layers":
    return _layers_pair(seed, config, directions)
  scene = make_scene(seed, config)
  views = [render(scene, 0), render(scene, 1)]
  tau = geo.COVIS_THRESHOLDS["synthetic"]
  return tuple(_direction(scene, views, d, tau, config.subpixel_search) for d in directions)


def pair_seed(seed: int, split: str, index: int) -> np.random.SeedSequence:
  """Per-pair seed; train/val/test streams are disjoint by construction (split is a spawn key)."""
  if split not in _SPLITS:
    raise ValueError(f"split must be one of {sorted(_SPLITS)}, got {split!r}")
  return np.random.SeedSequence([int(seed), _SPLITS[split], int(index)])


# ----------------------------------------------------------------------------------------------
# Writing the pair-folder format


def _write_labels(folder, sample):
  io.write_flo(os.path.join(folder, "flow.flo"), sample["flow"])
  for key in ("covisibility", "flow_valid", "covis_valid"):
    io.write_image(os.path.join(folder, f"{key}.png"), np.asarray(sample[key], np.uint8) * 255)


def _jsonable(meta):
  out = {}
  for k, v in meta.items():
    if k in ("depth0", "depth1", "segmentation0"):
      continue
    out[k] = v.tolist() if isinstance(v, np.ndarray) else v
  return out


def write_pair(folder: str, forward: dict, backward: dict | None = None, extra_meta=None):
  """Writes one pair folder atomically: everything goes to a temp folder renamed at the end."""
  parent = os.path.dirname(os.path.abspath(folder))
  tmp = os.path.join(parent, f".{os.path.basename(folder)}.tmp{os.getpid()}")
  shutil.rmtree(tmp, ignore_errors=True)
  os.makedirs(tmp)
  io.write_image(os.path.join(tmp, "image0.png"), forward["image0"])
  io.write_image(os.path.join(tmp, "image1.png"), forward["image1"])
  _write_labels(tmp, forward)
  meta = _jsonable(forward["meta"])
  meta.update(extra_meta or {})
  if backward is not None:
    os.makedirs(os.path.join(tmp, "reverse"))
    _write_labels(os.path.join(tmp, "reverse"), backward)
  if "depth0" in forward["meta"]:  # shift pairs have no scene, hence no depth
    np.savez_compressed(os.path.join(tmp, "depth.npz"), depth0=forward["meta"]["depth0"],
                        depth1=forward["meta"]["depth1"])
  with open(os.path.join(tmp, "meta.json"), "w") as f:
    json.dump(meta, f, indent=1)
  if os.path.exists(folder):
    shutil.rmtree(folder)
  os.replace(tmp, folder)


def main(argv=None):
  parser = argparse.ArgumentParser(
      prog="python -m ufm_jax.data.synthetic",
      description="Write synthetic pairs in the pair-folder format (see data/pairs_folder/README.md).")
  parser.add_argument("--out", required=True, help="output folder (one sub-folder per pair)")
  parser.add_argument("--pairs", type=int, required=True, help="number of pairs")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--size", default="112x112", help="HxW, e.g. 112x112 or 224x336")
  parser.add_argument("--split", default="train", choices=sorted(_SPLITS))
  parser.add_argument("--pair-type", default="mixed", choices=PAIR_TYPES)
  parser.add_argument("--moving-object-prob", type=float, default=0.5)
  parser.add_argument("--no-reverse", action="store_true",
                      help="do not write the reverse (1 -> 0) labels in <pair>/reverse/")
  args = parser.parse_args(argv)
  from tqdm import tqdm
  config = SyntheticConfig(size=parse_size(args.size), pair_type=args.pair_type,
                           moving_object_prob=args.moving_object_prob)
  os.makedirs(args.out, exist_ok=True)
  for i in tqdm(range(args.pairs), desc="synthetic pairs", unit="pair"):
    fwd, bwd = generate_pair(pair_seed(args.seed, args.split, i), config)
    write_pair(os.path.join(args.out, f"{i:06d}"), fwd, None if args.no_reverse else bwd,
               extra_meta=dict(seed=args.seed, split=args.split, index=i))
  return 0


if __name__ == "__main__":
  sys.exit(main())
