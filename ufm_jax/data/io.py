"""File formats: decoders (and writers for what the project writes itself).

Each reader's docstring gives the byte layout it decodes; which dataset stores what:
docs/datasets.md. Every reader raises `ValueError` naming the path and what was expected when a
file is malformed, and `FileNotFoundError` naming the path when it is missing. Writers are atomic
(temp file + rename): a crash never leaves half a file.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pathlib
import re
import shutil
import tempfile

import cv2
import numpy as np

from ufm_jax.data import decode
from ufm_jax.geometry import camera

FLO_MAGIC = 202021.25  # Middlebury .flo tag ("PIEH" as little-endian float32)
KITTI_FLOW_SCALE = 64.0  # KITTI / HD1K PNG: flow = (value - 2**15) / 64
KITTI_FLOW_OFFSET = 2.0**15


def _require_file(path) -> None:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: file not found")


@contextlib.contextmanager
def atomic_file(path, suffix: str = ""):
  """Yields a temp path next to `path`; renames it over `path` only if the block succeeds (the
  one atomic writer of the package: a crash never leaves half a file). `suffix` ends the temp
  name, for writers that pick the format from it (cv2.imwrite) or append one (np.savez)."""
  path = os.fspath(path)
  tmp = f"{path}.tmp{os.getpid()}{suffix}"
  try:
    yield tmp
    os.replace(tmp, path)
  finally:
    if os.path.exists(tmp):
      os.remove(tmp)


@contextlib.contextmanager
def staging_dir(path):
  """Yields a new temp folder beside `path` (same file system, so renames out of it are
  atomic), removed with whatever is left in it when the block ends."""
  path = pathlib.Path(path).absolute()
  path.parent.mkdir(parents=True, exist_ok=True)
  tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
  try:
    yield tmp
  finally:
    shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(path):
  """Yields a temp folder that becomes the new folder `path` when the block succeeds (never
  overwrites: FileExistsError when `path` exists); on any error nothing is left behind."""
  path = pathlib.Path(path).absolute()
  if path.exists():
    raise FileExistsError(f"{path} already exists; refusing to overwrite it")
  with staging_dir(path) as tmp:
    yield tmp
    os.replace(tmp, path)


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
  """`np.save` of `array` to exactly `path`, atomically."""
  with atomic_file(path) as tmp:
    with open(tmp, "wb") as f:
      np.save(f, np.asarray(array))


# ------------------------------------------------------------------------------------------------
# Middlebury .flo (Sintel, FlyingChairs)


FLO_UNKNOWN = 1e9  # Middlebury marks unknown flow with |u| or |v| > 1e9 (writers use 1e10)


def require_finite(values, path, valid=None, what: str = "flow") -> None:
  """Raises ValueError naming `path` when `values` ([H, W] or [H, W, C]) is NaN or infinite at a
  pixel of `valid` (default: every pixel).

  For formats whose "no ground truth" marker is something else (a mask file, 1e9 in .flo, 0
  depth), a non-finite value where the labels count is a damaged or mis-exported file: the
  training pipeline skips and counts such a sample instead of silently training on less.
  """
  bad = ~camera.finite_pixels(np.asarray(values))
  if valid is not None:
    bad &= np.asarray(valid, bool)
  n = int(bad.sum())
  if n:
    where = "" if valid is None else " marked valid"
    raise ValueError(f"{path}: non-finite {what} (NaN/Inf) at {n} of {bad.size} pixels{where}")


def read_flo(path: str | os.PathLike) -> np.ndarray:
  """Middlebury .flo -> [H, W, 2] float32 (u, v). Unknown-flow markers (>1e9) are kept as is."""
  _require_file(path)
  with open(path, "rb") as f:
    header = f.read(12)
    if len(header) < 12:
      raise ValueError(f"{path}: truncated .flo header (expected 12 bytes, got {len(header)})")
    magic = np.frombuffer(header[:4], "<f4")[0]
    if magic != FLO_MAGIC:
      raise ValueError(f"{path}: not a Middlebury .flo file (tag {magic!r}, expected {FLO_MAGIC})")
    w, h = (int(x) for x in np.frombuffer(header[4:], "<i4"))
    if not (0 < w < 100000 and 0 < h < 100000):
      raise ValueError(f"{path}: implausible .flo size width={w} height={h} (expected 1..99999)")
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
  with atomic_file(path) as tmp:
    with open(tmp, "wb") as f:
      f.write(np.array([FLO_MAGIC], "<f4").tobytes())
      f.write(np.array([w, h], "<i4").tobytes())
      f.write(flow.astype("<f4").tobytes())


# ------------------------------------------------------------------------------------------------
# KITTI / HD1K 16-bit PNG flow


def read_kitti_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
  """KITTI 16-bit PNG -> (flow [H, W, 2] float32, valid [H, W] bool).

  File channels (RGB order) are u, v, valid; `flow = (value - 2**15) / 64`. OpenCV returns BGR, so
  the channel axis is reversed here. Invalid pixels get flow 0.
  """
  _require_file(path)
  raw = decode.imread_unchanged(path)
  if raw is None:
    raise ValueError(f"{path}: not a readable PNG (expected a KITTI 3-channel uint16 flow PNG)")
  if raw.dtype != np.uint16 or raw.ndim != 3 or raw.shape[2] != 3:
    raise ValueError(f"{path}: expected a 3-channel uint16 KITTI flow PNG, got dtype {raw.dtype} "
                     f"shape {raw.shape}")
  valid = raw[..., 0] > 0  # BGR order: index 0 = valid, 1 = v, 2 = u
  flow = np.empty(raw.shape[:2] + (2,), np.float32)
  for c in range(2):  # plane by plane: ~2x faster than broadcasting over the trailing axis
    plane = flow[..., c]
    np.subtract(raw[..., 2 - c], np.float32(KITTI_FLOW_OFFSET), out=plane, dtype=np.float32)
    plane *= np.float32(1.0 / KITTI_FLOW_SCALE)
    plane *= valid
  return flow, valid


def write_kitti_flow(path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None):
  """[H, W, 2] flow (+ optional valid mask) -> KITTI 16-bit PNG (rounded to 1/64 px, clipped).

  Non-finite flow is written as invalid. Used for KITTI submissions (evaluate.py --save_predictions).
  """
  flow = np.asarray(flow, np.float64)
  if flow.ndim != 3 or flow.shape[2] != 2:
    raise ValueError(f"write_kitti_flow({path}): flow must be [H, W, 2], got shape {flow.shape}")
  ok = np.isfinite(flow).all(-1)
  if valid is not None:
    valid = np.asarray(valid, bool)
    if valid.shape != flow.shape[:2]:
      raise ValueError(f"write_kitti_flow({path}): valid shape {valid.shape} != {flow.shape[:2]}")
    ok &= valid
  enc = np.clip(np.round(np.nan_to_num(flow) * KITTI_FLOW_SCALE + KITTI_FLOW_OFFSET), 0, 65535)
  rgb = np.concatenate([enc, ok[..., None].astype(np.float64)], -1).astype(np.uint16)
  with atomic_file(path, ".png") as tmp:
    if not cv2.imwrite(tmp, rgb[..., ::-1]):
      raise OSError(f"{path}: cv2.imwrite failed")


# ------------------------------------------------------------------------------------------------
# PFM (FlyingThings3D, Monkaa)


def read_pfm(path: str | os.PathLike) -> np.ndarray:
  """PFM -> [H, W] (Pf) or [H, W, 3] (PF) float32, top row first.

  Header: `PF`/`Pf`, `W H`, scale (negative = little-endian); rows are stored bottom-to-top.
  """
  _require_file(path)
  with open(path, "rb") as f:
    data = f.read()
  # Three whitespace-terminated header tokens after the type line; parse them from the raw bytes.
  m = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)(?:\r\n|\s)", data)
  if m is None:
    raise ValueError(f"{path}: not a PFM file (expected header 'PF'|'Pf', 'W H', scale)")
  channels = 3 if m.group(1) == b"PF" else 1
  w, h = int(m.group(2)), int(m.group(3))
  try:
    scale = float(m.group(4))
  except ValueError:
    raise ValueError(f"{path}: PFM scale {m.group(4)!r} is not a number") from None
  if scale == 0:
    raise ValueError(f"{path}: PFM scale is 0 (expected a signed non-zero number)")
  dtype = "<f4" if scale < 0 else ">f4"
  body = data[m.end():]
  n = w * h * channels
  if len(body) != 4 * n:
    raise ValueError(f"{path}: PFM payload has {len(body)} bytes, expected {w}*{h}*{channels}*4 "
                     f"= {4 * n}")
  arr = np.frombuffer(body, dtype).reshape((h, w, channels) if channels == 3 else (h, w))
  return arr[::-1].astype(np.float32, order="C")


def write_pfm(path: str | os.PathLike, array: np.ndarray, little_endian: bool = True) -> None:
  """[H, W] or [H, W, 3] float -> PFM (scale -1 little-endian or +1 big-endian), atomically."""
  array = np.asarray(array, np.float32)
  if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)):
    raise ValueError(f"write_pfm({path}): expected [H, W] or [H, W, 3], got {array.shape}")
  h, w = array.shape[:2]
  kind = b"PF" if array.ndim == 3 else b"Pf"
  header = kind + b"\n" + f"{w} {h}\n".encode() + (b"-1\n" if little_endian else b"1\n")
  body = array[::-1].astype("<f4" if little_endian else ">f4").tobytes()
  with atomic_file(path) as tmp:
    with open(tmp, "wb") as f:
      f.write(header + body)


# ------------------------------------------------------------------------------------------------
# Spring .flo5 / .dsp5 (HDF5)


def _read_h5(path, key: str, ndim: int, what: str) -> np.ndarray:
  import h5py  # optional dependency, only needed for Spring
  _require_file(path)
  try:
    with h5py.File(path, "r") as f:
      if key not in f:
        raise ValueError(f"{path}: HDF5 file has no dataset {key!r} (keys {list(f.keys())}); "
                         f"expected a Spring {what}")
      arr = np.asarray(f[key][()], np.float32)
  except OSError as e:
    raise ValueError(f"{path}: not a readable HDF5 file (expected a Spring {what}): {e}") from None
  if arr.ndim != ndim or (ndim == 3 and arr.shape[2] != 2):
    raise ValueError(f"{path}: dataset {key!r} has shape {arr.shape}, expected "
                     f"{'(H, W, 2)' if ndim == 3 else '(H, W)'}")
  return arr


def read_flo5(path: str | os.PathLike) -> np.ndarray:
  """Spring `.flo5` -> [H, W, 2] float32, NaN where there is no GT.

  Spring GT is stored at twice the image resolution (3840x2160 for 1920x1080 frames) while the
  values are in image-resolution pixels; `[::2, ::2]` gives the GT for the frames (official
  spring_utils do the same).
  """
  return _read_h5(path, "flow", 3, ".flo5 flow file (dataset 'flow', shape (H, W, 2))")


def read_flo5_strided(path: str | os.PathLike, step: int) -> tuple[np.ndarray, tuple[int, int]]:
  """(read_flo5(path)[::step, ::step] as a new contiguous array, the file's (H, W)).

  Spring readers keep every other GT pixel. For gzip-chunked float32 files (what Spring and
  write_flo5 produce) the chunks are inflated here (decode.inflate) and only the kept rows/columns are
  copied: about half the time of HDF5's own read (whose deflate filter grows its buffer from the
  compressed size) plus the strided copy. Other layouts go through h5py.
  """
  import h5py
  _require_file(path)
  what = ".flo5 flow file (dataset 'flow', shape (H, W, 2))"
  try:
    with h5py.File(path, "r") as f:
      d = f.get("flow")
      if isinstance(d, h5py.Dataset) and d.ndim == 3 and d.shape[2] == 2 and \
          d.dtype == np.dtype("<f4") and d.chunks is not None and d.compression == "gzip" and \
          not d.shuffle and not d.fletcher32 and d.scaleoffset is None and \
          d.id.get_create_plist().get_nfilters() == 1 and hasattr(d.id, "chunk_iter"):
        chunks = []
        d.id.chunk_iter(chunks.append)
        full = d.shape
        if len(chunks) == int(np.prod([-(-n // c) for n, c in zip(full, d.chunks)])) and \
            all(c.filter_mask == 0 for c in chunks):
          return _inflate_strided(path, chunks, full, d.chunks, step), full[:2]
  except OSError as e:
    raise ValueError(f"{path}: not a readable HDF5 file (expected a Spring {what}): {e}") from None
  full = read_flo5(path)
  return np.ascontiguousarray(full[::step, ::step]), full.shape[:2]


def _inflate_strided(path, chunks, shape, chunk_shape, step):
  """Rows and columns 0, step, 2 step, ... of a gzip-chunked float32 [H, W, C] HDF5 dataset whose
  chunk list (offset, byte position, size) came from HDF5 (edge chunks are stored full size)."""
  with open(path, "rb") as f:
    buf = f.read()
  h, w, nc = shape
  ch, cw, cc = chunk_shape
  out = np.empty((-(-h // step), -(-w // step), nc), np.float32)
  nbytes = ch * cw * cc * 4
  for c in chunks:
    r0, c0, k0 = c.chunk_offset
    try:
      raw = decode.inflate(buf[c.byte_offset:c.byte_offset + c.size], bufsize=nbytes)
    except decode.INFLATE_ERRORS as e:
      raise ValueError(f"{path}: corrupt gzip chunk at {c.chunk_offset} ({e})") from None
    if len(raw) != nbytes:
      raise ValueError(f"{path}: chunk at {c.chunk_offset} inflates to {len(raw)} bytes, "
                       f"expected {nbytes}")
    rs, cs = -r0 % step, -c0 % step  # first kept row / column inside the chunk
    rr, cr = (r0 + rs) // step, (c0 + cs) // step
    block = np.frombuffer(raw, "<f4").reshape(ch, cw, cc)[rs::step, cs::step]
    # Rows/columns past the dataset's edge (chunk padding) land past the output's edge.
    hh, ww, kk = min(len(block), out.shape[0] - rr), min(block.shape[1], out.shape[1] - cr), \
        min(cc, nc - k0)
    if hh > 0 and ww > 0:
      out[rr:rr + hh, cr:cr + ww, k0:k0 + kk] = block[:hh, :ww, :kk]
  return out


def read_dsp5(path: str | os.PathLike) -> np.ndarray:
  """Spring `.dsp5` -> [H, W] float32 disparity (2x resolution like .flo5), NaN = no GT."""
  return _read_h5(path, "disparity", 2, ".dsp5 disparity file (dataset 'disparity', shape (H, W))")


def _write_h5(path, key: str, arr: np.ndarray) -> None:
  import h5py
  with atomic_file(path) as tmp:
    with h5py.File(tmp, "w") as f:
      f.create_dataset(key, data=arr, compression="gzip", compression_opts=5)


def write_flo5(path: str | os.PathLike, flow: np.ndarray) -> None:
  """[H, W, 2] flow -> Spring `.flo5` (dataset 'flow', gzip 5, as the Spring writer), atomically."""
  flow = np.asarray(flow, np.float32)
  if flow.ndim != 3 or flow.shape[2] != 2:
    raise ValueError(f"write_flo5({path}): flow must be [H, W, 2], got shape {flow.shape}")
  _write_h5(path, "flow", flow)


def write_dsp5(path: str | os.PathLike, disparity: np.ndarray) -> None:
  """[H, W] disparity -> Spring `.dsp5` (dataset 'disparity'), atomically."""
  disparity = np.asarray(disparity, np.float32)
  if disparity.ndim != 2:
    raise ValueError(f"write_dsp5({path}): disparity must be [H, W], got shape {disparity.shape}")
  _write_h5(path, "disparity", disparity)


# ------------------------------------------------------------------------------------------------
# LMB .float3 (StaticThings3D as distributed by robustmvd)


def read_float3(path: str | os.PathLike) -> np.ndarray:
  """LMB `.float3` -> float32 array.

  Layout: `float\\n`, number of dims N, N dim sizes (fastest-varying first, one per line), then raw
  little-endian float32. The dims are reversed into numpy order (W, H -> (H, W)).
  """
  _require_file(path)
  with open(path, "rb") as f:
    data = f.read()
  m = re.match(rb"float\n(\d+)\n", data)
  if m is None:
    raise ValueError(f"{path}: not an LMB .float3 file (expected 'float' then the number of dims)")
  ndim = int(m.group(1))
  if not 1 <= ndim <= 8:
    raise ValueError(f"{path}: .float3 declares {ndim} dims (expected 1..8)")
  pos, dims = m.end(), []
  for _ in range(ndim):
    end = data.find(b"\n", pos)
    token = data[pos:end] if end >= 0 else b""
    if not token.strip().isdigit():
      raise ValueError(f"{path}: .float3 dim line {len(dims) + 1} is {token[:20]!r}, expected an "
                       "integer")
    dims.append(int(token))
    pos = end + 1
  shape = tuple(reversed(dims))
  n = int(np.prod(shape))
  if len(data) - pos != 4 * n:
    raise ValueError(f"{path}: .float3 payload has {len(data) - pos} bytes, expected {shape} "
                     f"float32 = {4 * n}")
  return np.frombuffer(data[pos:], "<f4").reshape(shape).astype(np.float32)


def write_float3(path: str | os.PathLike, array: np.ndarray) -> None:
  """float array -> LMB `.float3`, atomically."""
  array = np.asarray(array, np.float32)
  header = b"float\n" + f"{array.ndim}\n".encode()
  header += b"".join(f"{d}\n".encode() for d in reversed(array.shape))
  with atomic_file(path) as tmp:
    with open(tmp, "wb") as f:
      f.write(header + array.astype("<f4").tobytes())


# ------------------------------------------------------------------------------------------------
# Images, masks and 16-bit PNG depth


_IMREAD_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)  # OpenCV >= 4.11 decodes straight to RGB


# The image files read_image reads (OpenCV's codecs in opencv-python-headless), by suffix: the list
# that --frames folders are filtered by and that every refusal names.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp")
IMAGE_FORMATS = "PNG, JPEG, WebP, BMP, TIFF, PPM/PGM"


def read_image(path: str | os.PathLike, bgr: bool = False) -> np.ndarray:
  """An image file (IMAGE_FORMATS) -> [H, W, 3] uint8 RGB: the one image reader of the project
  (datasets, benchmarks, the CLI, the demo).

  Gray images are repeated to 3 channels, alpha is dropped, 16-bit images are scaled to 8 bits.
  Common PNGs go through `decode.decode_png` (~2x OpenCV's decoder); everything else through
  OpenCV's IMREAD_COLOR, which turns JPEGs by their EXIF orientation, as a photo viewer shows
  them. bgr=True keeps OpenCV's channel order (B, G, R) (for label maps read channel by channel).
  """
  _require_file(path)
  with open(path, "rb") as f:
    buf = f.read()
  img = decode.decode_png(buf, rgb=not bgr)
  if img is None:
    flag = cv2.IMREAD_COLOR if (bgr or _IMREAD_RGB is None) else _IMREAD_RGB
    img = cv2.imdecode(np.frombuffer(buf, np.uint8), flag)
    if img is None:
      raise ValueError(f"{path}: not a readable image (expected {IMAGE_FORMATS})")
    if not bgr and _IMREAD_RGB is None:
      img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)  # a plain channel swap, ~20x [..., ::-1]
    return img
  if img.dtype == np.uint16:
    img = (img >> 8).astype(np.uint8)
  elif img.dtype != np.uint8:
    raise ValueError(f"{path}: expected an 8- or 16-bit image, got dtype {img.dtype}")
  if img.ndim == 2:
    return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
  if img.shape[2] == 4:
    return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)  # drops alpha, keeps the order
  if img.shape[2] != 3:
    raise ValueError(f"{path}: expected 1, 3 or 4 channels, got {img.shape[2]}")
  return img


def encode_png(image: np.ndarray) -> bytes:
  """[H, W, 3] RGB or [H, W] grey uint8 -> PNG bytes."""
  image = np.asarray(image)
  if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
    raise ValueError(f"encode_png: expected [H, W, 3] RGB or [H, W] grey uint8, got {image.dtype} "
                     f"{image.shape}")
  ok, buf = cv2.imencode(".png", image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
  if not ok:
    raise ValueError(f"OpenCV could not PNG-encode an image of shape {image.shape}")
  return buf.tobytes()


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
  """[H, W, 3] uint8 RGB or [H, W] grey -> image file (format from the extension, PNG when
  none), atomically: the one image writer of the project."""
  image = np.asarray(image)
  if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
    raise ValueError(f"write_image({path}): expected [H, W, 3] uint8 RGB or [H, W] grey, got "
                     f"{image.dtype} {image.shape}")
  ext = os.path.splitext(os.fspath(path))[1] or ".png"
  bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
  with atomic_file(path, ext) as tmp:
    if not cv2.imwrite(tmp, bgr):
      raise OSError(f"{path}: cv2.imwrite failed")


def read_mask(path: str | os.PathLike) -> np.ndarray:
  """Binary mask image (0/1 or 0/255; any channel set counts) -> [H, W] bool."""
  _require_file(path)
  img = decode.imread_unchanged(path)
  if img is None:
    raise ValueError(f"{path}: not a readable mask image (expected a PNG)")
  return img.any(-1) if img.ndim == 3 else img > 0


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
  """[H, W] bool -> 8-bit PNG with values 0 / 255, atomically."""
  mask = np.asarray(mask)
  if mask.ndim != 2:
    raise ValueError(f"write_mask({path}): expected [H, W], got {mask.shape}")
  with atomic_file(path, ".png") as tmp:
    if not cv2.imwrite(tmp, np.where(mask.astype(bool), 255, 0).astype(np.uint8)):
      raise OSError(f"{path}: cv2.imwrite failed")


def read_png_depth16(path: str | os.PathLike, scale: float) -> np.ndarray:
  """Single-channel uint16 PNG depth -> [H, W] float32 `value / scale` (0 stays 0 = invalid).

  E.g. scale=1000 for millimetre PNGs (ScanNet), 256 for KITTI disparity PNGs.
  """
  _require_file(path)
  raw = decode.imread_unchanged(path)
  if raw is None:
    raise ValueError(f"{path}: not a readable PNG (expected a single-channel uint16 depth PNG)")
  if raw.dtype != np.uint16 or raw.ndim != 2:
    raise ValueError(f"{path}: expected a single-channel uint16 depth PNG, got dtype {raw.dtype} "
                     f"shape {raw.shape}")
  return raw.astype(np.float32) / np.float32(scale)


def write_png_depth16(path: str | os.PathLike, depth: np.ndarray, scale: float) -> None:
  """[H, W] depth -> uint16 PNG `round(depth * scale)`; non-finite/negative/overflow -> 0 (invalid)."""
  depth = np.asarray(depth, np.float64)
  if depth.ndim != 2:
    raise ValueError(f"write_png_depth16({path}): expected [H, W], got {depth.shape}")
  enc = np.round(np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0) * scale)
  enc[(enc < 0) | (enc > 65535)] = 0
  with atomic_file(path, ".png") as tmp:
    if not cv2.imwrite(tmp, enc.astype(np.uint16)):
      raise OSError(f"{path}: cv2.imwrite failed")


# ------------------------------------------------------------------------------------------------
# safetensors (released model weights)


def read_safetensors(path) -> dict[str, np.ndarray]:
  """All tensors of a .safetensors file (numpy); a damaged file's error names it and, when its
  header promises more bytes than it has, the expected and actual sizes."""
  from safetensors.numpy import load_file
  path = pathlib.Path(path)
  try:
    return load_file(str(path))
  except Exception as e:  # safetensors raises its own error types
    raise ValueError(f"{path}: cannot read safetensors ({e}){_truncation_hint(path)}") from e


def _truncation_hint(path: pathlib.Path) -> str:
  """'; the file looks truncated: ...' when its header promises more bytes than it has."""
  size = path.stat().st_size
  try:
    with open(path, "rb") as f:
      n = int.from_bytes(f.read(8), "little")
      header = json.loads(f.read(n)) if 0 < n <= size - 8 else None
  except (OSError, ValueError):
    header = None
  if header is None:
    return ""
  ends = [int(v["data_offsets"][1]) for k, v in header.items()
          if k != "__metadata__" and isinstance(v, dict) and "data_offsets" in v]
  expected = 8 + n + max(ends, default=0)
  if size < expected:
    return (f"; the file looks truncated: its header describes {expected:,} bytes, the file has "
            f"{size:,} (an interrupted download?)")
  return ""



def check_dir(path: str | os.PathLike, layout: str) -> str:
  """Returns `path` if it is a directory, else raises naming it and the layout expected there."""
  path = os.fspath(path)
  if not os.path.isdir(path):
    raise FileNotFoundError(f"{path}: directory not found; expected {layout}")
  return path


def write_json_atomic(path: str | os.PathLike, obj) -> None:
  """Standard JSON (`json_safe`: undefined numbers as null) written through a temp file + rename
  (readers never see half a file); the folder is created. Other values JSON cannot hold (paths)
  are written as str."""
  path = os.fspath(path)
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  with atomic_file(path, ".json") as tmp:
    with open(tmp, "w") as f:
      json.dump(json_safe(obj), f, indent=1, sort_keys=False, default=_json_default,
                allow_nan=False)


def json_safe(obj):
  """`obj` for standard JSON: NaN and infinities (Python's or numpy's) as None, since strict
  parsers (jq, JSON.parse, serde) reject the bare NaN that Python's json writes; numpy scalars
  as Python numbers. Containers are copied, other values passed through."""
  if isinstance(obj, dict):
    return {k: json_safe(v) for k, v in obj.items()}
  if isinstance(obj, (list, tuple)):
    return [json_safe(v) for v in obj]
  if isinstance(obj, np.ndarray) and obj.ndim == 0:
    obj = obj.item()
  if isinstance(obj, (float, np.floating)):
    return float(obj) if math.isfinite(obj) else None
  if isinstance(obj, np.bool_):
    return bool(obj)
  if isinstance(obj, np.integer):
    return int(obj)
  return obj


def _json_default(x):
  try:
    return json_safe(float(x))   # e.g. a jax scalar
  except (TypeError, ValueError):
    return str(x)
