"""Fast decoding of what training reads most: zlib streams, the PNGs OpenCV writes, HDF5 rows.

Inflating dominates PNG and deflated .flo5 decoding, and the zlib that OpenCV and CPython link here
inflates at ~80-100 MB/s. ISA-L (the `isal` package) inflates the same streams ~3x faster, so:
  - `inflate` is zlib.decompress through ISA-L when it is installed (stdlib zlib otherwise);
  - `imread_unchanged` decodes the common PNG layouts itself (8/16-bit gray, RGB, RGBA,
    non-interlaced, rows filtered with None/Sub/Up: OpenCV writes every row with Sub) with
    `inflate` and a vectorised un-filter, and hands every other file (JPEG, PPM, palette, Paeth
    or Average rows, interlaced, transparency chunks, anything malformed) to cv2.imread. The
    result equals cv2.imread(path, cv2.IMREAD_UNCHANGED) bit for bit (tests/test_decode.py).
  - `h5_row` reads a row of a gzip-chunked HDF5 dataset (the official processed shards) a chunk
    at a time through `inflate`.
Measured gain of the PNG path, CPU ms per sample at 560x420 (single thread, min of 10; this path
vs cv2.imread for every PNG), `python benchmarks/source_load.py --repeats 10` vs the same with `--opencv_png`
(2026-12-04): tartanair_v2 18.0 vs 25.8, kubric4d 18.0 vs 22.1, flyingthings 13.0 vs 15.5, monkaa
13.1 vs 15.4, sintel_clean 8.0 vs 11.3, spring 17.4 vs 22.8, hd1k 9.0 vs 15.0, kitti2015 12.5 vs
15.2 (JPEG-image readers such as blendedmvs: no change).
"""

from __future__ import annotations

import itertools
import os
import struct
import zlib

import cv2
import numpy as np

try:
  from isal import isal_zlib as _fast_zlib
except ImportError:  # pragma: no cover - isal is a dependency; stay correct without it
  _fast_zlib = None

INFLATE_ERRORS = (zlib.error,) + ((_fast_zlib.error,) if _fast_zlib is not None else ())

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 6: 4}  # colour type -> channels (gray, RGB, RGBA)
# Chunks that never change decoded pixel values (OpenCV applies no gamma/colour management).
_HARMLESS = {b"IHDR", b"IDAT", b"IEND", b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs", b"gAMA",
             b"cHRM", b"sRGB", b"iCCP", b"sBIT"}


def inflate(data, bufsize: int = 16384) -> bytes:
  """zlib.decompress(data, bufsize=bufsize), through ISA-L when available."""
  if _fast_zlib is not None:
    return _fast_zlib.decompress(data, bufsize=max(int(bufsize), 1))
  return zlib.decompress(data, bufsize=max(int(bufsize), 1))


def decode_png(buf: bytes, rgb: bool = True) -> np.ndarray | None:
  """PNG bytes -> [H, W] or [H, W, C] uint8/uint16 in the file's channel order (rgb=True) or
  OpenCV's (B, G, R[, A]); None when the file is not one of the layouts handled here."""
  if buf[:8] != _PNG_SIGNATURE:
    return None
  pos, idat, header = 8, [], None
  view = memoryview(buf)
  try:
    while pos + 12 <= len(buf):
      length, kind = struct.unpack_from(">I4s", buf, pos)
      if kind not in _HARMLESS or pos + 12 + length > len(buf):
        return None
      if kind == b"IHDR":
        header = struct.unpack_from(">IIBBBBB", buf, pos + 8)
      elif kind == b"IDAT":
        idat.append(view[pos + 8:pos + 8 + length])
      elif kind == b"IEND":
        break
      pos += 12 + length
    if header is None or not idat:
      return None
    w, h, depth, ctype, _, _, interlace = header
    if ctype not in _CHANNELS or depth not in (8, 16) or interlace != 0 or w == 0 or h == 0:
      return None
    c = _CHANNELS[ctype]
    bpp = c * depth // 8
    row = w * bpp + 1
    raw = inflate(b"".join(idat) if len(idat) > 1 else idat[0], bufsize=h * row)
  except (struct.error, *INFLATE_ERRORS):
    return None
  if len(raw) != h * row:
    return None
  rows = np.frombuffer(raw, np.uint8).reshape(h, row)
  out = _unfilter(rows[:, 0], rows[:, 1:].reshape(h, w, bpp))
  if out is None:
    return None
  if depth == 16:
    out = out.view(">u2").astype(np.uint16)
  if c == 1:
    return out.reshape(h, w)
  out = out.reshape(h, w, c)
  if rgb:
    return out
  return cv2.cvtColor(out, cv2.COLOR_RGB2BGR if c == 3 else cv2.COLOR_RGBA2BGRA)


def prefix_sum_u8(f: np.ndarray) -> np.ndarray:
  """Running sum of uint8 `f` along axis 1, wrapping mod 256 like PNG's Sub and Up filters.
  Log-step doubling (out[:, i] += out[:, i - k] for k = 1, 2, 4, ...): a few whole-array uint8
  adds, 1.5-3x faster than np.cumsum, whose uint8 accumulation runs element by element."""
  a, b = f.copy(), np.empty_like(f)
  k = 1
  while k < f.shape[1]:
    b[:, :k] = a[:, :k]
    np.add(a[:, k:], a[:, :-k], out=b[:, k:])
    a, b = b, a
    k *= 2
  return a


def _unfilter(kinds: np.ndarray, f: np.ndarray) -> np.ndarray | None:
  """Reverses PNG filters None (0), Sub (1) and Up (2) on [H, W, bytes per pixel] rows;
  None when a row uses Average or Paeth (sequential along the row: left to libpng)."""
  if kinds.max(initial=0) > 2:
    return None
  sub = kinds == 1
  if sub.all():
    return prefix_sum_u8(f)
  out = f.copy()
  if sub.any():
    out[sub] = prefix_sum_u8(f[sub])
  up = kinds == 2
  if up.any():
    # A run of Up rows [a, b) adds up along the rows, starting from the decoded row a - 1.
    edges = np.flatnonzero(np.diff(np.concatenate([[0], up.view(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
      out[a:b] = prefix_sum_u8(f[None, a:b])[0]   # along the rows
      if a > 0:
        out[a:b] += out[a - 1]
  return out


def imread_unchanged(path, rgb: bool = False) -> np.ndarray | None:
  """cv2.imread(path, cv2.IMREAD_UNCHANGED) (None when unreadable), with colour channels in
  file (R, G, B[, A]) order when rgb=True; common PNGs are decoded by `decode_png`."""
  path = os.fspath(path)
  try:
    with open(path, "rb") as f:
      buf = f.read()
  except OSError:
    return None
  out = decode_png(buf, rgb=rgb)
  if out is not None:
    return out
  img = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_UNCHANGED)
  if img is None or not rgb or img.ndim != 3 or img.shape[2] not in (3, 4):
    return img
  return cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)


def h5_row(dataset, pos: int, where: str = "") -> np.ndarray:
  """dataset[pos] of an h5py Dataset, inflating its chunks through `inflate` when the only filter
  is deflate (what the official preprocessing writes: gzip 9 for FlyingThings3D / Monkaa, gzip 4
  for the TartanAir shards): HDF5's own deflate filter inflates with the linked zlib, slower than
  ISA-L (docs/host_input.md). Any other layout (contiguous, shuffle, fletcher32, unallocated chunks) goes through
  h5py. `where` names the file in errors."""
  d = dataset
  chunks = d.chunks
  if (chunks is None or d.compression != "gzip" or d.dtype.kind not in "biuf" or d.ndim < 1
      or not 0 <= pos < d.shape[0] or d.id.get_create_plist().get_nfilters() != 1):
    return d[pos]
  tail, ctail = d.shape[1:], chunks[1:]
  nbytes = int(np.prod(chunks)) * d.dtype.itemsize
  start = pos // chunks[0] * chunks[0]
  grid = [range(0, n, c) for n, c in zip(tail, ctail)]
  out = np.empty(tail, d.dtype)
  for offsets in itertools.product(*grid):
    try:
      mask, raw = d.id.read_direct_chunk((start,) + offsets)
    except (KeyError, OSError, RuntimeError, ValueError):   # e.g. a chunk never written
      return d[pos]
    if mask == 0:
      try:
        raw = inflate(raw, bufsize=nbytes)
      except INFLATE_ERRORS as e:
        raise ValueError(f"{where}{d.name}: corrupt gzip chunk at {(start,) + offsets} ({e})") \
            from None
    if len(raw) != nbytes:
      raise ValueError(f"{where}{d.name}: chunk at {(start,) + offsets} holds {len(raw)} bytes, "
                       f"expected {nbytes}")
    block = np.frombuffer(raw, d.dtype).reshape(chunks)[pos - start]
    # Edge chunks are stored full size: their padding lies past the dataset's edge.
    dst = tuple(slice(o, min(o + c, n)) for o, c, n in zip(offsets, ctail, tail))
    out[dst] = block[tuple(slice(0, s.stop - s.start) for s in dst)]
  return out if tail else out[()]
