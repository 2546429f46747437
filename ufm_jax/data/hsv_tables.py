"""PIL's RGB <-> HSV conversions as two lookup tables over all 2^24 colours, for the official
hue jitter (torchvision `adjust_hue` on a PIL image: `convert("HSV")`, the hue plane shifted with
uint8 wrap-around, `convert("RGB")`; torchvision/transforms/_functional_pil.py).

Each conversion is a function of one pixel's three bytes, so a table indexed by the packed pixel
gives PIL's result exactly: the tables are PIL's own output for every colour (built once with PIL,
~2 s of CPU), and a hue shift becomes two gathers and one byte add (~7x faster than PIL's two
conversions on a 420x560 image, docs/host_input.md). They are cached as one .npy file
(`UFM_CACHE_DIR`, default ~/.cache/ufm_jax; named by the Pillow version) and memory-mapped, so
the grain worker processes of a host share one copy of the 128 MiB in the page cache.

Packing: a pixel's bytes (c0, c1, c2) are the uint32 c0 | c1 << 8 | c2 << 16, i.e. the
little-endian word of (c0, c1, c2, 0).
"""

from __future__ import annotations

import os
import pathlib
import sys
import tempfile
import threading

import cv2
import numpy as np

_LOCK = threading.Lock()
_TABLES: np.ndarray | None = None


def cache_path() -> pathlib.Path:
  import PIL  # pylint: disable=g-import-not-at-top
  root = os.environ.get("UFM_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache",
                                                          "ufm_jax")
  return pathlib.Path(root) / f"pil_hsv_tables_{PIL.__version__}.npy"


def _all_colours() -> np.ndarray:
  """[4096, 4096, 3] uint8 holding every colour once, in packed order."""
  packed = np.arange(1 << 24, dtype=np.uint32)
  return packed.view(np.uint8).reshape(1 << 24, 4)[:, :3].reshape(4096, 4096, 3)


def _pack(image: np.ndarray) -> np.ndarray:
  """[..., 3] uint8 -> [...] uint32 c0 | c1 << 8 | c2 << 16."""
  rgba = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2RGBA)
  return rgba.view(np.uint32)[..., 0] & np.uint32(0xFFFFFF)


def build() -> np.ndarray:
  """[2, 2^24] uint32: PIL's RGB -> HSV and HSV -> RGB of every packed pixel."""
  from PIL import Image  # pylint: disable=g-import-not-at-top
  colours = _all_colours()
  to_hsv = np.asarray(Image.fromarray(colours, "RGB").convert("HSV"))
  to_rgb = np.asarray(Image.fromarray(colours, "HSV").convert("RGB"))
  return np.stack([_pack(to_hsv).ravel(), _pack(to_rgb).ravel()])


def _load(path: pathlib.Path):
  """The cached tables, or None when the file is absent or not what `build` writes."""
  try:
    t = np.load(path, mmap_mode="r")
  except (OSError, ValueError):
    t = None
  if t is not None and t.shape == (2, 1 << 24) and t.dtype == np.uint32:
    return t
  if path.exists():
    print(f"hsv_tables: {path} is not a table file; rebuilding it", file=sys.stderr)
  return None


def tables() -> np.ndarray:
  """The [2, 2^24] tables: the memory-mapped cache file, written first when absent (atomically,
  by one process of a host while the others wait; an unwritable cache folder keeps them in this
  process only)."""
  global _TABLES
  with _LOCK:
    if _TABLES is not None:
      return _TABLES
    path = cache_path()
    _TABLES = _load(path)
    if _TABLES is not None:
      return _TABLES
    try:
      import fcntl  # pylint: disable=g-import-not-at-top
      path.parent.mkdir(parents=True, exist_ok=True)
      with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)      # the grain workers of a host build it once
        _TABLES = _load(path)
        if _TABLES is None:
          with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as f:
            np.save(f, build())
          os.chmod(f.name, 0o644)
          os.replace(f.name, path)
          _TABLES = np.load(path, mmap_mode="r")
    except OSError:
      _TABLES = build()
    return _TABLES


def adjust_hue(image: np.ndarray, shift: int) -> np.ndarray:
  """[H, W, 3] uint8 RGB with PIL's HSV hue plane moved by `shift` (mod 256), exactly as
  `convert("HSV")`, the uint8 add and `convert("RGB")`."""
  to_hsv, to_rgb = tables()
  hsv = to_hsv.take(_pack(image))
  hsv = (hsv & np.uint32(0xFFFF00)) | ((hsv + np.uint32(shift & 0xFF)) & np.uint32(0xFF))
  rgb = to_rgb.take(hsv)
  return cv2.cvtColor(rgb.view(np.uint8).reshape(rgb.shape + (4,)), cv2.COLOR_RGBA2RGB)
