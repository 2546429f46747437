"""EXR depth maps through the OpenEXR bindings (PyPI `openexr`).

OpenCV's wheels ship with EXR disabled, yet the DUSt3R-preprocessed datasets (Habitat,
StaticThings, MegaDepth), the WAI format (ScanNet++ v2), the ETH3D preparation and the TA-WB
extraction store depth as EXR. A hand-written scanline reader (numpy + ISA-L inflate) came first;
it was not faster, so the maintained bindings replaced it. CPU ms per read of a 560x420 ZIP depth
map, min of 50, single thread: FLOAT 2.01 (hand-written) vs 1.58 (OpenEXR), HALF 0.87 vs 0.69.
Per sample, `python benchmarks/source_load.py --datasets scannetpp,habitat,eth3d,tawb
--repeats 10` (CPU ms, hand-written -> OpenEXR; a shared 2-core host, so within its noise):
scannetpp 22.2 -> 19.0, habitat 16.3 -> 15.7, eth3d 21.6 -> 18.3, tawb 24.7 -> 23.2.
"""

from __future__ import annotations

import os

import numpy as np
import OpenEXR

_MAGIC = b"\x76\x2f\x31\x01"  # 20000630, little-endian
_COMPRESSIONS = {"NONE": OpenEXR.NO_COMPRESSION, "ZIPS": OpenEXR.ZIPS_COMPRESSION,
                 "ZIP": OpenEXR.ZIP_COMPRESSION}


def read_exr(path: str | os.PathLike, channel: str | None = None) -> np.ndarray:
  """Reads one channel of an EXR -> [H, W] float32.

  `channel` defaults to the only channel, else the first of Z, Y, R, depth present.
  """
  try:
    with open(path, "rb") as f:
      magic = f.read(4)
  except OSError as e:
    raise FileNotFoundError(f"{path}: cannot read EXR depth file ({e.strerror})") from e
  if magic != _MAGIC:
    raise ValueError(f"{path}: not an OpenEXR file (bad magic number)")
  try:
    # The File owns its channels: closing it empties the dict, so copy the pixels out inside.
    with OpenEXR.File(os.fspath(path), separate_channels=True) as f:
      channels = f.channels()
      (x0, y0), (x1, y1) = f.header()["dataWindow"]
      names = list(channels)
      if channel is None:
        channel = names[0] if len(names) == 1 else next(
            (c for c in ("Z", "Y", "R", "depth") if c in names), None)
      pixels = np.array(channels[channel].pixels, np.float32) if channel in names else None
  except RuntimeError as e:  # OpenEXR's error for damaged or truncated files
    raise ValueError(f"{path}: cannot decode EXR ({e})") from e
  if pixels is None:
    raise ValueError(f"{path}: EXR has channels {names}, expected {channel!r}")
  if pixels.shape != (y1 - y0 + 1, x1 - x0 + 1):
    raise ValueError(f"{path}: EXR channel {channel!r} is {pixels.shape[1]}x{pixels.shape[0]}, "
                     f"the data window {x1 - x0 + 1}x{y1 - y0 + 1} (subsampled channels are not "
                     "depth maps)")
  return pixels


def write_exr(path: str | os.PathLike, depth: np.ndarray, half: bool = False,
              compression: str = "ZIP", channel: str = "Y") -> None:
  """[H, W] float -> single-channel scanline EXR (HALF or FLOAT), written atomically."""
  depth = np.asarray(depth)
  if depth.ndim != 2:
    raise ValueError(f"write_exr({path}): expected a [H, W] map, got shape {depth.shape}")
  if compression not in _COMPRESSIONS:
    raise ValueError(f"write_exr({path}): compression {compression!r}; expected one of "
                     f"{sorted(_COMPRESSIONS)}")
  header = {"compression": _COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
  pixels = np.ascontiguousarray(depth, np.float16 if half else np.float32)
  path = os.fspath(path)
  tmp = f"{path}.tmp{os.getpid()}.exr"
  try:
    with OpenEXR.File(header, {channel: pixels}) as f:
      f.write(tmp)
    os.replace(tmp, path)
  finally:
    if os.path.exists(tmp):
      os.remove(tmp)
