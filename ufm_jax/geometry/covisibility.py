"""Correspondence and covisibility from depth and poses (supplementary "Computing Covisibility Mask").

A source pixel i_s with 3D point p_s (at the target time) projects to the fractional target pixel
i_t. It is covisible iff p_s is in front of camera 2, i_t lies inside image 2, and the depth
reprojection error
    e = | ||p_s - O_2|| - D_2(i_t) |  <  tau_d + tau_r * ||p_s - O_2||
where D_2 is the target *range* map (distance to O_2, i.e. z-depth * ||K^-1 [u, v, 1]||) sampled
bilinearly at i_t. Because p_s, p_t = the target surface point seen at i_t, and O_2 are collinear,
e = ||p_s - p_t||, the 3D distance of the paper's eq. S.1. Bilinear sampling only mixes valid
target depths (weights renormalised); with no valid neighbour the pixel is not covisible.
The threshold is the paper's (no temperature term; tartanairpy adds -ln(0.5) * 0.1 on top).
"""

from __future__ import annotations

import numpy as np

from ufm_jax.geometry import camera

# Points closer than this to the target image plane (scene units) count as behind the camera.
MIN_Z = 1e-6


def bilinear_sample(image: np.ndarray, uv: np.ndarray, valid: np.ndarray | None = None):
  """Samples image [H, W] (or [H, W, C]) at fractional pixel centres uv [..., 2].

  Coordinates are clamped to the border (so the half-pixel margin -0.5..0 repeats the edge).
  With `valid` [H, W], only valid neighbours contribute and weights are renormalised.
  Returns (values [...] or [..., C], ok [...]) where ok = some valid neighbour had weight > 0.
  """
  image = np.asarray(image, np.float64)
  h, w = image.shape[:2]
  uv = np.asarray(uv, np.float64)
  finite = np.isfinite(uv).all(axis=-1)
  u = np.clip(np.where(finite, uv[..., 0], 0.0), 0.0, w - 1)
  v = np.clip(np.where(finite, uv[..., 1], 0.0), 0.0, h - 1)
  x0 = np.minimum(np.floor(u).astype(np.int64), max(w - 2, 0))
  y0 = np.minimum(np.floor(v).astype(np.int64), max(h - 2, 0))
  x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
  fx, fy = u - x0, v - y0
  corners = ((y0, x0, (1 - fx) * (1 - fy)), (y0, x1, fx * (1 - fy)),
             (y1, x0, (1 - fx) * fy), (y1, x1, fx * fy))
  if valid is None:
    valid = np.ones((h, w), bool)
  values = np.where(valid.reshape(valid.shape + (1,) * (image.ndim - 2)), image, 0.0)
  values = np.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0)
  acc = np.zeros(uv.shape[:-1] + image.shape[2:])
  wsum = np.zeros(uv.shape[:-1])
  for yy, xx, wt in corners:
    wt = wt * valid[yy, xx]
    wsum += wt
    acc += values[yy, xx] * wt.reshape(wt.shape + (1,) * (image.ndim - 2))
  ok = finite & (wsum > 1e-9)
  safe = np.where(ok, wsum, 1.0)
  return acc / safe.reshape(safe.shape + (1,) * (image.ndim - 2)), ok


def nearest_sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
  """Nearest-pixel lookup at uv [..., 2] (pixel centres at integers; clamped to the border)."""
  image = np.asarray(image)
  h, w = image.shape[:2]
  uv = np.nan_to_num(np.asarray(uv, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
  x = np.clip(np.floor(uv[..., 0] + 0.5), 0, w - 1).astype(np.int64)
  y = np.clip(np.floor(uv[..., 1] + 0.5), 0, h - 1).astype(np.int64)
  return image[y, x]


def inside_image(uv: np.ndarray, height: int, width: int) -> np.ndarray:
  """-0.5 <= u < W - 0.5 and -0.5 <= v < H - 0.5 (the pixel areas; nan -> False)."""
  u, v = uv[..., 0], uv[..., 1]
  with np.errstate(invalid="ignore"):
    return (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)


def covisibility_from_points(points_world: np.ndarray, valid0: np.ndarray, depth1: np.ndarray,
                             K1: np.ndarray, cam2world1: np.ndarray, tau_d: float, tau_r: float,
                             subpixel_search: float = 0.0):
  """Core shared by static scenes, rigid objects and scene flow.

  points_world: [H, W, 3] the 3D point of every source pixel, moved to the target time.
  valid0: [H, W] where those points are defined (source depth valid).
  Returns dict(flow [H,W,2] float32, covisibility, fov_mask, valid, valid_other, in_front, error):
    fov_mask    = valid0 and in front of camera 2 and inside image 2 (regardless of occlusion);
    valid_other = fov_mask and target depth valid at the nearest target pixel (V_other);
    in_front    = valid0 and z > 0 in camera 2: where the flow is geometrically defined;
    error       = e (inf where not evaluated).
  Flow is 0 where not in_front.
  subpixel_search = r > 0 also accepts a pixel when the error test passes at one of the 8 target
  locations offset by (+-r, 0, +-r) px: a grid-search stand-in for tartanairpy's sub-pixel offset
  optimisation, which removes most of the false "not covisible" band that bilinear depth mixing
  leaves along silhouettes and creases. 0 (default) is the paper's rule.
  """
  points_world = np.asarray(points_world, np.float64)
  valid0 = np.asarray(valid0, bool)
  depth1 = np.asarray(depth1, np.float64)
  if depth1.ndim != 2:
    raise ValueError(f"target depth must be [H, W], got shape {depth1.shape}")
  h0, w0 = points_world.shape[:2]
  h1, w1 = depth1.shape
  pc = camera.transform(camera.invert_pose(cam2world1), points_world)
  uv, z = camera.project(pc, K1)
  with np.errstate(invalid="ignore"):
    in_front = valid0 & np.isfinite(pc).all(-1) & (z > MIN_Z) & np.isfinite(uv).all(-1)
  fov = in_front & inside_image(uv, h1, w1)
  valid1 = camera.valid_depth(depth1)
  range1 = np.where(valid1, depth1, 0.0) * camera.ray_norms(h1, w1, K1)
  uv_safe = np.where(in_front[..., None], uv, 0.0)
  sampled, ok = bilinear_sample(range1, uv_safe, valid1)
  expected = np.linalg.norm(np.where(in_front[..., None], pc, 0.0), axis=-1)
  error = np.where(fov & ok, np.abs(expected - sampled), np.inf)
  threshold = tau_d + tau_r * expected
  covis = fov & ok & (error < threshold)
  if subpixel_search > 0:
    todo = np.flatnonzero(fov & ~covis)
    uv_t = uv_safe.reshape(-1, 2)[todo]
    want, thr = expected.reshape(-1)[todo], threshold.reshape(-1)[todo]
    found = np.zeros(len(todo), bool)
    for dx in (-subpixel_search, 0.0, subpixel_search):
      for dy in (-subpixel_search, 0.0, subpixel_search):
        if dx or dy:
          val, ok_t = bilinear_sample(range1, uv_t + (dx, dy), valid1)
          found |= ok_t & (np.abs(want - val) < thr)
    covis = covis.copy()
    covis.reshape(-1)[todo[found]] = True
  valid_other = fov & nearest_sample(valid1, uv_safe)
  flow = np.where(in_front[..., None], uv_safe - camera.pixel_grid(h0, w0), 0.0)
  return dict(flow=flow.astype(np.float32), covisibility=covis, fov_mask=fov, valid=valid0,
              valid_other=valid_other, in_front=in_front, error=error)


def _check_depth(name, depth):
  depth = np.asarray(depth)
  if depth.ndim != 2:
    raise ValueError(f"{name} must be an [H, W] depth map, got shape {depth.shape}")
  return depth


def correspondence_from_depth(depth0, K0, cam2world0, depth1, K1, cam2world1,
                              tau_d: float, tau_r: float, subpixel_search: float = 0.0):
  """Static scene: flow 0->1 and covisibility from z-depths, intrinsics and OpenCV c2w poses.

  Invalid depths (0, inf, nan) mark pixels without ground truth: invalid source pixels get
  valid=False (and flow 0, all masks False); invalid target pixels never confirm covisibility.
  Returns the dict of `covisibility_from_points` (see there for `subpixel_search`).
  """
  depth0 = _check_depth("depth0", depth0)
  _check_depth("depth1", depth1)
  for name, K in (("K0", K0), ("K1", K1)):
    if np.shape(K) != (3, 3):
      raise ValueError(f"{name} must be [3, 3], got shape {np.shape(K)}")
  for name, T in (("cam2world0", cam2world0), ("cam2world1", cam2world1)):
    if np.shape(T) != (4, 4):
      raise ValueError(f"{name} must be [4, 4], got shape {np.shape(T)}")
  valid0 = camera.valid_depth(depth0)
  points = camera.transform(cam2world0, camera.unproject(np.where(valid0, depth0, 0.0), K0))
  return covisibility_from_points(points, valid0, depth1, K1, cam2world1, tau_d, tau_r,
                                  subpixel_search)
