"""Supervision masks (supplementary "Covisibility Supervision Range") and sample-dict labels."""

from __future__ import annotations

import numpy as np

from ufm_jax.geometry import camera
from ufm_jax.geometry.covisibility import inside_image, nearest_sample


def fov_mask_from_flow(flow: np.ndarray, target_shape: tuple[int, int] | None = None) -> np.ndarray:
  """Source pixels whose flow target lies inside the target image (pixel areas, -0.5 margin)."""
  flow = np.asarray(flow, np.float64)
  h, w = flow.shape[:2]
  th, tw = target_shape if target_shape is not None else (h, w)
  target = camera.pixel_grid(h, w) + flow
  return inside_image(target, th, tw) & camera.finite_pixels(flow)


def other_view_validity(valid1: np.ndarray, flow: np.ndarray) -> np.ndarray:
  """V_other[i] = V_2(i + flow[i]) with nearest lookup; False where the target leaves image 2."""
  valid1 = np.asarray(valid1, bool)
  flow = np.asarray(flow, np.float64)
  target = camera.pixel_grid(*flow.shape[:2]) + flow
  return inside_image(target, *valid1.shape) & nearest_sample(valid1, target)


def covis_supervision_mask(valid0: np.ndarray, fov_mask: np.ndarray,
                           valid_other: np.ndarray) -> np.ndarray:
  """V_covis = (V_1 and not F_1) or (F_1 and V_other).

  Out-of-view pixels with a valid source depth are surely not covisible; in-view pixels can only be
  judged where the target depth is valid.
  """
  valid0, fov, other = (np.asarray(a, bool) for a in (valid0, fov_mask, valid_other))
  return (valid0 & ~fov) | (fov & other)


def labels_from_correspondence(corr: dict) -> dict:
  """Output of correspondence_from_depth / _rigid_objects -> the sample-dict label keys.

  flow_valid marks where the ground-truth flow is defined (valid source depth, point in front of
  the target camera), including occluded and out-of-view pixels; the paper's flow loss is further
  restricted to `covisibility`.
  """
  valid0 = corr["valid"]
  fov = corr["fov_mask"]
  in_front = corr.get("in_front", fov)
  # A point behind camera 2 is out of its view, so it counts as not-F_1 in V_covis.
  return dict(flow=np.asarray(corr["flow"], np.float32),
              covisibility=np.asarray(corr["covisibility"], bool),
              flow_valid=np.asarray(in_front, bool),
              covis_valid=covis_supervision_mask(valid0, fov, corr["valid_other"]))


def flyingchairs_labels(flow: np.ndarray) -> dict:
  """FlyingChairs: no occlusion GT. Covisibility := FoV mask (a proxy used for flow supervision
  only); covis_valid all False so the proxy never trains the covisibility head."""
  flow = np.asarray(flow, np.float32)
  finite = camera.finite_pixels(flow)
  return dict(flow=np.where(finite[..., None], flow, 0.0).astype(np.float32),
              covisibility=fov_mask_from_flow(flow),
              flow_valid=finite,
              covis_valid=np.zeros(flow.shape[:2], bool))
