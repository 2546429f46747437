"""File formats: decoders (and writers for what the project writes itself).

Every reader raises `ValueError` naming the path and what was expected when a file is malformed.
"""

from __future__ import annotations

import os

import numpy as np

FLO_MAGIC = 202021.25  # Middlebury .flo tag ("PIEH" as little-endian float32)


def read_flo(path: str | os.PathLike) -> np.ndarray:
  """Middlebury .flo -> [H, W, 2] float32 (u, v)."""
  with open(path, "rb") as f:
    header = f.read(12)
    if len(header) < 12:
      raise ValueError(f"{path}: truncated .flo header (expected 12 bytes, got {len(header)})")
    magic = np.frombuffer(header[:4], "<f4")[0]
    if magic != FLO_MAGIC:
      raise ValueError(f"{path}: not a Middlebury .flo file (tag {magic!r}, expected {FLO_MAGIC})")
    w, h = (int(x) for x in np.frombuffer(header[4:], "<i4"))
    if not (0 < w < 1 << 16 and 0 < h < 1 << 16):
      raise ValueError(f"{path}: implausible .flo size width={w} height={h}")
    data = np.frombuffer(f.read(), "<f4")
  if data.size != h * w * 2:
    raise ValueError(f"{path}: .flo payload has {data.size} floats, expected {h}*{w}*2={h * w * 2}")
  return data.reshape(h, w, 2).astype(np.float32)


def write_flo(path: str | os.PathLike, flow: np.ndarray) -> None:
  """[H, W, 2] flow -> Middlebury .flo, written atomically (temp file + rename)."""
  flow = np.asarray(flow, np.float32)
  if flow.ndim != 3 or flow.shape[2] != 2:
    raise ValueError(f"write_flo({path}): flow must be [H, W, 2], got shape {flow.shape}")
  h, w = flow.shape[:2]
  tmp = f"{path}.tmp{os.getpid()}"
  with open(tmp, "wb") as f:
    f.write(np.array([FLO_MAGIC], "<f4").tobytes())
    f.write(np.array([w, h], "<i4").tobytes())
    f.write(flow.astype("<f4").tobytes())
  os.replace(tmp, path)
