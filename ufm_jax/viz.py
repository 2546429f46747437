"""Visualisation: Middlebury flow colours, warping by flow, covisibility overlays, panels.

All images are HWC uint8 RGB numpy arrays; flow is [H, W, 2] float (u right, v down, pixels).
"""

from __future__ import annotations


import cv2
import numpy as np


def make_colorwheel() -> np.ndarray:
  """The Middlebury 55-colour wheel (Baker et al. 2007) as [55, 3] float in 0..255.

  Segments red->yellow (15), yellow->green (6), green->cyan (4), cyan->blue (11),
  blue->magenta (13), magenta->red (6).
  """
  segments = [(15, (255, 0, 0), (255, 255, 0)), (6, (255, 255, 0), (0, 255, 0)),
              (4, (0, 255, 0), (0, 255, 255)), (11, (0, 255, 255), (0, 0, 255)),
              (13, (0, 0, 255), (255, 0, 255)), (6, (255, 0, 255), (255, 0, 0))]
  rows = []
  for n, start, end in segments:
    t = np.arange(n)[:, None] / n
    start, end = np.array(start, float), np.array(end, float)
    # the rising/falling channel uses floor(255 * i / n) as in the reference implementation
    rows.append(start + np.floor(255 * t) * np.sign(end - start))
  return np.concatenate(rows).astype(np.float64)


COLORWHEEL = make_colorwheel()


def flow_to_color(flow: np.ndarray, max_flow: float | None = None,
                  mask: np.ndarray | None = None) -> np.ndarray:
  """[H, W, 2] flow -> [H, W, 3] uint8 RGB in the Middlebury colour coding.

  Hue = direction (+u is red, +v (down) is yellow-green, -u cyan, -v blue-magenta), saturation =
  magnitude / max_flow (default: the largest magnitude, over `mask` if given); zero flow is
  white, magnitudes above max_flow are darkened (x0.75) as in the reference code.
  """
  flow = np.asarray(flow, np.float64)
  if flow.ndim != 3 or flow.shape[-1] != 2:
    raise ValueError(f"flow_to_color: flow must be [H, W, 2], got shape {flow.shape}")
  flow = np.where(np.isfinite(flow), flow, 0.0)
  u, v = flow[..., 0], flow[..., 1]
  rad = np.sqrt(u * u + v * v)
  if max_flow is None:
    sel = rad if mask is None else rad[np.asarray(mask, bool)]
    max_flow = float(sel.max()) if sel.size else 0.0
  scale = 1.0 / (max_flow + 1e-5)
  u, v, rad = u * scale, v * scale, rad * scale
  ncols = len(COLORWHEEL)
  a = np.arctan2(-v, -u) / np.pi
  fk = (a + 1) / 2 * (ncols - 1)
  k0 = np.floor(fk).astype(np.int64)
  k1 = np.where(k0 + 1 == ncols, 0, k0 + 1)
  f = (fk - k0)[..., None]
  col = ((1 - f) * COLORWHEEL[k0] + f * COLORWHEEL[k1]) / 255.0
  inside = (rad <= 1)[..., None]
  col = np.where(inside, 1 - rad[..., None] * (1 - col), col * 0.75)
  return np.floor(255 * col).astype(np.uint8)


def warp_by_flow(image: np.ndarray, flow: np.ndarray, border_value=0) -> np.ndarray:
  """Samples `image` (the target) at x + flow: the target warped into the source frame.

  Bilinear (cv2.remap); points falling outside the target get `border_value`.
  """
  flow = np.asarray(flow, np.float32)
  h, w = flow.shape[:2]
  xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
  map_x, map_y = xs + flow[..., 0], ys + flow[..., 1]
  return cv2.remap(np.ascontiguousarray(image), map_x, map_y, interpolation=cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)


def grey_out(image: np.ndarray, covisibility: np.ndarray, threshold: float = 0.5) -> np.ndarray:
  """Pixels with covisibility < threshold become a low-contrast grey of their luminance.

  grey = 128 + (luma - 128) / 4 on every channel; covisible pixels are unchanged.
  """
  image = np.asarray(image)
  luma = image.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
  grey = np.clip(np.round(128 + (luma - 128) / 4), 0, 255).astype(np.uint8)
  hidden = np.asarray(covisibility) < threshold
  out = image.copy()
  out[hidden] = grey[hidden][:, None]
  return out


def covisibility_to_image(covisibility: np.ndarray) -> np.ndarray:
  """[H, W] probability -> [H, W] uint8 (0..255, rounded)."""
  return np.clip(np.round(np.asarray(covisibility, np.float32) * 255), 0, 255).astype(np.uint8)


def flow_views(target: np.ndarray, flow: np.ndarray, covisibility: np.ndarray | None = None,
               threshold: float = 0.5, max_flow: float | None = None):
  """(flow colours, target warped into the source frame), both at the flow's size.

  With `covisibility`, pixels below `threshold` are greyed out in both, and the colour scale
  (max_flow=None) is the largest flow over the covisible pixels, so occluded outliers do not
  wash out the colours.
  """
  mask = None if covisibility is None else np.asarray(covisibility) >= threshold
  colours = flow_to_color(flow, max_flow=max_flow, mask=mask if mask is not None and mask.any() else None)
  warped = warp_by_flow(target, flow)
  if covisibility is not None:
    warped = grey_out(warped, covisibility, threshold)
    colours = grey_out(colours, covisibility, threshold)
  return colours, warped


def panel(source: np.ndarray, target: np.ndarray, flow: np.ndarray,
          covisibility: np.ndarray | None = None, max_flow: float | None = None) -> np.ndarray:
  """One RGB row: source | target | flow colours | target warped into the source frame.

  The target is shown resized to the source size; the warp uses the full-resolution target; with
  `covisibility`, non-covisible pixels of the warp (and of the flow colours) are greyed out.
  """
  h, w = source.shape[:2]
  tgt_small = target if target.shape[:2] == (h, w) else cv2.resize(
      np.ascontiguousarray(target), (w, h), interpolation=cv2.INTER_AREA)
  colours, warped = flow_views(target, flow, covisibility, max_flow=max_flow)
  return np.concatenate([source, tgt_small, colours, warped], axis=1)


