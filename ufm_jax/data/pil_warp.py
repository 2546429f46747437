"""PIL's bicubic `Image.transform` of an RGB image for a scale + shift per axis (the official static
crop warp, base_stereo_view_dataset.py:289-293: PERSPECTIVE with a homography that has no
rotation), computed to the same bytes ~3x faster.

Pillow (libImaging/Geometry.c: perspective_transform, the BICUBIC macros, bicubic_filter32RGB)
maps output pixel (x, y) to the input position (a0 (x + 0.5) + a2, a4 (y + 0.5) + a5), fills
pixels whose position falls outside the image with 0, and otherwise interpolates the 4 x 4
neighbours around position - 0.5 (indices clamped to the image) with the cubic convolution of
a = -1, in double: each of the 4 rows in Horner form at the fractional x, then those 4 values at
the fractional y, the result clipped to [0, 255] and truncated. With no rotation the row values
depend on (source row, output column) only, so they are computed once per source row and
reused by every output row that reads it; every value is the same double computed the same way,
hence the same bytes (tests/test_augment.py against PIL's transform).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _cubic(v1, v2, v3, v4, d):
  """Geometry.c's BICUBIC macro, term for term."""
  p1 = v2
  p2 = -v1 + v3
  p3 = 2 * (v1 - v2) + v3 - v4
  p4 = -v1 + v2 - v3 + v4
  return p1 + d * (p2 + d * (p3 + d * p4))


@numba.njit(cache=True, nogil=True)
def _axis(a, b, n, size):
  """(inside, first tap, fraction) of the n output positions a (i + 0.5) + b along an axis."""
  inside = np.zeros(n, np.bool_)
  first = np.zeros(n, np.int64)
  frac = np.zeros(n)
  for i in range(n):
    pos = a * (i + 0.5) + b
    if pos >= 0.0 and pos < size:
      inside[i] = True
      p = pos - 0.5
      f = np.floor(p)
      frac[i] = p - f
      first[i] = np.int64(f) - 1
  return inside, first, frac


@numba.njit(cache=True, nogil=True)
def _scale_shift(image, a0, a2, a4, a5, oh, ow):
  h, w, nb = image.shape
  out = np.zeros((oh, ow, nb), np.uint8)
  inx, x0, fx = _axis(a0, a2, ow, w)
  iny, y0, fy = _axis(a4, a5, oh, h)
  needed = np.zeros(h, np.bool_)
  for y in range(oh):
    if iny[y]:
      for k in range(4):
        needed[min(max(y0[y] + k, 0), h - 1)] = True
  rows = np.empty((h, ow, nb))
  for r in range(h):
    if not needed[r]:
      continue
    for x in range(ow):
      if not inx[x]:
        continue
      c0, c1 = min(max(x0[x], 0), w - 1), min(max(x0[x] + 1, 0), w - 1)
      c2, c3 = min(max(x0[x] + 2, 0), w - 1), min(max(x0[x] + 3, 0), w - 1)
      for b in range(nb):
        rows[r, x, b] = _cubic(float(image[r, c0, b]), float(image[r, c1, b]),
                               float(image[r, c2, b]), float(image[r, c3, b]), fx[x])
  for y in range(oh):
    if not iny[y]:
      continue
    r0, r1 = min(max(y0[y], 0), h - 1), min(max(y0[y] + 1, 0), h - 1)
    r2, r3 = min(max(y0[y] + 2, 0), h - 1), min(max(y0[y] + 3, 0), h - 1)
    for x in range(ow):
      if not inx[x]:
        continue
      for b in range(nb):
        v = _cubic(rows[r0, x, b], rows[r1, x, b], rows[r2, x, b], rows[r3, x, b], fy[y])
        out[y, x, b] = 0 if v <= 0.0 else (255 if v >= 255.0 else np.uint8(v))
  return out


def bicubic_transform(image: np.ndarray, data, size_wh) -> np.ndarray:
  """`Image.fromarray(image).transform(size_wh, Image.PERSPECTIVE, data, Image.BICUBIC)` as an
  array, for the 8 perspective coefficients `data` of a scale + shift (data[1], data[3],
  data[6], data[7] zero: ValueError otherwise, where PIL's own transform is the way)."""
  a = [float(v) for v in data]
  if a[1] != 0.0 or a[3] != 0.0 or a[6] != 0.0 or a[7] != 0.0:
    raise ValueError(f"bicubic_transform: {a} is not a scale + shift per axis")
  image = np.ascontiguousarray(image, np.uint8)
  if image.ndim != 3:
    raise ValueError(f"bicubic_transform: expected an H x W x C image, got {image.shape}")
  return _scale_shift(image, a[0], a[2], a[4], a[5], int(size_wh[1]), int(size_wh[0]))
