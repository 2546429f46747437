"""PyTorch-exact image resampling on the host (CPU float32 kernels): the antialiased bilinear
resize of the official predict, plain bilinear and legacy nearest. One home for the resizes that
inference (ufm_jax.runtime.inference), the official augmentation and the benchmark readers
(ufm_jax.data.official_ops) share.
"""

from __future__ import annotations

import functools

import numpy as np

_f32 = np.float32


@functools.lru_cache(maxsize=64)
def aa_linear_weights(in_size: int, out_size: int) -> np.ndarray:
  """[out, in] float32 matrix of `F.interpolate(bilinear, align_corners=False, antialias=True)`.

  Mirrors ATen's `_compute_indices_min_size_weights_aa` for the linear (triangle) filter: the
  support is `scale` when downsampling (filter stretched by `scale`), 1 when upsampling (plain
  bilinear with edge clamping); weights normalised to sum 1. float32 like the CPU kernel.
  """
  scale = _f32(in_size) / _f32(out_size)
  support = _f32(1.0) * scale if scale >= 1.0 else _f32(1.0)
  invscale = _f32(1.0 / float(scale)) if scale >= 1.0 else _f32(1.0)
  mat = np.zeros((out_size, in_size), np.float32)
  for i in range(out_size):
    center = _f32(float(scale) * (i + 0.5))
    xmin = max(int(float(center - support) + 0.5), 0)
    xmax = min(int(float(center + support) + 0.5), in_size)
    j = np.arange(xmin, xmax)
    # (j + xmin - center + 0.5) in float32 then times invscale
    arg = ((j.astype(np.float32) - center).astype(np.float64) + 0.5) * float(invscale)
    w = np.maximum(_f32(1.0) - np.abs(arg.astype(np.float32)), _f32(0.0)).astype(np.float32)
    total = _f32(0.0)
    for v in w:
      total = _f32(total + v)
    if total != 0:
      w = (w / total).astype(np.float32)
    mat[i, xmin:xmax] = w
  return mat


def resize_bilinear_aa(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """[..., H, W, C] float -> [..., h, w, C] float32: torch bilinear antialias resize.

  Separable like ATen: the width pass first, then the height pass (a dim whose size does not
  change is copied, not filtered).
  """
  x = np.asarray(image, np.float32)
  h_in, w_in = x.shape[-3], x.shape[-2]
  h, w = size
  if w != w_in:  # [..., H, W, C] x [w, W] -> [..., H, C, w] -> [..., H, w, C]
    x = np.moveaxis(np.tensordot(x, aa_linear_weights(w_in, w), axes=([-2], [1])), -1, -2)
  if h != h_in:
    x = np.moveaxis(np.tensordot(x, aa_linear_weights(h_in, h), axes=([-3], [1])), -1, -3)
  return np.ascontiguousarray(x, np.float32)


def _linear_indices(in_size: int, out_size: int):
  """Indices/weights of torch bilinear (align_corners=False, no antialias) along one axis."""
  scale = _f32(in_size) / _f32(out_size)
  dst = np.arange(out_size, dtype=np.float32)
  src = np.maximum(scale * (dst + _f32(0.5)) - _f32(0.5), _f32(0.0)).astype(np.float32)
  i0 = np.minimum(np.floor(src).astype(np.int64), in_size - 1)
  lam = np.clip(src - i0.astype(np.float32), 0.0, 1.0).astype(np.float32)
  i1 = i0 + (i0 < in_size - 1)
  return i0, i1, lam


def resize_bilinear(x: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """[H, W, C] -> [h, w, C] float32, torch `bilinear`, align_corners=False, no antialias."""
  x = np.asarray(x, np.float32)
  y0, y1, ly = _linear_indices(x.shape[0], size[0])
  x0, x1, lx = _linear_indices(x.shape[1], size[1])
  ly, lx = ly[:, None, None], lx[None, :, None]
  top = (_f32(1) - lx) * x[y0][:, x0] + lx * x[y0][:, x1]
  bot = (_f32(1) - lx) * x[y1][:, x0] + lx * x[y1][:, x1]
  return ((_f32(1) - ly) * top + ly * bot).astype(np.float32)


def nearest_index(in_size: int, out_size: int) -> np.ndarray:
  """torch legacy 'nearest': floor(dst * float32(in / out)), with ATen's exact-ratio shortcuts."""
  dst = np.arange(out_size)
  if out_size == in_size:
    return dst
  if out_size == 2 * in_size:
    return dst >> 1
  scale = _f32(in_size) / _f32(out_size)
  return np.minimum(np.floor(dst.astype(np.float32) * scale).astype(np.int64), in_size - 1)


def resize_nearest(x: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """[H, W, ...] -> [h, w, ...], torch legacy `nearest`."""
  x = np.asarray(x)
  return x[nearest_index(x.shape[0], size[0])][:, nearest_index(x.shape[1], size[1])]
