"""The official resize and crop operations, shared by the training augmentation
(ufm_jax.data.augment) and the benchmark readers (ufm_jax.data.sources._benchmark_branch): the
official training and benchmark branches run the same dataset code (etola/UFM train d8c421e,
benchmark 2a949e5; paths below are relative to its root).

* Flow sets (labels stored per pixel): `ResizeShortAxisManipulation` then a crop of both views
  (`FlowCrop`; `center_flow_crop` = `CenterCropManipulation`), images with torch's antialiased
  bilinear truncated to uint8 (`flow_crop_images`), flow and masks with legacy nearest, the masks
  cut where a match leaves the crop (`flow_crop_labels`; utils/flow_manipulation.py:224-347,
  488-503, 682-704, 841-863; base/base_optical_flow_dataset.py:64-106).
* Posed views (depth + cameras): `BaseStereoViewDataset._crop_resize_if_necessary`
  (`resize_cover_center_crop`; base/base_stereo_view_dataset.py:183-211, utils/cropping.py:60-132)
  and the turn of portrait views to landscape (`rotate_to_landscape`, :492-529).

Pixel convention: integer (u, v) is a pixel centre (OpenCV), as in all official label code.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import cv2
import numpy as np
from PIL import Image

from ufm_jax.data import resize
# torch's legacy 'nearest' index, shared with the model's input and output resizing.
from ufm_jax.data.resize import nearest_index


# ----------------------------------------------------------------------------------- resampling

def trunc_u8(x: np.ndarray) -> np.ndarray:
  """float -> uint8 as torch's `.to(torch.uint8)` on values clamped to [0, 255]: truncation."""
  return np.clip(x, 0, 255).astype(np.uint8)


def resize_bilinear_aa(image: np.ndarray, size_hw, box_hw=None) -> np.ndarray:
  """torch `F.interpolate(bilinear, align_corners=False, antialias=True)` of a uint8 image in
  float, cast back with `.to(uint8)` (truncation): the official flow-set image resize.

  box_hw = (top, left, h, w): only that window of the `size_hw` result. Downsampling: PIL's
  identical antialiased bilinear, in float, on the source region of the window (the same pixels
  as resizing all and cropping); upsampling: OpenCV's float bilinear of the whole image, then the
  window."""
  image = np.asarray(image)
  H, W = image.shape[:2]
  h, w = (int(s) for s in size_hw)
  top, left, oh, ow = box_hw if box_hw is not None else (0, 0, h, w)
  if h >= H and w >= W:
    # Upsampling: the antialiasing filter's support is one pixel, i.e. plain bilinear with
    # half-pixel centres, which OpenCV's float resize computes several times faster than three
    # PIL planes (and closer to torch's weights).
    full = cv2.resize(image.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    return trunc_u8(full[top:top + oh, left:left + ow])
  sy, sx = H / h, W / w
  box = (left * sx, top * sy, min((left + ow) * sx, W), min((top + oh) * sy, H))
  out = np.empty((oh, ow, 3), np.float32)
  for c in range(3):
    plane = Image.fromarray(np.ascontiguousarray(image[..., c], np.float32), "F")
    out[..., c] = np.asarray(plane.resize((ow, oh), Image.BILINEAR, box=box))
  return trunc_u8(out)


def resize_short_axis_size(hw, min_hw) -> tuple[int, int]:
  """ResizeShortAxisManipulation(min_hw).output_shape (flow_manipulation.py:492-499)."""
  H, W = hw
  ratio = max(min_hw[0] / H + 1e-8, min_hw[1] / W + 1e-8)
  return int(H * ratio), int(W * ratio)


# ------------------------------------------------------------------------------- flow crops

@dataclasses.dataclass(frozen=True)
class FlowCrop:
  """Resize both views to `resized_hw` (from `hw`), then crop `out_hw` at (top, left) per view."""
  hw: tuple[int, int]
  resized_hw: tuple[int, int]
  out_hw: tuple[int, int]
  crop0: tuple[int, int]    # (top, left) in view 0
  crop1: tuple[int, int]    # (top, left) in view 1

  def source_grid(self, view: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the stored pixels the crop of `view` reads (nearest taps), sorted."""
    (top, left) = self.crop0 if view == 0 else self.crop1
    rows = nearest_index(self.hw[0], self.resized_hw[0])[top:top + self.out_hw[0]]
    cols = nearest_index(self.hw[1], self.resized_hw[1])[left:left + self.out_hw[1]]
    return rows, cols


def center_flow_crop(hw, out_hw) -> FlowCrop:
  """ResizeShortAxisManipulation(out_hw) + CenterCropManipulation(out_hw)."""
  rh, rw = resize_short_axis_size(hw, out_hw)
  c = ((rh - out_hw[0]) // 2, (rw - out_hw[1]) // 2)
  return FlowCrop(tuple(hw), (rh, rw), tuple(out_hw), c, c)


def flow_crop_images(image0, image1, crop: FlowCrop, exact: bool = False):
  """Both images resized to `crop.resized_hw` and cropped at their (top, left).

  exact=False (the training rows): `resize_bilinear_aa`, faster; its weights round differently
  from torch's, so a few pixels are one grey level off. exact=True (the benchmarks): torch's
  weights to the last bit (`ufm_jax.data.resize.resize_bilinear_aa`) on the whole image, then the
  crop."""
  out = []
  for image, (top, left) in ((image0, crop.crop0), (image1, crop.crop1)):
    if exact:
      full = resize.resize_bilinear_aa(np.asarray(image, np.float32), crop.resized_hw)
      out.append(trunc_u8(full[top:top + crop.out_hw[0], left:left + crop.out_hw[1]]))
    else:
      out.append(resize_bilinear_aa(image, crop.resized_hw, (top, left) + crop.out_hw))
  return out


def in_frame(flow: np.ndarray) -> np.ndarray:
  """x + u in [0, W), y + v in [0, H) (float32, integer pixel index; NaN flow passes, as the
  official `fov_mask[(x < 0) | ...] = False`)."""
  h, w = flow.shape[:2]
  x = np.arange(w, dtype=np.float32)[None, :] + flow[..., 0]
  y = np.arange(h, dtype=np.float32)[:, None] + flow[..., 1]
  with np.errstate(invalid="ignore"):
    return ~((x < 0) | (y < 0) | (x >= w) | (y >= h))


def flow_crop_labels(labels: Mapping[str, Any], crop: FlowCrop, view: int, mask_rule: str,
                     grid: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
  """Labels of the pair whose source is `view`, resized (nearest) and cropped like its image.

  mask_rule 'in_crop' (random crops, flow_manipulation.py:682-704, 841-863): covisibility and
  covis_valid (and fov_mask) are AND-ed with "the match stays inside the other crop".
  'center_forward' / 'center_backward' (CenterCropManipulation, :292-313): covisibility is, and
  covis_valid / fov_mask are AND-ed with the covisibility from before that test (forward) or
  after it (backward). 'keep' (not official, `AugmentConfig.supervise_out_of_view`): covisibility
  is AND-ed with the in-crop test, covis_valid and fov_mask are left as they are. flow_valid
  (where the flow is defined) is only resized and cropped.
  grid: the labels hold only the stored pixels rows x cols (`FlowCrop.source_grid`).
  """
  rows, cols = crop.source_grid(view)
  if grid is not None:
    rows, cols = np.searchsorted(grid[0], rows), np.searchsorted(grid[1], cols)
  (h, w), (rh, rw) = crop.hw, crop.resized_hw
  (top, left), (otop, oleft) = ((crop.crop0, crop.crop1) if view == 0 else
                                (crop.crop1, crop.crop0))
  oh, ow = len(rows), len(cols)
  # Rows gathered as contiguous copies, columns as 8-byte (u, v) items; the scale and shift per
  # interleaved (u, v) column (numpy is slow broadcasting over a trailing axis of 2).
  flow = np.ascontiguousarray(labels["flow"], np.float32).take(rows, 0)
  flow = flow.view(np.complex64)[..., 0].take(cols, 1).view(np.float32)
  flow *= np.tile(np.float32([rw / w, rh / h]), ow)
  if (top, left) != (otop, oleft):
    flow += np.tile(np.float32([left - oleft, top - otop]), ow)
  flow = flow.reshape(oh, ow, 2)
  # The masks packed as bits of one uint8 plane: one gather for all.
  masks = [k for k in ("covisibility", "flow_valid", "covis_valid", "fov_mask") if k in labels]
  packed = np.zeros(np.shape(labels[masks[0]]), np.uint8)
  for bit, k in enumerate(masks):
    packed |= np.asarray(labels[k], bool).view(np.uint8) << bit
  packed = packed.take(rows, 0).take(cols, 1)
  out = {"flow": flow}
  for bit, k in enumerate(masks):
    out[k] = (packed & (1 << bit)) != 0
  inside = in_frame(flow)
  before = out["covisibility"]
  out["covisibility"] = before & inside
  extra = {"in_crop": inside, "center_forward": before,
           "center_backward": out["covisibility"], "keep": None}[mask_rule]
  for k in ("covis_valid", "fov_mask"):
    if k in out and extra is not None:
      out[k] = out[k] & extra
  return out


# ------------------------------------------------------------------------- posed views

@dataclasses.dataclass
class StaticView:
  image: np.ndarray       # [H, W, 3] uint8
  depth: np.ndarray       # [H, W] z-depth, 0 = invalid
  K: np.ndarray           # [3, 3] OpenCV
  cam2world: np.ndarray   # [4, 4]


def portrait_resolution(hw, out_hw, rng, random_square: bool):
  """Official per-view choice of the crop orientation: (h, w) to crop, and whether it is the
  transposed (portrait) one that `rotate_to_landscape` later turns."""
  H, W = hw
  oh, ow = out_hw
  if H > 1.1 * W:
    return (ow, oh), True
  if 0.9 < H / W < 1.1 and oh != ow and random_square and rng is not None and rng.integers(2):
    return (ow, oh), True
  return (oh, ow), False


def rotate_to_landscape(v: StaticView) -> StaticView:
  """rotate_90(k=1) (base_stereo_view_dataset.py:492-529): the image turned counter-clockwise,
  K and the pose so that the turned view sees the same rays: u' = v, v' = W - 1 - u."""
  h, w = v.depth.shape
  K = np.asarray(v.K, np.float64)
  K2 = np.array([[K[1, 1], 0.0, K[1, 2]], [0.0, K[0, 0], w - 1 - K[0, 2]], [0.0, 0.0, 1.0]])
  rz = np.eye(4)
  rz[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
  return StaticView(np.ascontiguousarray(np.rot90(v.image)),
                    np.ascontiguousarray(np.rot90(v.depth)), K2,
                    np.asarray(v.cam2world, np.float64) @ rz)


def resize_cover_center_crop(v: StaticView, out_hw, landscape: bool = True) -> StaticView:
  """`_crop_resize_if_necessary` (base_stereo_view_dataset.py:183-211, cropping.py:60-132):
  rescale so the image covers the (orientation-matched) shape (PIL Lanczos when shrinking,
  bicubic otherwise; depth cv2 nearest; K through the +0.5 COLMAP convention), crop the centre
  (offsets rounded half-to-even), then turn a portrait view to landscape."""
  (oh, ow), portrait = portrait_resolution(v.depth.shape, out_hw, None, False)
  H, W = v.depth.shape
  size = np.array([W, H])
  scale = max(np.array([ow, oh]) / size) + 1e-8
  new = np.floor(size * scale).astype(int)
  image = Image.fromarray(np.asarray(v.image)).resize(
      tuple(int(s) for s in new), Image.LANCZOS if scale < 1 else Image.BICUBIC)
  depth = cv2.resize(np.asarray(v.depth, np.float32), (int(new[0]), int(new[1])),
                     interpolation=cv2.INTER_NEAREST)
  # The official numpy operations, in K's own dtype (cropping.py:93-132), so that the rounded
  # crop offset ties break as there.
  K = _camera_matrix_of_crop(np.asarray(v.K), size, new, scale)
  left, top = np.int32(np.round(K[:2, 2] - _camera_matrix_of_crop(K, new, np.array([ow, oh]),
                                                                   1)[:2, 2]))
  K = K.copy()
  K[0, 2] -= left
  K[1, 2] -= top
  out = StaticView(np.ascontiguousarray(np.asarray(image)[top:top + oh, left:left + ow]),
                   np.ascontiguousarray(depth[top:top + oh, left:left + ow]), K,
                   np.asarray(v.cam2world, np.float64))
  return rotate_to_landscape(out) if portrait and landscape else out


def _camera_matrix_of_crop(K, in_res, out_res, scaling):
  """cropping.camera_matrix_of_crop with offset_factor 0.5 (through the COLMAP +0.5 frame)."""
  offset = 0.5 * (np.asarray(in_res) * scaling - out_res)
  K = K.copy()
  K[0, 2] += 0.5
  K[1, 2] += 0.5
  K[:2, :] *= scaling
  K[:2, 2] -= offset
  K[0, 2] -= 0.5
  K[1, 2] -= 0.5
  return K
