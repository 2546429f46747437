"""Covisibility for scene-flow datasets (FlyingThings3D, Monkaa) and flow-only FoV masks.

Supplementary "Computing Covisibility Mask", paragraph "Optical (Scene) Flow": the 3D point seen
at source pixel i_s moves to target pixel i_t = i_s + flow(i_s) with its depth changed to
D1(i_s) + D_{1->2}(i_s). It is covisible when it lands inside the target image, in front of the
camera, and its expected distance to the target camera centre agrees with the target depth map
bilinearly interpolated at i_t:

  e = | ||p_{s,1->2} - O_2|| - D_2(i_t) |  <  tau_d + tau_r * ||p_{s,1->2} - O_2||.

Distances are Euclidean ranges (z-depth times the norm of K^-1 [u, v, 1]), as in the static-scene
rule; the target z-depth is converted to range before interpolation. Scene-flow datasets store
disparity d, not depth: z = f * B / d, and the disparity change gives the moved point's disparity
d + d_change (so the depth change of the formula is f B / (d + d_change) - f B / d).

Conventions: pixel (u, v) = (column, row), pixel centres at integer coordinates, a location is in
view when -0.5 <= u < W - 0.5 and -0.5 <= v < H - 0.5.

The training labels follow the official preprocess instead (`official_sceneflow_covisibility`:
z-depths, zero-padded lookups, a temperature term); this rule is the supplementary's.
"""

from __future__ import annotations

import cv2
import numpy as np

# Supplementary Table S1, "Scene flow + reprojection threshold" rows: (tau_d, tau_r) in scene units.
SCENEFLOW_THRESHOLDS = {"flyingthings": (0.01, 0.001), "monkaa": (0.01, 0.001)}

# FlyingThings3D / Monkaa virtual camera: focal 1050 px at 960x540 (35 mm lens, 32 mm sensor) and a
# stereo baseline of 1 scene unit, so depth = 1050 / disparity (as public scene-flow loaders do).
SCENEFLOW_FOCAL = 1050.0
SCENEFLOW_BASELINE = 1.0


def sceneflow_intrinsics(height: int, width: int, focal: float = SCENEFLOW_FOCAL) -> np.ndarray:
  """Pinhole K with the principal point at the image centre (pixel-centre convention)."""
  return np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0, 0, 1]],
                  np.float64)


def fov_mask(flow: np.ndarray) -> np.ndarray:
  """[H, W] bool: flow finite and the target location x + flow inside the image."""
  h, w = flow.shape[:2]
  u = np.arange(w, dtype=np.float32)[None, :] + flow[..., 0]
  v = np.arange(h, dtype=np.float32)[:, None] + flow[..., 1]
  # NaN compares False, so non-finite flow is out of view.
  with np.errstate(invalid="ignore"):
    return (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)


def fill_invalid(flow: np.ndarray, valid: np.ndarray, fill: float = 0.0) -> np.ndarray:
  """float32 copy of flow [H, W, C] with `fill` where not valid [H, W]: np.where(valid[..., None],
  flow, fill), one channel plane at a time (numpy's broadcast over a trailing axis of 2 is ~4x
  slower)."""
  out = np.empty(np.shape(flow), np.float32)
  for c in range(out.shape[-1]):
    out[..., c] = np.where(valid, flow[..., c], np.float32(fill))
  return out


def _ray_norm(u, v, K):
  """||K^-1 [u, v, 1]|| for a pinhole K without skew."""
  x = (u - np.float32(K[0, 2])) * np.float32(1.0 / K[0, 0])
  y = (v - np.float32(K[1, 2])) * np.float32(1.0 / K[1, 1])
  return np.sqrt(x * x + y * y + np.float32(1.0))


def _bilinear(img: np.ndarray, valid_f: np.ndarray, valid_u8: np.ndarray, u: np.ndarray,
              v: np.ndarray):
  """Samples img at (u, v); where a neighbour with weight is invalid, falls back to nearest.

  img: contiguous float32 [H, W]; valid_f / valid_u8: its validity as float32 / uint8.
  Coordinates in the half-pixel border band are clamped to the outermost centres. OpenCV's remap
  is ~15x faster than numpy gathers here; it quantises the sub-pixel position to 1/32 px, i.e. an
  interpolation error below |depth gradient| / 64 per pixel, far under the Table S1 thresholds.
  Returns (value, nearest_valid).
  """
  h, w = img.shape
  uc = np.clip(u, 0, w - 1).astype(np.float32, copy=False)
  vc = np.clip(v, 0, h - 1).astype(np.float32, copy=False)
  val = cv2.remap(img, uc, vc, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
  frac_valid = cv2.remap(valid_f, uc, vc, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
  nearest = cv2.remap(img, uc, vc, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
  nearest_valid = cv2.remap(valid_u8, uc, vc, cv2.INTER_NEAREST,
                            borderMode=cv2.BORDER_REPLICATE) > 0
  return np.where(frac_valid > 0.999, val, nearest), nearest_valid


# Source rows are processed in blocks of about this many pixels so the temporaries stay cached.
_BLOCK_PIXELS = 1 << 15


def sceneflow_covisibility(flow: np.ndarray, disparity0: np.ndarray, disparity_change: np.ndarray,
                           disparity1: np.ndarray, tau_d: float, tau_r: float,
                           K: np.ndarray | None = None, baseline: float = SCENEFLOW_BASELINE):
  """Covisibility of source pixels from optical flow, disparity and disparity change.

  Args:
    flow: [H, W, 2] source -> target flow in pixels.
    disparity0: [H, W] source disparity (> 0 valid).
    disparity_change: [H, W] disparity of the moved point at the target time minus disparity0.
    disparity1: [H, W] target disparity (> 0 valid).
    tau_d, tau_r: absolute and relative thresholds (supplementary Table S1).
    K: [3, 3] intrinsics shared by both frames (default: `sceneflow_intrinsics`).
    baseline: stereo baseline; depth = K[0, 0] * baseline / disparity.

  Returns dict of [H, W] arrays: covisibility (bool), fov_mask (bool, F1: lands in view in front of
  the camera), valid (bool, V1: source depth valid), covis_valid (bool, V_covis =
  (V1 & ~F1) | (F1 & V_other)), error (float32 range error, inf outside F1), depth0 and depth1
  (float32 z-depth, 0 where invalid).
  """
  flow = np.asarray(flow, np.float32)
  h, w = flow.shape[:2]
  for name, a in (("disparity0", disparity0), ("disparity_change", disparity_change),
                  ("disparity1", disparity1)):
    if np.shape(a) != (h, w):
      raise ValueError(f"sceneflow_covisibility: {name} has shape {np.shape(a)}, expected {(h, w)}")
  K = sceneflow_intrinsics(h, w) if K is None else np.asarray(K, np.float64)
  fb = np.float32(K[0, 0] * baseline)
  d0 = np.asarray(disparity0, np.float32)
  d1 = np.asarray(disparity1, np.float32)
  dm = d0 + np.asarray(disparity_change, np.float32)  # disparity of the moved point
  with np.errstate(invalid="ignore", divide="ignore"):
    valid0 = np.isfinite(d0) & (d0 > 0)
    valid1 = np.isfinite(d1) & (d1 > 0)
    depth0 = np.where(valid0, fb / d0, np.float32(0))
    depth1 = np.where(valid1, fb / d1, np.float32(0))
    moved_ok = valid0 & np.isfinite(dm) & (dm > 0)  # positive disparity = in front of the camera
    z_moved = np.where(moved_ok, fb / dm, np.float32(0))

  grid_norm = _ray_norm(np.arange(w, dtype=np.float32)[None, :],
                        np.arange(h, dtype=np.float32)[:, None], K)
  target = (np.ascontiguousarray(depth1 * grid_norm, np.float32), valid1.astype(np.float32),
            valid1.astype(np.uint8))
  fov, covisible, covis_valid = (np.empty((h, w), bool) for _ in range(3))
  error = np.empty((h, w), np.float32)
  grid_u = np.arange(w, dtype=np.float32)[None, :]
  step = max(1, _BLOCK_PIXELS // max(w, 1))
  for r0 in range(0, h, step):
    r1 = min(h, r0 + step)
    u = grid_u + flow[r0:r1, :, 0]
    v = np.arange(r0, r1, dtype=np.float32)[:, None] + flow[r0:r1, :, 1]
    # In view (as fov_mask; NaN compares False) and in front of the camera.
    with np.errstate(invalid="ignore"):
      view = (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5) & moved_ok[r0:r1]
    # Keep out-of-view samples inside the array; their result is masked by `view` below (so
    # where the flow is NaN any in-range position will do: fmax/fmin map NaN to the bound).
    u_s = np.fmin(np.fmax(u, np.float32(-0.5)), np.float32(w - 0.5))
    v_s = np.fmin(np.fmax(v, np.float32(-0.5)), np.float32(h - 0.5))
    observed, other_valid = _bilinear(*target, u_s, v_s)
    expected = z_moved[r0:r1] * _ray_norm(u_s, v_s, K)
    err = np.where(view, np.abs(expected - observed), np.float32(np.inf))
    other_valid &= view
    np.logical_and(other_valid,
                   err < np.float32(tau_d) + np.float32(tau_r) * expected, out=covisible[r0:r1])
    np.logical_or(valid0[r0:r1] & ~view, other_valid, out=covis_valid[r0:r1])
    fov[r0:r1], error[r0:r1] = view, err
  return dict(covisibility=covisible, fov_mask=fov, valid=valid0, covis_valid=covis_valid,
              error=error.astype(np.float32, copy=False), depth0=depth0.astype(np.float32, copy=False),
              depth1=depth1.astype(np.float32, copy=False))


def official_sceneflow_covisibility(flow, disparity0, disparity_change, disparity1, params,
                                   K=None, baseline: float = SCENEFLOW_BASELINE) -> dict:
  """The official preprocess's scene-flow labels (preprocess_flyingthings.py:385-433, 485-604;
  preprocess_monkaa.py the same), params = (absolute, temperature, relative), officially
  (0.01, 0.01, 0.001). Unlike the supplementary's rule above: z-depths are compared, not ranges;
  the target is in view iff 0 <= x + u < W and 0 <= y + v < H (no half-pixel margin, no in-front
  test); the target depth is sampled bilinearly with zero padding (holes and the border pull
  samples towards 0); the threshold has the temperature term. Its `opt_iters=1` has no effect
  (the uv residual is never re-read). The official forward direction reads the backward
  direction's projections for its supervision mask (the loop variables of :583-597); with valid
  depth everywhere, as in FlyingThings3D and Monkaa, that gives the mask computed here.
  Returns the dict of `sceneflow_covisibility`, error on z-depth."""
  flow = np.asarray(flow, np.float32)
  h, w = flow.shape[:2]
  for name, a in (("disparity0", disparity0), ("disparity_change", disparity_change),
                  ("disparity1", disparity1)):
    if np.shape(a) != (h, w):
      raise ValueError(f"sceneflow_covisibility: {name} has shape {np.shape(a)}, expected {(h, w)}")
  K = sceneflow_intrinsics(h, w) if K is None else np.asarray(K, np.float64)
  fb = np.float32(K[0, 0] * baseline)
  d0 = np.asarray(disparity0, np.float32)
  d1 = np.asarray(disparity1, np.float32)
  with np.errstate(invalid="ignore", divide="ignore"):
    valid0 = np.isfinite(d0) & (d0 > 0)
    valid1 = np.isfinite(d1) & (d1 > 0)
    depth0 = np.where(valid0, fb / d0, np.float32(0))
    depth1 = np.where(valid1, fb / d1, np.float32(0))
    expected = fb / (d0 + np.asarray(disparity_change, np.float32))   # z of the moved point
  expected = np.where(np.isfinite(expected), expected, np.float32(np.inf)).astype(np.float32)
  absolute, temperature, relative = (np.float32(p) for p in params)
  bias = absolute - np.float32(np.log(0.5)) * temperature
  from ufm_jax.geometry.covisibility import _ZeroPaddedRange  # pylint: disable=g-import-not-at-top
  target = _ZeroPaddedRange(depth1)
  u = np.arange(w, dtype=np.float32)[None, :] + flow[..., 0]
  v = np.arange(h, dtype=np.float32)[:, None] + flow[..., 1]
  with np.errstate(invalid="ignore"):
    view = valid0 & (u >= 0) & (u < w) & (v >= 0) & (v < h)
  us = np.where(view, u, 0).astype(np.float64)
  vs = np.where(view, v, 0).astype(np.float64)
  observed, other_valid = target.sample(us, vs)
  with np.errstate(invalid="ignore"):
    err = np.where(view, np.abs(observed - expected), np.float32(np.inf)).astype(np.float32)
    covisible = view & (err < bias + relative * expected)
  other_valid &= view
  return dict(covisibility=covisible, fov_mask=view, valid=valid0,
              covis_valid=(valid0 & ~view) | other_valid, error=err, depth0=depth0,
              depth1=depth1)
