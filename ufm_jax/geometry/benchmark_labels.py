"""Flow and covisibility labels of a posed static pair as the UFM benchmark branch computes them.

The ETH3D and DTU dense benches of the official benchmark branch (etola/UFM `benchmark`, 2a949e5)
label their pairs with `static_flow_postprocessing_pathway` ->
`flow_occlusion_post_processing` (uniflowmatch/datasets/base/flow_postprocessing.py:237-249,
544-714). `branch_static_labels` reproduces it in float32 numpy, for `--protocol official`.
It is not the rule of ufm_jax.geometry.covisibility (the paper's, used for training) in four ways:

  * threshold: tau = a + r * d - ln(0.5) * T, with d = ||p_s - O_2|| (lines 621-627): the
    "temperature" T adds ln(2) T, so ETH3D's (a, T, r) = (0.1, 0.1, 0.005) m gives
    0.169 + 0.005 d and DTU's (12, 12, 0.01) mm gives 20.318 + 0.01 d;
  * the target range map is sampled bilinearly with zero padding (grid_sample, align_corners
    False, after clipping the normalised coordinates to [-1, 1]; lines 444-480): invalid (0)
    target depths and the area beyond the border mix into the sample as zeros;
  * occluded iff error >= tau (line 661);
  * the in-view test is -0.5 <= u < W - 0.5, -0.5 <= v < H - 0.5 and z > 0
    (uniflowmatch/utils/geometry.py:417-420), and masks then drop invalid source depths
    (lines 711-714).

The ETH3D bench runs the pathway with its default `opt_iters=2` (two Adam steps on a sub-pixel
offset meant to lower the reprojection error). Those steps change no label: the offset is added
once, `valid_uv = valid_uv + uv_residual` (line 642), while it is still zero; `opt.step()` (line
679) then updates `uv_residual` in place, but the later passes re-slice the `valid_uv` tensor
computed before the step (line 686), so they re-test the same positions on the pixels already
found occluded, which stay occluded. They are therefore left out here.
"""

from __future__ import annotations

import numpy as np

_F = np.float32

# (a, T, r) of `flow_occlusion_post_processing` per bench, in the units of the branch's data:
# ETH3D metres (the pathway's defaults, widebaseline_datasets.py:126), DTU millimetres
# (widebaseline_datasets.py:160-168).
BRANCH_THRESHOLDS = {"eth3d": (0.1, 0.1, 0.005), "dtu": (12.0, 12.0, 0.01)}


def branch_threshold(a: float, temperature: float, r: float, distance):
  """tau(d) = a + r * d - ln(0.5) * T, float32 like the branch's tensors."""
  return _F(a) + _F(r) * np.asarray(distance, _F) + _F(-np.log(0.5) * temperature)


def _grid_coords(u, v, w: int, h: int):
  """Pixel coordinates -> grid_sample's unnormalised input coordinates: (uv + 0.5) / size * 2 - 1
  clipped to [-1, 1] (flow_postprocessing.py:444-450), then ((g + 1) * size - 1) / 2
  (align_corners=False), all float32."""
  out = []
  for x, n in ((u, w), (v, h)):
    g = np.clip((np.asarray(x, _F) + _F(0.5)) / _F(n) * _F(2) - _F(1), _F(-1), _F(1))
    out.append(((g + _F(1)) * _F(n) - _F(1)) / _F(2))
  return out


def sample_bilinear_zeros(image: np.ndarray, u, v) -> np.ndarray:
  """grid_sample(bilinear, padding zeros, align_corners=False) of [H, W] `image` at pixel coords."""
  h, w = image.shape
  ix, iy = _grid_coords(u, v, w, h)
  x0, y0 = np.floor(ix), np.floor(iy)
  # ATen's weights: (x0 + 1 - x) and (x - x0), corners summed nw, ne, sw, se.
  wxs, wys = ((x0 + _F(1)) - ix, ix - x0), ((y0 + _F(1)) - iy, iy - y0)
  x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
  img = np.asarray(image, _F)
  out = np.zeros(ix.shape, _F)
  for dy, wy in enumerate(wys):
    for dx, wx in enumerate(wxs):
      xx, yy = x0 + dx, y0 + dy
      ok = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
      out += np.where(ok, img[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)], _F(0)) * (wx * wy)
  return out


def sample_nearest_zeros(mask: np.ndarray, u, v) -> np.ndarray:
  """grid_sample(nearest, padding zeros, align_corners=False) of a bool [H, W] mask; nearest
  rounds half to even as torch's nearbyint."""
  h, w = mask.shape
  ix, iy = _grid_coords(u, v, w, h)
  x, y = np.rint(ix).astype(np.int64), np.rint(iy).astype(np.int64)
  ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
  return ok & np.asarray(mask, bool)[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)]


def _points_world(depth, K, c2w):
  """depthmap_to_absolute_camera_coordinates (uniflowmatch/utils/geometry.py:232-327): camera
  coordinates in float64 stored as float32, then the float32 rigid transform."""
  h, w = depth.shape
  u, v = np.meshgrid(np.arange(w), np.arange(h))
  K = np.asarray(K, _F)
  pts = np.empty((h, w, 3), _F)
  pts[..., 0] = (u - K[0, 2]) * depth / K[0, 0]
  pts[..., 1] = (v - K[1, 2]) * depth / K[1, 1]
  pts[..., 2] = depth
  c2w = np.asarray(c2w, _F)
  return pts @ c2w[:3, :3].T + c2w[:3, 3]


def _range_map(depth, K):
  """z_depthmap_to_norm_depthmap_batched: z * ||((u - cx) / fx, (v - cy) / fy, 1)||, float32."""
  h, w = depth.shape
  K = np.asarray(K, _F)
  x = (np.arange(w, dtype=_F) - K[0, 2]) / K[0, 0]
  y = (np.arange(h, dtype=_F) - K[1, 2]) / K[1, 1]
  norm = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + _F(1))
  return np.asarray(depth, _F) * norm


def branch_static_labels(depth0, K0, cam2world0, depth1, K1, cam2world1, thresholds) -> dict:
  """Labels of view 0 -> view 1 from z-depths (0 = invalid), OpenCV intrinsics and c2w poses.

  thresholds: (a, T, r) of `branch_threshold` (see BRANCH_THRESHOLDS).
  Returns dict(flow [H, W, 2] float32 (0 outside the view), fov_mask (in view of camera 1 and
  valid source depth: the branch's `valid_mask`), non_occluded (its `covisible_mask`),
  occlusion_supervision (its `occlusion_supervision_mask`)).
  """
  depth0 = np.asarray(depth0, _F)
  depth1 = np.asarray(depth1, _F)
  if depth0.ndim != 2 or depth1.ndim != 2:
    raise ValueError(f"depth maps must be [H, W], got {depth0.shape} and {depth1.shape}")
  h0, w0 = depth0.shape
  h1, w1 = depth1.shape
  pts = _points_world(depth0, K0, cam2world0)
  w2c1 = np.linalg.inv(np.asarray(cam2world1, _F))
  p = pts @ w2c1[:3, :3].T + w2c1[:3, 3]
  x, y, z = p[..., 0], p[..., 1], p[..., 2]
  K1 = np.asarray(K1, _F)
  with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
    u = K1[0, 0] * x / z + K1[0, 2]
    v = K1[1, 1] * y / z + K1[1, 2]
    in_view = (z > 0) & (u >= -0.5) & (u < w1 - 0.5) & (v >= -0.5) & (v < h1 - 0.5)
  gu, gv = np.meshgrid(np.arange(w0, dtype=_F), np.arange(h0, dtype=_F))
  flow = np.where(in_view[..., None], np.stack([u - gu, v - gv], -1), _F(0)).astype(_F)
  # Positions outside the view are never read: park them on the source pixel (finite).
  u, v = np.where(in_view, u, gu), np.where(in_view, v, gv)
  distance = np.sqrt(x * x + y * y + z * z)
  sampled = sample_bilinear_zeros(_range_map(depth1, K1), u, v)
  with np.errstate(invalid="ignore"):
    occluded = np.abs(sampled - distance) >= branch_threshold(*thresholds, distance)
  valid0 = depth0 > 0
  other_valid = sample_nearest_zeros(depth1 > 0, u, v) & in_view
  return dict(flow=flow, fov_mask=in_view & valid0, non_occluded=in_view & ~occluded & valid0,
              occlusion_supervision=(valid0 & ~in_view) | other_valid)
