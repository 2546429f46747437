"""Label-consistent training augmentation: random scale + crop to a fixed shape, flips, colour jitter.

Each view v (source 0, target 1) gets its own affine pixel map, in the project's pixel-centre
convention (pixel i covers [i-0.5, i+0.5]):
  x' = s_v * (x + 0.5) - 0.5 - c_v          (resize by s_v, then crop at integer offset c_v)
so a correspondence x -> y = x + flow(x) becomes x' -> A_1(y), i.e.
  flow'(x') = A_1(x + flow(x)) - x'         with x = A_0^-1(x')
which stays exact when the two views are scaled differently. Labels are point-sampled at x:
flow bilinearly (only where all four neighbours are valid), masks by nearest neighbour; images are
resampled with area averaging when shrinking. Colour jitter touches the images only.

The training shape is one of a few (H, W) pairs, all multiples of 14, picked per batch from
(seed, step) so that jit compiles one program per shape.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

import cv2
import numpy as np

PATCH = 14
# Width:height ratios between 3:1 and 1:1 (paper sec. 3.3); landscape, as in the paper.
DEFAULT_ASPECT_RATIOS = (3.0, 2.0, 16 / 9, 4 / 3, 1.0)
LABEL_KEYS = ("flow", "covisibility", "flow_valid", "covis_valid")


def training_shapes(longest_side: int, aspect_ratios: Sequence[float] = DEFAULT_ASPECT_RATIOS,
                    patch: int = PATCH) -> tuple[tuple[int, int], ...]:
  """(H, W) training shapes: W = longest_side, H = W / ratio, both rounded to multiples of `patch`."""
  if longest_side % patch:
    raise ValueError(f"longest_side={longest_side} is not a multiple of the patch size {patch}")
  shapes = []
  for ratio in aspect_ratios:
    if not 1.0 <= ratio <= 3.0 + 1e-6:
      raise ValueError(f"aspect ratio {ratio} outside [1, 3] (width:height)")
    h = max(patch, int(round(longest_side / ratio / patch)) * patch)
    if (h, longest_side) not in shapes:
      shapes.append((h, longest_side))
  return tuple(shapes)


def shape_for_step(shapes: Sequence[tuple[int, int]], seed: int, step: int) -> tuple[int, int]:
  """The training shape of global batch `step`; the same on every host and after a resume."""
  rng = np.random.default_rng([seed, step, 0x5A9E])
  return tuple(shapes[int(rng.integers(len(shapes)))])


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
  """Ranges of the random augmentation; `AugmentConfig.from_dict(config.input.augment)`."""
  zoom: tuple[float, float] = (1.0, 1.3)    # shared zoom on top of the smallest covering scale
  view_scale_jitter: float = 0.05           # per-view extra log-scale in [-j, j]
  crop_shift: float = 0.0                   # independent target-crop shift, fraction of out size
  hflip_prob: float = 0.0                   # mirror BOTH views (u negated)
  brightness: float = 0.2                   # multiplicative factor in [1-b, 1+b]
  contrast: float = 0.2
  saturation: float = 0.2
  hue: float = 0.02                         # fraction of the hue circle
  asymmetric_color_prob: float = 0.2        # jitter the two images with independent draws
  color_prob: float = 0.8                   # probability that any colour jitter is applied

  @classmethod
  def from_dict(cls, d: Mapping[str, Any] | None) -> "AugmentConfig":
    d = dict(d or {})
    unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
      raise KeyError(f"unknown augment keys {sorted(unknown)}; known: "
                     f"{[f.name for f in dataclasses.fields(cls)]}")
    if "zoom" in d:
      d["zoom"] = tuple(d["zoom"])
    return cls(**d)


@dataclasses.dataclass(frozen=True)
class View:
  """x' = sx * (x + 0.5) - 0.5 - cx (same for y) maps original pixels of one view to output pixels."""
  sx: float
  sy: float
  cx: int
  cy: int
  resized_hw: tuple[int, int]   # full resized image size before the crop

  def matrix(self) -> np.ndarray:
    """2x3 affine map original -> output, for cv2.warpAffine."""
    return np.array([[self.sx, 0.0, 0.5 * self.sx - 0.5 - self.cx],
                     [0.0, self.sy, 0.5 * self.sy - 0.5 - self.cy]], np.float64)

  def inverse_matrix(self) -> np.ndarray:
    """2x3 affine map output -> original (what cv2.WARP_INVERSE_MAP wants)."""
    return np.array([[1 / self.sx, 0.0, (self.cx + 0.5) / self.sx - 0.5],
                     [0.0, 1 / self.sy, (self.cy + 0.5) / self.sy - 0.5]], np.float64)


@dataclasses.dataclass(frozen=True)
class Params:
  view0: View
  view1: View
  hflip: bool
  color0: tuple[float, float, float, float] | None  # brightness, contrast, saturation, hue
  color1: tuple[float, float, float, float] | None


def _resized_size(hw, scale, out_hw):
  h, w = hw
  return max(out_hw[0], int(round(h * scale))), max(out_hw[1], int(round(w * scale)))


def _color_draw(rng, cfg: AugmentConfig):
  u = lambda r: float(rng.uniform(1 - r, 1 + r)) if r > 0 else 1.0
  return (u(cfg.brightness), u(cfg.contrast), u(cfg.saturation),
          float(rng.uniform(-cfg.hue, cfg.hue)) if cfg.hue > 0 else 0.0)


def sample_params(rng: np.random.Generator, hw0: tuple[int, int], hw1: tuple[int, int],
                  out_hw: tuple[int, int], cfg: AugmentConfig) -> Params:
  """Draws the geometric and photometric parameters of one pair."""
  out_h, out_w = out_hw
  zoom = float(np.exp(rng.uniform(np.log(cfg.zoom[0]), np.log(cfg.zoom[1]))))
  views = []
  for hw in (hw0, hw1):
    cover = max(out_h / hw[0], out_w / hw[1])
    jitter = float(np.exp(rng.uniform(-cfg.view_scale_jitter, cfg.view_scale_jitter)))
    rh, rw = _resized_size(hw, cover * max(1.0, zoom * jitter), out_hw)
    views.append((rh / hw[0], rw / hw[1], (rh, rw)))
  (sy0, sx0, r0), (sy1, sx1, r1) = views
  cy0 = int(rng.integers(0, r0[0] - out_h + 1))
  cx0 = int(rng.integers(0, r0[1] - out_w + 1))
  # The target crop looks at the same original region (so small-motion pairs keep small flow),
  # optionally shifted.
  centre_y = (cy0 + out_h / 2) / sy0
  centre_x = (cx0 + out_w / 2) / sx0
  shift_y = rng.uniform(-cfg.crop_shift, cfg.crop_shift) * out_h
  shift_x = rng.uniform(-cfg.crop_shift, cfg.crop_shift) * out_w
  cy1 = int(np.clip(round(centre_y * sy1 - out_h / 2 + shift_y), 0, r1[0] - out_h))
  cx1 = int(np.clip(round(centre_x * sx1 - out_w / 2 + shift_x), 0, r1[1] - out_w))
  hflip = bool(rng.uniform() < cfg.hflip_prob)
  color0 = color1 = None
  if rng.uniform() < cfg.color_prob:
    color0 = _color_draw(rng, cfg)
    color1 = _color_draw(rng, cfg) if rng.uniform() < cfg.asymmetric_color_prob else color0
  return Params(View(sx0, sy0, cx0, cy0, r0), View(sx1, sy1, cx1, cy1, r1), hflip, color0, color1)


def _warp(a: np.ndarray, view: View, out_hw, interpolation) -> np.ndarray:
  return cv2.warpAffine(np.ascontiguousarray(a), view.inverse_matrix(), (out_hw[1], out_hw[0]),
                        flags=interpolation | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def warp_image(image: np.ndarray, view: View, out_hw) -> np.ndarray:
  """Resamples one image into the output window (area averaging when shrinking)."""
  if view.sx < 1 or view.sy < 1:
    rh, rw = view.resized_hw
    resized = cv2.resize(image, (rw, rh), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(resized[view.cy:view.cy + out_hw[0], view.cx:view.cx + out_hw[1]])
  return _warp(image, view, out_hw, cv2.INTER_LINEAR)


def _taps(coord: np.ndarray, size: int):
  """Bilinear taps along one axis (clamped at the border); the upper tap collapses when w == 0."""
  coord = np.clip(coord, 0, size - 1)
  lo = np.floor(coord).astype(np.int64)
  w = (coord - lo).astype(np.float32)
  hi = np.where(w > 0, np.minimum(lo + 1, size - 1), lo)
  nearest = np.floor(coord + 0.5).astype(np.int64)
  return lo, hi, w, nearest


@dataclasses.dataclass(frozen=True)
class LabelGrid:
  """The pixels of an original image (size hw) that `warp_labels` reads for one view: rows x cols
  (sorted, unique). Labels computed on this grid alone give the same output as full ones."""
  rows: np.ndarray
  cols: np.ndarray
  hw: tuple[int, int]


def _output_in_original(view: View, out_hw):
  """Original coordinates of the output pixel centres along x and y (float64)."""
  x = (np.arange(out_hw[1], dtype=np.float64) + view.cx + 0.5) / view.sx - 0.5
  y = (np.arange(out_hw[0], dtype=np.float64) + view.cy + 0.5) / view.sy - 0.5
  return x, y


def label_grid(view: View, hw: tuple[int, int], out_hw) -> LabelGrid:
  """The grid of original pixels (image size hw) whose labels `warp_labels` reads for `view`:
  the bilinear and nearest taps of the output pixels. Labelling only these (e.g. depth
  reprojection on a sub-grid) skips the pixels the crop drops or an upscale never touches."""
  def read(coord, size):
    lo, hi, _, nearest = _taps(coord, size)
    return np.unique(np.concatenate([lo, hi, nearest]))
  x, y = _output_in_original(view, out_hw)
  return LabelGrid(read(y, hw[0]), read(x, hw[1]), (int(hw[0]), int(hw[1])))


def warp_labels(sample: Mapping[str, np.ndarray], view0: View, view1: View, out_hw,
                grid: LabelGrid | None = None) -> dict:
  """Flow and masks of a (source view0 -> target view1) sample, in output pixels.

  Sampled in float64 coordinates with numpy (not cv2's 1/32-pixel fixed point) so labels stay
  exact to float precision. With `grid`, the sample's label arrays hold only the pixels of
  `label_grid(view0, ...)` (the output is the same as with full-size labels).
  """
  out_h, out_w = out_hw
  valid = np.asarray(sample["flow_valid"], bool)
  flow = np.asarray(sample["flow"], np.float32)
  h, w = valid.shape if grid is None else grid.hw
  xp = np.arange(out_w, dtype=np.float64)
  yp = np.arange(out_h, dtype=np.float64)
  x, y = _output_in_original(view0, out_hw)
  x0, x1, wx, xn = _taps(x, w)
  y0, y1, wy, yn = _taps(y, h)
  if grid is not None:  # original pixel -> its place in the grid (every tap is on it)
    x0, x1, xn = (np.searchsorted(grid.cols, t) for t in (x0, x1, xn))
    y0, y1, yn = (np.searchsorted(grid.rows, t) for t in (y0, y1, yn))

  # The flow stays interleaved [.., W, 2]: rows are gathered as contiguous copies, columns move
  # each (u, v) pair as one 8-byte item (a complex64 view), and every weight is broadcast along a
  # contiguous run (a per-row scalar over the row, a per-column weight repeated for u and v):
  # numpy is several times slower broadcasting over a trailing axis of 2 or gathering 4-byte
  # items of a strided view.
  flow = np.ascontiguousarray(flow)
  # Flow is nearly always finite everywhere (one fast whole-array test); then the validity mask
  # alone decides which taps are zeroed.
  all_finite = bool(np.isfinite(flow).all())

  def tap_rows(rows):  # only the rows the output reads are cleaned
    f = flow.take(rows, 0)
    m = valid.take(rows, 0)
    if all_finite:
      np.copyto(f.view(np.complex64)[..., 0], 0, where=~m)
      return f, m
    return np.where(m[..., None] & np.isfinite(f), f, np.float32(0)), m

  # Separable: blend the two source rows, then the two columns (np.take, not fancy indexing).
  # In place, in the same operation order as a * (1 - w) + b * w.
  wy = wy[:, None, None]
  rows, v0 = tap_rows(y0)
  lower, v1 = tap_rows(y1)
  rows *= 1 - wy
  lower *= wy
  rows += lower
  pairs = rows.view(np.complex64)[..., 0]
  flow_r = pairs.take(x0, 1).view(np.float32)   # [out_h, 2 * out_w]: u, v, u, v, ...
  right = pairs.take(x1, 1).view(np.float32)
  flow_r *= np.repeat(1 - wx, 2)
  right *= np.repeat(wx, 2)
  flow_r += right
  # A label is valid only if every bilinear tap with weight was valid (no blending with garbage).
  vrows = v0 & v1
  flow_valid = vrows.take(x0, 1)
  flow_valid &= vrows.take(x1, 1)
  # The three nearest-tap masks packed in one uint8 for a single column gather.
  near = valid.take(yn, 0).view(np.uint8).copy()
  for bit, key in ((1, "covisibility"), (2, "covis_valid")):
    near |= np.asarray(sample[key], bool).take(yn, 0).view(np.uint8) << bit
  near = near.take(xn, 1)
  flow_valid &= (near & 1).view(bool)
  # flow' = A1(x + flow) - x' = s1 * flow + (s1 * x + b1 - x'); the bracket is 1-D, in float64.
  a1 = view1.matrix()
  off_x = (a1[0, 0] * x + a1[0, 2] - xp).astype(np.float32)
  off_y = (a1[1, 1] * y + a1[1, 2] - yp).astype(np.float32)
  shift = np.zeros(2 * out_w, np.float32)
  shift[0::2] = off_x
  flow_r *= np.tile(np.float32([a1[0, 0], a1[1, 1]]), out_w)
  flow_r += shift
  flow_r = flow_r.reshape(out_h, out_w, 2)
  flow_r[..., 1] += off_y[:, None]
  return {"flow": flow_r, "flow_valid": flow_valid, "covisibility": (near & 2) != 0,
          "covis_valid": (near & 4) != 0}


def hflip_labels(labels: dict) -> dict:
  out = {k: np.ascontiguousarray(v[:, ::-1]) for k, v in labels.items()}
  out["flow"][..., 0] *= -1
  return out


def color_jitter(image: np.ndarray, params) -> np.ndarray:
  """Brightness, contrast, saturation (factors) and hue (circle fraction) on a uint8 RGB image."""
  if params is None:
    return image
  brightness, contrast, saturation, hue = params
  # brightness b, contrast c (around the mean grey m), saturation s (around the pixel's grey g)
  # fold into one affine blend: out = s*b*c * img + (1-s)*b*c * g + m*(1-c), m = b * mean(g).
  grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
  m = brightness * float(grey.mean())
  bc = brightness * contrast
  img = cv2.addWeighted(image, saturation * bc, cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB),
                        (1 - saturation) * bc, m * (1 - contrast))
  if hue:
    hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV_FULL)
    hsv[..., 0] += np.uint8(int(round(hue * 256)) % 256)  # uint8 wraps: the shift mod 256
    img = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB_FULL)
  return img


def apply(sample: Mapping[str, Any], params: Params, out_hw,
          backward: Mapping[str, Any] | None = None,
          label_grids: tuple[LabelGrid, LabelGrid] | None = None) -> list[dict]:
  """Augments one pair; with `backward` (the (image1 -> image0) labels) returns [fwd, bwd].

  The backward pair reuses the forward's augmented images swapped, so (a, b) and (b, a) in a
  symmetrized batch show exactly the same pixels. `label_grids`: the forward labels hold only
  the pixels of the first grid (`label_grid(params.view0, ...)`), the backward ones the second's.
  """
  out_hw = tuple(int(s) for s in out_hw)
  g0, g1 = label_grids or (None, None)
  im0 = color_jitter(warp_image(np.asarray(sample["image0"]), params.view0, out_hw), params.color0)
  im1 = color_jitter(warp_image(np.asarray(sample["image1"]), params.view1, out_hw), params.color1)
  pairs = [(im0, im1, warp_labels(sample, params.view0, params.view1, out_hw, g0))]
  if backward is not None:
    pairs.append((im1, im0, warp_labels(backward, params.view1, params.view0, out_hw, g1)))
  outs = []
  for a, b, labels in pairs:
    if params.hflip:
      a, b, labels = a[:, ::-1], b[:, ::-1], hflip_labels(labels)
    outs.append({"image0": np.ascontiguousarray(a), "image1": np.ascontiguousarray(b), **labels})
  return outs


def augment(sample: Mapping[str, Any], rng: np.random.Generator, out_hw, cfg: AugmentConfig,
            backward: Mapping[str, Any] | None = None) -> list[dict]:
  """Random parameters + `apply`; returns [fwd] or [fwd, bwd] dicts of output-shaped arrays."""
  hw0 = np.shape(sample["image0"])[:2]
  hw1 = np.shape(sample["image1"])[:2]
  return apply(sample, sample_params(rng, hw0, hw1, out_hw, cfg), out_hw, backward)
