"""Rigid posed objects (Kubric-4D): every pixel belongs to a rigid object with known poses.

p_s,1->2 = tau_2^(k) tau_1^(k)^-1 (T_1 pi_1^-1(i_s) D_1(i_s)),  k = S[i_s]   (supplementary eq.)
then the same projection, interpolation and threshold as static scenes.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ufm_jax.geometry import camera
from ufm_jax.geometry.covisibility import (_check_depth, _correspond, _k_inverse,
                                           _source_in_target, official_correspond, on_grid)


def _pose_table(poses, name: str) -> tuple[np.ndarray, np.ndarray]:
  """dict {id: 4x4} or array [N, 4, 4] (row = id) -> (table [N, 4, 4], known [N])."""
  if isinstance(poses, Mapping):
    n = max((int(k) for k in poses), default=-1) + 1
    table, known = np.tile(np.eye(4), (max(n, 1), 1, 1)), np.zeros(max(n, 1), bool)
    for k, T in poses.items():
      if np.shape(T) != (4, 4):
        raise ValueError(f"{name}[{k}] must be [4, 4], got shape {np.shape(T)}")
      table[int(k)], known[int(k)] = T, True
    return table, known
  table = np.asarray(poses, np.float64)
  if table.ndim != 3 or table.shape[1:] != (4, 4):
    raise ValueError(f"{name} must be [N, 4, 4] or a dict of 4x4, got shape {table.shape}")
  return table, np.isfinite(table).all(axis=(1, 2))


def object_motions(object_poses0, object_poses1) -> tuple[np.ndarray, np.ndarray]:
  """Per object id the world-frame motion tau_1 tau_0^-1 [N, 4, 4] and which ids have both poses.

  Object poses are object-to-world at the source (0) and target (1) time.
  """
  t0, k0 = _pose_table(object_poses0, "object_poses0")
  t1, k1 = _pose_table(object_poses1, "object_poses1")
  n = max(len(t0), len(t1))
  pad = lambda t, k: (np.concatenate([t, np.tile(np.eye(4), (n - len(t), 1, 1))]),
                      np.concatenate([k, np.zeros(n - len(k), bool)]))
  (t0, k0), (t1, k1) = pad(t0, k0), pad(t1, k1)
  known = k0 & k1
  t0 = np.where(known[:, None, None], t0, np.eye(4))
  t1 = np.where(known[:, None, None], t1, np.eye(4))
  return t1 @ camera.invert_pose(t0), known


def correspondence_from_rigid_objects(depth0, K0, cam2world0, segmentation0, object_poses0,
                                      depth1, K1, cam2world1, object_poses1,
                                      tau_d: float, tau_r: float, subpixel_search: float = 0.0,
                                      rows=None, cols=None, official_params=None):
  """Flow 0->1 and covisibility for a scene of rigid objects.

  segmentation0: [H, W] int object id per source pixel. object_poses0/1: object-to-world poses
  at the two times, as an array [N, 4, 4] indexed by id or a dict {id: 4x4}; give the static
  background (Kubric id 0) the identity (or any equal poses) at both times. Pixels whose id has
  no pose at either time get valid=False. Returns the dict of `covisibility_from_points`.
  rows, cols: only the source pixels of that grid, as in `correspondence_from_depth`.
  official_params: (absolute, temperature, relative) -> the official training code's rule
  instead (kubric_flow_postprocessing_pathway, flow_postprocessing.py:252-314): the output dict
  of `official_labels` (tau_d, tau_r, subpixel_search unused).
  """
  depth0 = _check_depth("depth0", depth0)
  depth1 = _check_depth("depth1", depth1)
  seg = np.asarray(segmentation0)
  if seg.shape != depth0.shape:
    raise ValueError(f"segmentation0 shape {seg.shape} differs from depth0 shape {depth0.shape}")
  if not np.issubdtype(seg.dtype, np.integer):
    raise ValueError(f"segmentation0 must hold integer object ids, got dtype {seg.dtype}")
  rows, cols, depth0, seg = on_grid(rows, cols, depth0, seg)
  motions, known = object_motions(object_poses0, object_poses1)
  in_table = (seg >= 0) & (seg < len(motions))
  ids = np.where(in_table, seg, 0)
  valid0 = camera.valid_depth(depth0) & in_table & known[ids]
  # Per object the whole chain camera 1 -> world -> moved -> camera 2 is one rigid transform
  # (composed in float64). The most common object (usually the static background) is done on
  # the dense grid; the other objects' pixels are gathered, transformed and scattered back.
  rel = camera.invert_pose(cam2world1) @ motions @ np.asarray(cam2world0, np.float64)
  ids = ids.reshape(-1).astype(np.intp, copy=False)
  counts = np.bincount(ids, minlength=len(rel))
  base = int(counts.argmax())
  dtype = np.float32 if official_params is not None else np.float64   # as official_correspond
  xyz = _source_in_target(depth0, valid0, K0, rel[base], rows, cols, dtype)
  others = np.flatnonzero(ids != base) if counts[base] < ids.size else np.zeros(0, np.intp)
  if others.size:
    affine = rel[:, :3].copy()
    affine[:, :, :3] = affine[:, :, :3] @ _k_inverse(K0)
    coef = affine.reshape(len(affine), 12)  # per id the rows of [R K0^-1 | t]
    # Objects one at a time with scalar coefficients (the same float64 operations as a per-pixel
    # coefficient gather, without the gather): pixels grouped by id with a stable sort.
    present = np.flatnonzero(counts)
    present = present[present != base]
    if len(present) > 1:
      order = np.argsort(ids[others], kind="stable")
      ends = np.cumsum(counts[present])
      groups = [(k, others[order[e - n:e]]) for k, n, e in zip(present, counts[present], ends)]
    else:
      groups = [(present[0], others)]
    w = depth0.shape[1]
    flat_valid, flat_depth = valid0.reshape(-1), depth0.reshape(-1)
    for k, pix in groups:
      c = coef[k]
      u, v = pix % w, pix // w
      if rows is not None:
        u, v = cols[u], rows[v]
      u, v = u.astype(np.float64), v.astype(np.float64)
      d = np.where(flat_valid[pix], flat_depth[pix], 0.0)
      for i in range(3):
        xyz[i].reshape(-1)[pix] = (c[4 * i] * u + c[4 * i + 1] * v + c[4 * i + 2]) * d \
            + c[4 * i + 3]
  planes = lambda r0, r1: [c[r0:r1] for c in xyz]
  if official_params is not None:
    return official_correspond(planes, valid0, depth1, K1, official_params, rows, cols)
  return _correspond(planes, valid0, depth1, K1, tau_d, tau_r, subpixel_search, rows, cols)
