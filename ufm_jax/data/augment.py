"""Training augmentation and labels after the crop, as the official UFM training code makes them.

The official code (train branch, d8c421e) has three pathways; each dataset takes one:

* static (depth + poses: BlendedMVS, MegaDepth, ScanNet++, StaticThings, Habitat): each view is
  cropped (intrinsics shift) BEFORE labelling, then flow and masks are computed from the cropped
  depth maps and cameras (`ufm_jax.geometry.official_labels`), so a pixel whose match leaves the
  other view's crop is out of fov, not covisible and not supervised as flow
  (base/flow_postprocessing.py:556-714). Crops: `static_crop_pair` (aug_crop='auto_crop_asis')
  or, without augmentation and for `no_crop_datasets`, `resize_cover_center_crop`.
* flow (labels stored per pixel: FlyingThings3D, Monkaa, FlyingChairs, Spring, HD1K, TA-WB and
  our TartanAir V2): resize so the short side covers U(1, 1.2) x the training shape, the same
  random crop offset in both views, flow and masks resized by nearest neighbour; covisibility and
  the occlusion-supervision mask are AND-ed with "the match stays inside the crop"
  (utils/flow_manipulation.py:488-503, 741-874, base_optical_flow_dataset.py:64-106).
* kubric (Kubric-4D): labels at the stored size, then the same resize and an independent crop per
  view chosen among 10 x 10 candidates by the covisible pixels they keep
  (flow_postprocessing.py:252-392, flow_manipulation.py:505-738).

Colour (per image, independently): torchvision ColorJitter(0.5, 0.5, 0.5, 0.1), grayscale 5 %,
Gaussian blur 5 % and, for `low_light_datasets`, darkening 1 % (base_stereo_view_dataset.py:92-95,
361-374; base_optical_flow_dataset.py:29-30, 114-124). Static pairs become identical-view pairs
with probability 0.005 (aug_monocular, base_stereo_view_dataset.py:387-389).

The resize and crop operations themselves, shared with the benchmark readers, are in
ufm_jax.data.official_ops.

`official_no_aug` is the deterministic path (aug_crop=False, transform='imgnorm'). Every option
that deviates from the official code, and every official quirk, is a named key of `AugmentConfig`
(`config.input.augment`).

Pixel convention: integer (u, v) is a pixel centre (OpenCV), as in all official label code.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

import cv2
import numpy as np
from PIL import Image, ImageEnhance

from ufm_jax import geometry
from ufm_jax.data import hsv_tables, pil_warp
from ufm_jax.data.official_ops import (FlowCrop, StaticView, center_flow_crop, flow_crop_images,
                                       flow_crop_labels, nearest_index, portrait_resolution,
                                       resize_cover_center_crop, resize_short_axis_size,
                                       rotate_to_landscape, trunc_u8)

PATCH = 14
# Width:height ratios between 3:1 and 1:1 (paper sec. 3.3); landscape, as in the paper.
DEFAULT_ASPECT_RATIOS = (3.0, 2.0, 16 / 9, 4 / 3, 1.0)
LABEL_KEYS = ("flow", "covisibility", "flow_valid", "covis_valid")
# The official training shapes (H, W), drawn uniformly per batch (BatchedRandomSampler,
# base/batched_sampler.py:55): configs/dataset/resolution_options/default.yaml.
SHAPES_560 = ((420, 560), (364, 560), (308, 560), (280, 560), (168, 560))  # 560_many_non_square_ar
SHAPES_560_SQUARE = ((560, 560),) + SHAPES_560                              # 560_many_ar (refine)
SHAPES_980 = ((644, 980), (560, 980), (490, 980), (308, 980))             # 980_many_opticalflow_ar


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


def check_shapes(shapes, patch: int = PATCH) -> tuple[tuple[int, int], ...]:
  """Explicit (H, W) training shapes: landscape or square, multiples of `patch`."""
  out = tuple((int(h), int(w)) for h, w in shapes)
  if not out:
    raise ValueError("input.shapes is empty")
  for h, w in out:
    if h % patch or w % patch or h > w or h <= 0:
      raise ValueError(f"input.shapes: ({h}, {w}) must be (H, W) with H <= W, both multiples of "
                       f"{patch}")
  return out


def shape_for_step(shapes: Sequence[tuple[int, int]], seed: int, step: int) -> tuple[int, int]:
  """The training shape of global batch `step` (uniform over `shapes`, as the official sampler);
  the same on every host and after a resume."""
  rng = np.random.default_rng([seed, step, 0x5A9E])
  return tuple(shapes[int(rng.integers(len(shapes)))])


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
  """`config.input.augment`: the official augmentation by default; each key says what it changes.

  enabled: False gives `official_no_aug` for every pair (aug_crop=False, transform='imgnorm').
  no_crop_datasets: static datasets without crop augmentation (resize to cover + centre crop),
    as the 560 recipe's Habitat (configs/dataset/ufm_560_all.yaml: `override habitat: default`).
  flow_pathway_datasets: datasets labelled from depth here that the official code reads as a flow
    set (TartanAir: the official TA-WB shards ship flow and masks; tartanair_assembled.py).
  static_crop_candidates: crops drawn per view; the pair sharing most correspondences wins
    (n_tentative_crops, base_stereo_view_dataset.py:54, 256-267).
  static_correspondences: correspondences that score the crop pairs (target_n_corres=500, :229).
  static_min_zoom: per-view zoom drawn log-uniformly in [1, 1 + max(f S, S (S - R) // R) / S]
    (S: short side of the stored image, R: training height; aug_crop 'auto', :236-240,
    cropping.py:352-369).
  static_pil_sampling: quirk. True (official): the cropped image and depth are sampled where PIL
    samples (output pixel x at input x_in = sx + (x + 0.5) / a - 0.5 for zoom a) while the
    intrinsics say sx + x / a: labels are off by 0.5 (1 - a) output px. False: sampled where the
    intrinsics say.
  portrait_to_landscape: portrait views (H > 1.1 W) are cropped portrait and rotated 90 degrees
    to landscape (base_stereo_view_dataset.py:246-254, 414-417).
  square_random_portrait: near-square views (0.9 < H/W < 1.1) take a portrait crop (then rotated)
    with probability 1/2 (:251-254).
  identical_view_prob: static pairs replaced by two copies of the first view (aug_monocular
    0.005 in every static dataset yaml).
  expansion: flow and Kubric pathways resize so the short side covers U(lo, hi) x the training
    shape (base_optical_flow_dataset.py:70, flow_postprocessing.py:338).
  kubric_crop_candidates, kubric_covisible_samples: CovisibleGuidedCropManipulation(N_crop=10)
    and its num_covisible_sample=2048 (flow_manipulation.py:505-530).
  kubric_score_quirk: True (official): the backward term of a crop pair's score is read with the
    two crop indices swapped (flow_manipulation.py:606-630); False scores matching pairs.
  photometric: True (official): the colour augmentation below. False: none of it (jitter,
    grayscale, blur, low light), only the geometric part (configs/distill.py colour=false;
    docs/distillation.md has runs with and without it).
  brightness, contrast, saturation, hue: torchvision ColorJitter(0.5, 0.5, 0.5, 0.1), each image
    independently, the four in random order.
  grayscale_prob, blur_prob, blur_sigma, blur_kernel: RandomGrayscale(0.05),
    RandomApply(GaussianBlur(5, (0.1, 1.0)), 0.05) (not on Kubric, which only jitters colours).
  low_light_prob, low_light_datasets: darkening + 16-level quantisation + noise, per image
    (aug_low_light=True in the FlyingChairs yaml and Habitat's `cropping` yaml).
  supervise_out_of_view: deviation. False (official): on the flow pathway a pixel whose match
    leaves the target view (or crop) is not covisible and is also dropped from covis_valid, so the
    covisibility head never sees it as a negative (flow_manipulation.py:292-313, 682-704,
    841-863). True: it stays in covis_valid, supervised as not covisible. The synthetic config
    sets it: its pairs' only non-covisible pixels are out of view, so the official rule would
    train the covisibility head on positives alone.
  fast_image_ops: deviation (every recipe: False). True: OpenCV instead of PIL for the static
    crops' bicubic warp (cubic kernel a = -0.75 instead of PIL's transform kernel a = -1,
    positions in 1/32 px) and the hue jitter's HSV round trip (rounding), and Kubric's colour
    jitter on uint8 like the other sets' instead of torch's float one; labels are unchanged.
    Host CPU: docs/host_input.md.
  """
  enabled: bool = True
  no_crop_datasets: tuple[str, ...] = ("habitat",)
  flow_pathway_datasets: tuple[str, ...] = ("tartanair_v2", "tartanair")
  static_crop_candidates: int = 4
  static_correspondences: int = 500
  static_min_zoom: float = 0.1
  static_pil_sampling: bool = True
  portrait_to_landscape: bool = True
  square_random_portrait: bool = True
  identical_view_prob: float = 0.005
  expansion: tuple[float, float] = (1.0, 1.2)
  kubric_crop_candidates: int = 10
  kubric_covisible_samples: int = 2048
  kubric_score_quirk: bool = True
  photometric: bool = True
  brightness: float = 0.5
  contrast: float = 0.5
  saturation: float = 0.5
  hue: float = 0.1
  grayscale_prob: float = 0.05
  blur_prob: float = 0.05
  blur_sigma: tuple[float, float] = (0.1, 1.0)
  blur_kernel: int = 5
  low_light_prob: float = 0.01
  low_light_datasets: tuple[str, ...] = ("flyingchairs",)
  supervise_out_of_view: bool = False
  fast_image_ops: bool = False

  @classmethod
  def from_dict(cls, d: Mapping[str, Any] | None) -> "AugmentConfig":
    d = dict(d or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(d) - set(fields)
    if unknown:
      raise KeyError(f"unknown input.augment keys {sorted(unknown)}; known: {sorted(fields)}")
    for k, v in d.items():
      if isinstance(getattr(cls, k, None), tuple) or str(fields[k].type).startswith("tuple"):
        d[k] = tuple(v)
    cfg = cls(**d)
    if not 1 <= cfg.expansion[0] <= cfg.expansion[1]:
      raise ValueError(f"input.augment.expansion={cfg.expansion}: need 1 <= lo <= hi")
    if cfg.blur_kernel % 2 != 1:
      raise ValueError(f"input.augment.blur_kernel={cfg.blur_kernel} must be odd")
    return cfg


# -------------------------------------------------------------------------- the flow pathway

def random_flow_crop(hw, out_hw, rng, cfg: AugmentConfig) -> FlowCrop:
  """Short side x U(expansion), the same random offset in both views (RandomEqualCrop):
  offsets from randint(0, range), whose upper end is exclusive."""
  e = rng.uniform(*cfg.expansion)
  rh, rw = resize_short_axis_size(hw, (int(out_hw[0] * e), int(out_hw[1] * e)))
  top = int(rng.integers(0, rh - out_hw[0])) if rh > out_hw[0] else 0
  left = int(rng.integers(0, rw - out_hw[1])) if rw > out_hw[1] else 0
  return FlowCrop(tuple(hw), (rh, rw), tuple(out_hw), (top, left), (top, left))


def covisible_guided_crops(fwd: Mapping[str, Any], bwd: Mapping[str, Any], hw, out_hw, rng,
                           cfg: AugmentConfig) -> FlowCrop:
  """Kubric: short side x U(expansion), then per view the crop among `kubric_crop_candidates`
  random ones whose pair keeps most sampled covisible matches in both directions
  (CovisibleGuidedCropManipulation, flow_manipulation.py:520-641)."""
  e = rng.uniform(*cfg.expansion)
  rh, rw = resize_short_axis_size(hw, (int(out_hw[0] * e), int(out_hw[1] * e)))
  oh, ow = out_hw
  ri, ci = nearest_index(hw[0], rh), nearest_index(hw[1], rw)
  n = cfg.kubric_crop_candidates

  def draw(extent, size):
    return rng.integers(0, extent - size, n) if extent > size else np.zeros(n, np.int64)

  pairs = []
  for labels in (fwd, bwd):
    covis = np.asarray(labels["covisibility"], bool).take(ri, 0).take(ci, 1)
    flat = np.flatnonzero(covis)
    keep = rng.random(len(flat)) < cfg.kubric_covisible_samples / (len(flat) + 1e-8)
    flat = flat[keep]
    y, x = np.divmod(flat, rw)
    flow = np.asarray(labels["flow"], np.float32)[ri[y], ci[x]]
    scale = np.array([np.float32(rw / hw[1]), np.float32(rh / hw[0])], np.float32)
    tx, ty = (x + np.rint(flow[:, 0] * scale[0]).astype(np.int64),
              y + np.rint(flow[:, 1] * scale[1]).astype(np.int64))
    pairs.append((x, y, tx, ty))
  crops = [(draw(rh, oh), draw(rw, ow)) for _ in range(2)]   # view -> (tops, lefts)

  def inside(x, y, view):
    tops, lefts = crops[view]
    return ((lefts[None, :] <= x[:, None]) & (x[:, None] < lefts[None, :] + ow)
            & (tops[None, :] <= y[:, None]) & (y[:, None] < tops[None, :] + oh))

  scores = []
  for src, (x, y, tx, ty) in enumerate(pairs):   # src 0: forward, 1: backward
    a = inside(x, y, src).astype(np.float32)
    b = inside(tx, ty, 1 - src).astype(np.float32)
    scores.append((a.T @ b) / np.float32(oh * ow))   # [own candidate, other candidate]
  fwd_s, bwd_s = scores
  if not cfg.kubric_score_quirk:
    bwd_s = bwd_s.T
  iou = fwd_s * bwd_s / (fwd_s + bwd_s + np.float32(1e-8)) * 2
  i, j = np.unravel_index(int(np.argmax(iou)), iou.shape)
  return FlowCrop(tuple(hw), (rh, rw), tuple(out_hw),
                  (int(crops[0][0][i]), int(crops[0][1][i])),
                  (int(crops[1][0][j]), int(crops[1][1][j])))


# ------------------------------------------------------------------------ the static pathway

def _project_pixels(v: StaticView, other: StaticView, idx=None) -> np.ndarray:
  """Flat index of the other view's pixel each pixel of v (or its flat indices idx) lands on:
  rounded half-to-even, clipped to the image, as cropping.reproject / ravel_xy (:201-223); in
  float32, as the official point maps."""
  h, w = v.depth.shape
  h2, w2 = other.depth.shape
  rel = geometry.invert_pose(other.cam2world) @ np.asarray(v.cam2world, np.float64)
  Kinv = np.linalg.inv(np.asarray(v.K, np.float64))
  M = (np.asarray(other.K, np.float64) @ rel[:3, :3] @ Kinv).astype(np.float32)
  t = (np.asarray(other.K, np.float64) @ rel[:3, 3]).astype(np.float32)
  depth = np.asarray(v.depth, np.float32)
  if idx is None:
    u = np.arange(w, dtype=np.float32)[None, :]
    vv = np.arange(h, dtype=np.float32)[:, None]
  else:
    u, vv = (idx % w).astype(np.float32), (idx // w).astype(np.float32)
    depth = depth.ravel()[idx]
  d = np.where(np.isfinite(depth), depth, np.float32(0))
  p = [(M[i, 0] * u + (M[i, 1] * vv + M[i, 2])) * d + t[i] for i in range(3)]
  with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
    inv = np.float32(1) / p[2]
    x, y = np.rint(p[0] * inv), np.rint(p[1] * inv)
  # ravel_xy: .round().astype(int32), clipped to the image; the int32 cast of NaN, inf and
  # values beyond its range gives INT_MIN, i.e. 0 after the clip.
  with np.errstate(invalid="ignore"):
    x = np.where(np.abs(x) < 2**31, x, 0)   # NaN compares False
    y = np.where(np.abs(y) < 2**31, y, 0)
  x = np.clip(x, 0, w2 - 1).astype(np.int64)
  y = np.clip(y, 0, h2 - 1).astype(np.int64)
  return (x + w2 * y).ravel()


def crop_correspondences(v0: StaticView, v1: StaticView, n: int, rng):
  """extract_correspondences_from_pts3d(target_n_corres=n, nneg=0) (cropping.py:144-198):
  n matches drawn uniformly from the reciprocal nearest-pixel matches (a pixel whose match maps
  back onto it), topped up with random non-reciprocal pixels when there are fewer.
  -> (xy0 [n, 2], xy1 [n, 2]) integer pixel coordinates.

  Reciprocity is a per-pixel test, so a uniform sample of the reciprocal set is drawn by testing
  random pixels until n pass (the same distribution as the official sample of all of them);
  only when fewer than n pass among 16 n tried are all pixels tested (the official way)."""
  w0, w1 = v0.depth.shape[1], v1.depth.shape[1]
  size = v0.depth.size
  tried = np.zeros(0, np.int64)
  found = np.zeros(0, np.int64)
  while len(tried) < min(size, 16 * n) and len(found) < n:
    cand = np.unique(rng.integers(0, size, 2 * n))
    cand = cand[~np.isin(cand, tried, assume_unique=True)]
    cand = cand[rng.permutation(len(cand))]
    tried = np.concatenate([tried, cand])
    there = _project_pixels(v0, v1, cand)
    back = _project_pixels(v1, v0, there)
    found = np.concatenate([found, cand[back == cand]])
  if len(found) >= n:
    pos1 = found[:n]
    pos2 = _project_pixels(v0, v1, pos1)
    return (np.stack([pos1 % w0, pos1 // w0], -1), np.stack([pos2 % w1, pos2 // w1], -1))
  c12, c21 = _project_pixels(v0, v1), _project_pixels(v1, v0)
  recip1 = c21[c12] == np.arange(len(c12))
  recip2 = c12[c21] == np.arange(len(c21))
  pos1 = np.flatnonzero(recip1)
  pos2 = c12[pos1]
  n_pos = min(len(pos1), n)
  n_neg = min(n - n_pos, int(min((~recip1).sum(), (~recip2).sum())))
  if n_pos + n_neg != n:
    n_pos = n - n_neg
  if n_pos < len(pos1):
    perm = rng.permutation(len(pos1))[:n_pos]
    pos1, pos2 = pos1[perm], pos2[perm]
  if n_neg > 0:
    p1, p2 = (~recip1).astype(np.float64), (~recip2).astype(np.float64)
    pos1 = np.r_[pos1, rng.choice(len(c12), n_neg, replace=False, p=p1 / p1.sum())]
    pos2 = np.r_[pos2, rng.choice(len(c21), n_neg, replace=False, p=p2 / p2.sum())]
  return (np.stack([pos1 % w0, pos1 // w0], -1), np.stack([pos2 % w1, pos2 // w1], -1))


def static_zoom_range(hw, out_h: int, min_zoom: float = 0.1) -> float:
  """Upper end of the per-view zoom: 1 + max(f S, S (S - R) // R) / S (the 'auto' aug_crop,
  base_stereo_view_dataset.py:236-240)."""
  S, R = min(hw), int(out_h)
  aug = max(min_zoom * S, S * (S - R) // R)
  return 1.0 + aug / S


def random_crop_boxes(hw, n: int, crop_hw, zoom_max: float, rng) -> np.ndarray:
  """gen_random_crops (cropping.py:352-369): n boxes (x0, y0, x1, y1) of the crop's aspect, all
  of one zoom drawn log-uniformly in [1, zoom_max], placed uniformly on the zoomed image."""
  size = np.array([hw[1], hw[0]], np.float64)
  res = np.array([crop_hw[1], crop_hw[0]], np.float64)
  crop = res * min(size / res)
  scaling = float(np.exp(rng.uniform(0, np.log(zoom_max))))
  size2 = np.floor(size * scaling).astype(np.int32)
  topleft = rng.random((n, 2)) * (size2 - crop)
  return np.c_[topleft, topleft + crop] / scaling


def crop_view_affine(v: StaticView, box, crop_hw, pil_sampling: bool = True,
                     fast: bool = False) -> StaticView:
  """crop_to_homography_no_rotation (cropping.py:318-349) + the PIL image / depth warps
  (base_stereo_view_dataset.py:269-303): the box (rounded) is mapped onto crop_hw with the
  box corners at output 0 and W (H); bicubic image, nearest depth (0 outside the image).

  The homography is a scale and shift per axis, so the depth is gathered per row and column
  where PIL's nearest sampling reads it; fast=True warps the image with OpenCV's bicubic
  (a = -0.75, positions in 1/32 px) instead of PIL's transform (a = -1: libImaging/Geometry.c's
  BICUBIC, each output pixel's 4 x 4 taps in double, truncated to uint8; its bytes computed by
  `pil_warp.bicubic_transform`)."""
  sx, sy, ex, ey = np.round(np.asarray(box, np.float64))
  ch, cw = crop_hw
  ax, ay = cw / (ex - sx), ch / (ey - sy)
  A = np.array([[ax, 0.0, -sx * ax], [0.0, ay, -sy * ay], [0.0, 0.0, 1.0]])
  K = np.asarray(v.K, np.float64)
  K2 = (A @ K).astype(np.float32)
  Hm = (K.astype(np.float32) @ np.linalg.inv(K2)).astype(np.float32)   # output -> input
  c = (Hm / Hm[2, 2]).ravel()[:8].astype(np.float64)
  # PIL maps output pixel x to input position c0 (x + 0.5) + c2 in its frame (pixel i spans
  # [i, i + 1]), i.e. pixel-centre coordinate c0 x + 0.5 c0 + c2 - 0.5; K2 says c0 x + c2.
  shift = (0.5 * c[0] - 0.5, 0.5 * c[4] - 0.5) if pil_sampling else (0.0, 0.0)
  x_in = c[0] * np.arange(cw) + c[2] + shift[0]   # pixel-centre input coordinates
  y_in = c[4] * np.arange(ch) + c[5] + shift[1]
  h, w = v.depth.shape
  # Nearest: PIL reads pixel int(position in its frame) (-1, i.e. nothing, below 0).
  xi, yi = np.floor(x_in + 0.5).astype(np.int64), np.floor(y_in + 0.5).astype(np.int64)
  depth = np.asarray(v.depth, np.float32)[np.clip(yi, 0, h - 1)][:, np.clip(xi, 0, w - 1)]
  depth[(yi < 0) | (yi >= h)] = 0
  depth[:, (xi < 0) | (xi >= w)] = 0
  if fast:
    M = np.array([[c[0], 0.0, c[2] + shift[0]], [0.0, c[4], c[5] + shift[1]]])
    image = cv2.warpAffine(np.ascontiguousarray(v.image), M, (cw, ch),
                           flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
  else:
    data = tuple(float(x) for x in c)
    if not pil_sampling:   # shift PIL's frame so that it samples where K2 says
      data = (data[0], data[1], data[2] + 0.5 - 0.5 * data[0], data[3], data[4],
              data[5] + 0.5 - 0.5 * data[4], data[6], data[7])
    if data[1] == data[3] == data[6] == data[7] == 0.0:   # PIL's bytes, ~3x faster
      image = pil_warp.bicubic_transform(v.image, data, (cw, ch))
    else:
      image = np.asarray(Image.fromarray(np.asarray(v.image)).transform(
          (cw, ch), Image.PERSPECTIVE, data, resample=Image.BICUBIC))
  return StaticView(image, depth, K2.astype(np.float64), np.asarray(v.cam2world, np.float64))


def static_crop_pair(v0: StaticView, v1: StaticView, out_hw, rng, cfg: AugmentConfig):
  """aug_crop='auto_crop_asis' (generate_crops_from_pair, base_stereo_view_dataset.py:228-303):
  per view `static_crop_candidates` boxes of one random zoom; the pair of boxes that holds the
  most correspondences (ties: the first) is cropped; portrait crops turned to landscape."""
  corres = crop_correspondences(v0, v1, cfg.static_correspondences, rng)
  boxes, shapes, inside = [], [], []
  for v, xy in zip((v0, v1), corres):
    hw = v.depth.shape
    crop_hw, portrait = portrait_resolution(hw, out_hw, rng, cfg.square_random_portrait)
    if not cfg.portrait_to_landscape:
      crop_hw, portrait = tuple(out_hw), False
    b = random_crop_boxes(hw, cfg.static_crop_candidates, crop_hw,
                          static_zoom_range(hw, out_hw[0], cfg.static_min_zoom), rng)
    boxes.append(b)
    shapes.append((crop_hw, portrait))
    inside.append(((xy[:, None] >= b[None, :, :2]) & (xy[:, None] < b[None, :, 2:])).all(-1))
  shared = inside[0].astype(np.float32).T @ inside[1].astype(np.float32)
  best = np.unravel_index(int(np.argmax(shared)), shared.shape)
  out = []
  for v, b, k, (crop_hw, portrait) in zip((v0, v1), boxes, best, shapes):
    c = crop_view_affine(v, b[k], crop_hw, cfg.static_pil_sampling, cfg.fast_image_ops)
    out.append(rotate_to_landscape(c) if portrait else c)
  return out


def static_labels(v0: StaticView, v1: StaticView, params) -> tuple[dict, dict]:
  """Forward and backward labels of a (cropped) static pair (`geometry.official_labels`)."""
  keys = LABEL_KEYS
  f = geometry.official_labels(v0.depth, v0.K, v0.cam2world, v1.depth, v1.K, v1.cam2world, params)
  b = geometry.official_labels(v1.depth, v1.K, v1.cam2world, v0.depth, v0.K, v0.cam2world, params)
  return {k: f[k] for k in keys}, {k: b[k] for k in keys}


# ------------------------------------------------------------------------------------ colour

def _blend_lut(base: float, factor: float) -> np.ndarray:
  """PIL Image.blend(constant base, image, factor) on uint8 as a lookup table: float32
  base + factor (x - base), clipped, truncated."""
  x = np.arange(256, dtype=np.float32)
  return trunc_u8(np.float32(base) + np.float32(factor) * (x - np.float32(base)))


def color_jitter(image: np.ndarray, params, fast: bool = False) -> np.ndarray:
  """torchvision ColorJitter on a PIL image: params = (order, brightness, contrast, saturation,
  hue), order a permutation of range(4) (0 brightness, 1 contrast, 2 saturation, 3 hue).
  PIL's ImageEnhance semantics (brightness and contrast as the equivalent lookup tables) and its
  HSV conversion, as torchvision's PIL path: the hue shift through PIL's conversions tabulated
  over every colour (`hsv_tables`, equal to PIL's; fast: OpenCV's HSV, which rounds otherwise)."""
  if params is None:
    return image
  order, b, c, s, h = params
  img = np.ascontiguousarray(image)
  for op in order:
    if op == 0:
      img = cv2.LUT(img, _blend_lut(0.0, b))
    elif op == 1:
      mean = int(np.asarray(Image.fromarray(img).convert("L")).mean() + 0.5)
      img = cv2.LUT(img, _blend_lut(mean, c))
    elif op == 2:
      img = np.asarray(ImageEnhance.Color(Image.fromarray(img)).enhance(s))
    elif fast:
      hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV_FULL)
      hsv[..., 0] += np.int32(h * 255).astype(np.uint8)   # wraps mod 256
      img = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB_FULL)
    else:
      img = hsv_tables.adjust_hue(img, int(np.int32(h * 255)))   # int8(hue * 255), mod 256
  return img


def color_jitter_float(image: np.ndarray, params) -> np.ndarray:
  """torchvision ColorJitter on a float tensor in [0, 1] (the Kubric path, kubric4d.py:171-178),
  returned as the official `(img * 255).to(uint8)`."""
  x = np.asarray(image, np.float32) / np.float32(255)
  if params is not None:
    order, b, c, s, h = params
    weights = np.array([[0.2989, 0.587, 0.114]], np.float32)   # torchvision rgb_to_grayscale
    for op in order:
      if op == 0:
        x *= np.float32(b)
      elif op == 1:
        mean = np.float32(cv2.mean(cv2.transform(x, weights))[0])
        x *= np.float32(c)
        x += np.float32(1 - c) * mean
      elif op == 2:
        grey = cv2.transform(x, np.float32(1 - s) * weights)
        x *= np.float32(s)
        x += grey[..., None]
      else:
        # On the contiguous hue plane; x - floor(x) is mod 1 to the last bit for finite x (the
        # subtraction is exact where np.mod's "+ 1" of a negative fmod rounds to the same value).
        hue, sat, val = cv2.split(cv2.cvtColor(x, cv2.COLOR_RGB2HSV))
        hue *= np.float32(1 / 360)
        hue += np.float32(h)
        np.subtract(hue, np.floor(hue), out=hue)
        hue *= np.float32(360)
        x = cv2.cvtColor(cv2.merge((hue, sat, val)), cv2.COLOR_HSV2RGB)
      np.clip(x, 0, 1, out=x)
  x *= np.float32(255)
  return x.astype(np.uint8)


def draw_color(rng, cfg: AugmentConfig):
  """ColorJitter.get_params: a random order and the four factors."""
  return (tuple(int(i) for i in rng.permutation(4)),
          float(rng.uniform(max(0.0, 1 - cfg.brightness), 1 + cfg.brightness)),
          float(rng.uniform(max(0.0, 1 - cfg.contrast), 1 + cfg.contrast)),
          float(rng.uniform(max(0.0, 1 - cfg.saturation), 1 + cfg.saturation)),
          float(rng.uniform(-cfg.hue, cfg.hue)))


def grayscale(image: np.ndarray) -> np.ndarray:
  """RandomGrayscale's PIL path: convert('L') replicated to three channels."""
  grey = np.asarray(Image.fromarray(np.asarray(image)).convert("L"))
  return np.repeat(grey[..., None], 3, axis=2)


def gaussian_blur(image: np.ndarray, sigma: float, kernel: int = 5) -> np.ndarray:
  """torchvision gaussian_blur on a uint8 image: float32 separable kernel, reflect padding,
  rounded back."""
  half = (kernel - 1) * 0.5
  x = np.linspace(-half, half, kernel, dtype=np.float32)
  pdf = np.exp(-0.5 * (x / np.float32(sigma)) ** 2)
  k = (pdf / pdf.sum()).astype(np.float32)
  out = cv2.sepFilter2D(np.asarray(image, np.float32), -1, k, k, borderType=cv2.BORDER_REFLECT_101)
  return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def low_light(image: np.ndarray, rng) -> np.ndarray:
  """apply_darkening_and_quantization (base_stereo_view_dataset.py:433-463): x U(0.1, 0.3),
  16 levels, N(0, 0.02*255) noise, U(0, 0.08*255) bias; the official float result is rounded
  to uint8 here (our batches carry uint8 images)."""
  x = np.clip(np.asarray(image, np.float64) * rng.uniform(0.1, 0.3), 0, 255)
  step = 255.0 / 16
  x = np.floor(x / step) * step
  x += rng.normal(0.0, 0.02 * 255, x.shape)
  x += rng.uniform(0, 0.08 * 255, x.shape)
  return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def photometric(image: np.ndarray, rng, cfg: AugmentConfig, low_light_on: bool,
                static: bool) -> np.ndarray:
  """One image's colour augmentation in the official order: jitter, grayscale, blur, low light
  (static datasets grey the image first, base_stereo_view_dataset.py:370-373)."""
  if not cfg.photometric:
    return image
  image = color_jitter(image, draw_color(rng, cfg), cfg.fast_image_ops)
  if rng.random() < cfg.grayscale_prob:
    image = grayscale(image)
  if rng.random() < cfg.blur_prob:
    image = gaussian_blur(image, rng.uniform(*cfg.blur_sigma), cfg.blur_kernel)
  if low_light_on and rng.random() < cfg.low_light_prob:
    image = low_light(grayscale(image) if static else image, rng)
  return np.ascontiguousarray(image)


# ------------------------------------------------------------------- pairs through a pathway

def _row(image0, image1, labels) -> dict:
  return {"image0": np.ascontiguousarray(image0), "image1": np.ascontiguousarray(image1),
          **{k: np.ascontiguousarray(v) for k, v in labels.items()}}


def static_pair(v0: StaticView, v1: StaticView, params, out_hw, rng, cfg: AugmentConfig, *,
                crop: bool = True, low_light_on: bool = False, backward: bool = True):
  """A static pair through the official static pathway -> [fwd] or [fwd, bwd] rows (the
  backward row shows the same two images swapped)."""
  if cfg.enabled and crop:
    v0, v1 = static_crop_pair(v0, v1, out_hw, rng, cfg)
  else:
    v0, v1 = (resize_cover_center_crop(v, out_hw, cfg.portrait_to_landscape) for v in (v0, v1))
  if cfg.enabled:
    v0.image = photometric(v0.image, rng, cfg, low_light_on, static=True)
    v1.image = photometric(v1.image, rng, cfg, low_light_on, static=True)
    if rng.random() < cfg.identical_view_prob:
      v1 = dataclasses.replace(v0)
  fwd, bwd = static_labels(v0, v1, params)
  rows = [_row(v0.image, v1.image, fwd)]
  if backward:
    rows.append(_row(v1.image, v0.image, bwd))
  return rows


def flow_pair(sample: Mapping[str, Any], backward: Mapping[str, Any] | None, out_hw, rng,
              cfg: AugmentConfig, *, low_light_on: bool = False, grid=None):
  """Stored labels through the official flow pathway -> [fwd] or [fwd, bwd] rows.

  grid: (forward grid, backward grid) when the labels hold only `FlowCrop.source_grid`'s
  pixels; use `flow_crop` first to know them (the pipeline's lazily labelled sources)."""
  crop = flow_crop(sample["image0"].shape[:2], out_hw, rng, cfg)
  return flow_pair_with_crop(sample, backward, crop, rng, cfg, low_light_on=low_light_on,
                             grid=grid)


def flow_crop(hw, out_hw, rng, cfg: AugmentConfig) -> FlowCrop:
  return random_flow_crop(hw, out_hw, rng, cfg) if cfg.enabled else center_flow_crop(hw, out_hw)


def flow_pair_with_crop(sample, backward, crop: FlowCrop, rng, cfg: AugmentConfig, *,
                        low_light_on: bool = False, grid=None, jittered: bool = False):
  if np.shape(sample["image0"]) != np.shape(sample["image1"]):
    raise ValueError(f"flow pathway: image shapes {np.shape(sample['image0'])} and "
                     f"{np.shape(sample['image1'])} differ (the official pathway needs equal ones)")
  image0, image1 = flow_crop_images(sample["image0"], sample["image1"], crop)
  if cfg.enabled and not jittered:
    image0 = photometric(image0, rng, cfg, low_light_on, static=False)
    image1 = photometric(image1, rng, cfg, low_light_on, static=False)
  g0, g1 = grid or (None, None)
  rules = ("in_crop", "in_crop") if cfg.enabled else ("center_forward", "center_backward")
  if cfg.supervise_out_of_view:
    rules = ("keep", "keep")
  rows = [_row(image0, image1, flow_crop_labels(_labels(sample), crop, 0, rules[0], g0))]
  if backward is not None:
    rows.append(_row(image1, image0, flow_crop_labels(_labels(backward), crop, 1, rules[1], g1)))
  return rows


def kubric_pair(sample: Mapping[str, Any], backward: Mapping[str, Any], out_hw, rng,
                cfg: AugmentConfig, *, with_backward: bool = True):
  """Kubric-4D through the official Kubric pathway (labels at the stored size, colour jitter on
  the stored images, then crops) -> [fwd] or [fwd, bwd] rows."""
  hw = np.shape(sample["image0"])[:2]
  colors = ((draw_color(rng, cfg), draw_color(rng, cfg)) if cfg.enabled and cfg.photometric
            else (None, None))
  jitter = ((lambda im, p: color_jitter(im, p, fast=True)) if cfg.fast_image_ops else
            color_jitter_float)
  images = {"image0": jitter(sample["image0"], colors[0]),
            "image1": jitter(sample["image1"], colors[1])}
  crop = (covisible_guided_crops(sample, backward, hw, out_hw, rng, cfg) if cfg.enabled else
          center_flow_crop(hw, out_hw))
  return flow_pair_with_crop({**_labels(sample), **images}, backward if with_backward else None,
                             crop, rng, cfg, jittered=True)


def _labels(sample: Mapping[str, Any]) -> dict:
  return {k: sample[k] for k in LABEL_KEYS + ("fov_mask",) if k in sample}


# ----------------------------------------------------------------------- no augmentation

def official_no_aug(sample: Mapping[str, Any], out_hw, kind: str,
                    backward: Mapping[str, Any] | None = None, params=None) -> list[dict]:
  """What the official dataset classes return with aug_crop=False, transform='imgnorm', at
  out_hw = (H, W) (images still uint8, not normalised): [forward] or [forward, backward] dicts
  with image0, image1, flow, covisibility (non_occluded_mask), flow_valid, covis_valid
  (occlusion_supervision_mask) and, where the input has one, fov_mask.

  kind 'static': `sample` in the dict interface with meta depth0/1, K0/1, cam2world0/1 (z-depth,
    OpenCV, 0 = no depth); each view `resize_cover_center_crop`, then `official_labels` with
    `params` (default: `geometry.rendering_parameters(meta['dataset'])`); both directions are
    returned (the official batch labels both views). The rows' meta hold the cropped cameras.
  kind 'flow': stored labels (forward `sample`, optional `backward` = the image1 -> image0
    labels): ResizeShortAxis + CenterCrop with the official mask update (forward masks AND-ed
    with the covisibility before the crop test, backward with the one after it; flow_valid only
    resized and cropped); images resized in float with antialiasing and truncated.
  kind 'kubric': 'flow' with the images first through the Kubric loader's float round trip
    (uint8 / 255 * 255, truncated).
  """
  out_hw = tuple(int(s) for s in out_hw)
  cfg = AugmentConfig(enabled=False)
  if kind == "static":
    meta = sample["meta"]
    if params is None:
      params = geometry.rendering_parameters(str(meta.get("dataset", "")))
      if params is None:
        raise ValueError(f"official_no_aug: no covisible_rendering_parameters for dataset "
                         f"{meta.get('dataset')!r}; pass params=(absolute, temperature, relative)")
    views = [StaticView(np.asarray(sample[f"image{i}"]), np.asarray(meta[f"depth{i}"]),
                        np.asarray(meta[f"K{i}"]), np.asarray(meta[f"cam2world{i}"]))
             for i in (0, 1)]
    v0, v1 = (resize_cover_center_crop(v, out_hw) for v in views)
    fwd, bwd = static_labels(v0, v1, params)
    cams = lambda a, b: {"meta": {"K0": a.K, "K1": b.K, "cam2world0": a.cam2world,
                                  "cam2world1": b.cam2world, "depth0": a.depth, "depth1": b.depth}}
    return [{**_row(v0.image, v1.image, fwd), **cams(v0, v1)},
            {**_row(v1.image, v0.image, bwd), **cams(v1, v0)}]
  if kind == "kubric":
    return kubric_pair(sample, backward, out_hw, None, cfg, with_backward=backward is not None)
  if kind == "flow":
    return flow_pair(sample, backward, out_hw, None, cfg)
  raise ValueError(f"official_no_aug: kind must be 'static', 'flow' or 'kubric', got {kind!r}")
