"""Visualisation: Middlebury flow colours, warping by flow, covisibility overlays, the flow's
uncertainty, panels.

All images are HWC uint8 RGB numpy arrays; flow is [H, W, 2] float (u right, v down, pixels); a
flow covariance is [H, W, 3] = (var_x, var_y, cov_xy) in px^2 (ufm_jax.models.covariance).
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


# The uncertainty images' fixed scale: sigma_max from 1/4 px to 64 px on a log scale, so that
# pictures of different pairs and models compare; values outside take the end colours.
UNCERTAINTY_RANGE_PX = (0.25, 64.0)
LEGEND_MIN_WIDTH = 320
LEGEND_HEIGHT = 40
LEGEND_FONT = 0.45         # cv2.FONT_HERSHEY_SIMPLEX scale: smaller ones render unreadably
PANEL_MIN_SIDE = 128       # panels of smaller images are enlarged (whole pixels) to this side


def _uncertainty_colours(sigma: np.ndarray, lo: float, hi: float) -> np.ndarray:
  t = (np.log2(np.clip(sigma, lo, hi)) - np.log2(lo)) / (np.log2(hi) - np.log2(lo))
  t = np.where(np.isfinite(t), t, 1.0)
  grey = np.round(255 * t).astype(np.uint8)
  return cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)


def uncertainty_to_image(covariance: np.ndarray, range_px=UNCERTAINTY_RANGE_PX) -> np.ndarray:
  """[H, W, 3] flow covariance -> [H, W, 3] uint8: sigma_max, the standard deviation along the
  error ellipse's long axis (sqrt of the covariance's larger eigenvalue, px), on the fixed log
  scale `range_px` of the inferno colour map (dark: sure to a fraction of a pixel; bright: tens
  of pixels)."""
  from ufm_jax.models import covariance as cov_lib
  cov = np.asarray(covariance, np.float64)
  if cov.ndim != 3 or cov.shape[-1] != 3:
    raise ValueError(f"uncertainty_to_image: covariance must be [H, W, 3], got {cov.shape}")
  return _uncertainty_colours(cov_lib.sigma_max(cov), *range_px)


def uncertainty_legend(width: int, range_px=UNCERTAINTY_RANGE_PX,
                       height: int = LEGEND_HEIGHT) -> np.ndarray:
  """[height, width, 3] uint8 legend of `uncertainty_to_image`: the colour bar with its ticks
  (powers of 4, the last with the unit, px), on white, each label centred on its tick."""
  lo, hi = range_px
  out = np.full((height, width, 3), 255, np.uint8)
  ticks = [v for v in 4.0 ** np.arange(-4, 6) if lo <= v <= hi]
  labels = [f"{v:g}" + (" px" if v == ticks[-1] else "") for v in ticks]
  sizes = [cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, LEGEND_FONT, 1)[0] for t in labels]
  # the bar starts and ends half a label in, so that the end labels sit whole under their ticks
  margin = max(8, sizes[0][0] // 2 + 2, sizes[-1][0] // 2 + 2)
  bar_h = height // 2 - 4
  xs = np.linspace(np.log2(lo), np.log2(hi), width - 2 * margin)
  out[2:2 + bar_h, margin:width - margin] = _uncertainty_colours(2.0 ** xs[None], lo, hi)
  for v, label, (tw, _) in zip(ticks, labels, sizes):
    x = margin + int(round((np.log2(v) - np.log2(lo)) / (np.log2(hi) - np.log2(lo))
                           * (width - 2 * margin - 1)))
    out[2 + bar_h:6 + bar_h, x] = 0
    cv2.putText(out, label, (x - tw // 2, height - 5), cv2.FONT_HERSHEY_SIMPLEX, LEGEND_FONT,
                (0, 0, 0), 1, cv2.LINE_AA)
  return out


def uncertainty_view(covariance: np.ndarray, range_px=UNCERTAINTY_RANGE_PX) -> np.ndarray:
  """`uncertainty_to_image` over its legend (at least LEGEND_MIN_WIDTH wide, padded white)."""
  image = uncertainty_to_image(covariance, range_px)
  h, w = image.shape[:2]
  width = max(w, LEGEND_MIN_WIDTH)
  top = np.full((h, width, 3), 255, np.uint8)
  top[:, (width - w) // 2:(width - w) // 2 + w] = image
  return np.concatenate([top, uncertainty_legend(width, range_px)], axis=0)


def panel(source: np.ndarray, target: np.ndarray, flow: np.ndarray,
          covisibility: np.ndarray | None = None, max_flow: float | None = None,
          covariance: np.ndarray | None = None) -> np.ndarray:
  """One RGB row: source | target | flow colours | target warped into the source frame, and with
  a flow `covariance` | its uncertainty (`uncertainty_to_image`) over a legend row under the
  panel. A source under PANEL_MIN_SIDE px on its short side has its row enlarged by a whole
  factor (each pixel a square block) until it is not.

  The target is shown resized to the source size; the warp uses the full-resolution target; with
  `covisibility`, non-covisible pixels of the warp (and of the flow colours) are greyed out.
  """
  h, w = source.shape[:2]
  tgt_small = target if target.shape[:2] == (h, w) else cv2.resize(
      np.ascontiguousarray(target), (w, h), interpolation=cv2.INTER_AREA)
  colours, warped = flow_views(target, flow, covisibility, max_flow=max_flow)
  tiles = [source, tgt_small, colours, warped]
  if covariance is not None:
    tiles.append(uncertainty_to_image(covariance))
  row = np.concatenate(tiles, axis=1)
  k = -(-PANEL_MIN_SIDE // min(h, w))
  if k > 1:
    row, w = np.repeat(np.repeat(row, k, axis=0), k, axis=1), w * k
  if covariance is None:
    return row
  # the legend ends under the uncertainty tile, at least LEGEND_MIN_WIDTH wide
  width = min(max(w, LEGEND_MIN_WIDTH), row.shape[1])
  legend = np.full((LEGEND_HEIGHT, row.shape[1], 3), 255, np.uint8)
  legend[:, row.shape[1] - width:] = uncertainty_legend(width)
  return np.concatenate([row, legend], axis=0)
