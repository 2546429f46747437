"""ufm_jax.data.decode: the fast PNG path equals cv2.imread(IMREAD_UNCHANGED) bit for bit.

PNGs are written by OpenCV (what the datasets' tools write: every row Sub-filtered) and by a
writer in this file that chooses each row's filter, so None/Sub/Up mixes, Paeth/Average rows
(left to OpenCV), several IDAT chunks and ancillary chunks are all covered.
"""

import struct
import zlib

import cv2
import numpy as np
import pytest

from ufm_jax.data import decode, io


def _chunk(kind: bytes, data: bytes) -> bytes:
  return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _filter_row(kind, row, prev, bpp):
  """PNG filter `kind` of one row (uint8 bytes), given the previous raw row."""
  r, p = row.astype(np.int32), prev.astype(np.int32)
  left = np.concatenate([np.zeros(bpp, np.int32), r[:-bpp]])
  upleft = np.concatenate([np.zeros(bpp, np.int32), p[:-bpp]])
  if kind == 0:
    pred = np.zeros_like(r)
  elif kind == 1:
    pred = left
  elif kind == 2:
    pred = p
  elif kind == 3:
    pred = (left + p) // 2
  else:  # Paeth
    pa, pb, pc = np.abs(p - upleft), np.abs(left - upleft), np.abs(left + p - 2 * upleft)
    pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, p, upleft))
  return ((r - pred) % 256).astype(np.uint8)


def write_png(path, img, filters, idat_parts=1, extra=(), interlace=0):
  """img [H, W] or [H, W, C] uint8/uint16 in file (RGB) order; filters: one kind per row."""
  img = np.asarray(img)
  h, w = img.shape[:2]
  c = 1 if img.ndim == 2 else img.shape[2]
  depth = 16 if img.dtype == np.uint16 else 8
  rows = img.astype(">u2" if depth == 16 else np.uint8).reshape(h, -1).view(np.uint8)
  bpp = c * depth // 8
  data, prev = b"", np.zeros(rows.shape[1], np.uint8)
  for y in range(h):
    data += bytes([filters[y]]) + _filter_row(filters[y], rows[y], prev, bpp).tobytes()
    prev = rows[y]
  z = zlib.compress(data)
  cuts = np.linspace(0, len(z), idat_parts + 1).astype(int)
  ihdr = struct.pack(">IIBBBBB", w, h, depth, {1: 0, 3: 2, 4: 6}[c], 0, 0, interlace)
  with open(path, "wb") as f:
    f.write(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + b"".join(extra) +
            b"".join(_chunk(b"IDAT", z[a:b]) for a, b in zip(cuts[:-1], cuts[1:])) +
            _chunk(b"IEND", b""))


def _image(shape, dtype=np.uint8, seed=0):
  rng = np.random.default_rng(seed)
  hi = 65536 if dtype == np.uint16 else 256
  # Smooth plus noise: both the structure that filters exploit and incompressible bits.
  base = np.cumsum(rng.integers(0, 5, shape), axis=1)
  return ((base + rng.integers(0, hi, shape) // 16) % hi).astype(dtype)


def _same_as_opencv(path):
  ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
  got = decode.imread_unchanged(path)
  assert ref is not None and got is not None
  assert got.dtype == ref.dtype and got.shape == ref.shape
  np.testing.assert_array_equal(got, ref)
  return got


@pytest.mark.parametrize("shape,dtype", [((17, 23, 3), np.uint8), ((17, 23, 4), np.uint8),
                                         ((17, 23), np.uint8), ((17, 23), np.uint16),
                                         ((9, 31, 3), np.uint16), ((1, 1, 3), np.uint8)])
def test_opencv_written_pngs(tmp_path, shape, dtype):
  img = _image(shape, dtype)
  path = str(tmp_path / "a.png")
  cv2.imwrite(path, img)
  assert decode.decode_png(open(path, "rb").read()) is not None  # took the fast path
  _same_as_opencv(path)


@pytest.mark.parametrize("filters", ["none", "sub", "up", "mixed"])
def test_filter_mixes(tmp_path, filters):
  img = _image((12, 19, 3))
  kinds = {"none": [0] * 12, "sub": [1] * 12, "up": [2] * 12,
           "mixed": [2, 2, 1, 0, 2, 2, 2, 1, 1, 2, 0, 2]}[filters]
  path = tmp_path / "a.png"
  write_png(path, img, kinds, idat_parts=3)
  assert decode.decode_png(path.read_bytes()) is not None
  got = _same_as_opencv(path)
  np.testing.assert_array_equal(got[..., ::-1], img)
  np.testing.assert_array_equal(decode.imread_unchanged(path, rgb=True), img)


def test_16bit_up_rows_and_ancillary_chunks(tmp_path):
  img = _image((8, 11, 3), np.uint16, seed=3)
  path = tmp_path / "a.png"
  extra = (_chunk(b"gAMA", struct.pack(">I", 45455)), _chunk(b"tEXt", b"Software\x00test"),
           _chunk(b"sBIT", bytes([12, 12, 12])))
  write_png(path, img, [2, 1, 2, 0, 2, 2, 1, 2], extra=extra)
  assert decode.decode_png(path.read_bytes()) is not None
  np.testing.assert_array_equal(_same_as_opencv(path)[..., ::-1], img)


@pytest.mark.parametrize("kinds", [[4] * 6, [3] * 6, [1, 4, 1, 2, 3, 0]])
def test_paeth_and_average_rows_go_to_opencv(tmp_path, kinds):
  img = _image((6, 9, 4))
  path = tmp_path / "a.png"
  write_png(path, img, kinds)
  assert decode.decode_png(path.read_bytes()) is None
  np.testing.assert_array_equal(_same_as_opencv(path), cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA))


def test_other_files_go_to_opencv(tmp_path):
  img = _image((10, 14, 3))
  # JPEG and PPM: not PNGs at all.
  for ext in (".jpg", ".ppm"):
    path = str(tmp_path / f"a{ext}")
    cv2.imwrite(path, img)
    _same_as_opencv(path)
  # A transparency chunk changes what OpenCV returns: not handled here.
  path = tmp_path / "trns.png"
  write_png(path, img, [1] * 10, extra=(_chunk(b"tRNS", struct.pack(">HHH", 1, 2, 3)),))
  assert decode.decode_png(path.read_bytes()) is None
  _same_as_opencv(path)
  # Interlaced: left to OpenCV (this stream is not Adam7, so the fast path must not accept it).
  path = tmp_path / "interlaced.png"
  write_png(path, img, [1] * 10, interlace=1)
  assert decode.decode_png(path.read_bytes()) is None


def test_corrupt_and_missing_files_read_as_none(tmp_path):
  img = _image((10, 14, 3))
  path = tmp_path / "a.png"
  cv2.imwrite(str(path), img)
  buf = path.read_bytes()
  start = buf.index(b"IDAT") + 4
  broken = buf[:start + 20] + bytes(30) + buf[start + 50:]  # damaged deflate stream
  (tmp_path / "bad.png").write_bytes(broken)
  (tmp_path / "short.png").write_bytes(buf[:len(buf) // 2])
  for name in ("bad.png", "short.png", "absent.png"):
    assert decode.decode_png(broken if name == "bad.png" else buf[:len(buf) // 2]) is None
    assert decode.imread_unchanged(tmp_path / name) is None, name
  with pytest.raises(ValueError, match="bad.png"):
    io.read_image(tmp_path / "bad.png")


def test_without_isal_stdlib_zlib_gives_the_same(tmp_path, monkeypatch):
  img = _image((13, 21, 4))
  path = tmp_path / "a.png"
  write_png(path, img, [1, 2] * 6 + [0])
  fast = decode.imread_unchanged(path)
  monkeypatch.setattr(decode, "_fast_zlib", None)
  np.testing.assert_array_equal(decode.imread_unchanged(path), fast)
  data = zlib.compress(b"x" * 1000)
  assert decode.inflate(data, bufsize=10) == b"x" * 1000


def test_readers_use_it_and_keep_their_results(tmp_path):
  """io.read_image / read_png_depth16 / read_kitti_flow give what OpenCV's path gave."""
  rgb = _image((7, 9, 3))
  io.write_image(tmp_path / "rgb.png", rgb)
  np.testing.assert_array_equal(io.read_image(tmp_path / "rgb.png"), rgb)
  np.testing.assert_array_equal(io.read_image(tmp_path / "rgb.png", bgr=True), rgb[..., ::-1])
  d16 = _image((7, 9), np.uint16)
  cv2.imwrite(str(tmp_path / "d.png"), d16)
  np.testing.assert_array_equal(io.read_png_depth16(tmp_path / "d.png", 1000.0),
                                d16.astype(np.float32) / np.float32(1000))
  flow = np.random.default_rng(1).uniform(-50, 50, (7, 9, 2)).astype(np.float32)
  valid = np.random.default_rng(2).random((7, 9)) > 0.3
  io.write_kitti_flow(tmp_path / "f.png", flow, valid)
  f, v = io.read_kitti_flow(tmp_path / "f.png")
  np.testing.assert_array_equal(v, valid)
  np.testing.assert_allclose(f[valid], flow[valid], atol=1 / 64)


def test_prefix_sum_equals_wrapping_cumsum():
  rng = np.random.default_rng(0)
  for shape in [(1, 1, 3), (3, 2, 1), (5, 17, 3), (4, 64, 4), (2, 300, 6), (7, 129)]:
    f = rng.integers(0, 256, shape, dtype=np.uint8)
    np.testing.assert_array_equal(decode.prefix_sum_u8(f), np.cumsum(f, axis=1, dtype=np.uint8))


# ------------------------------------------------------------------------- HDF5 rows (h5_row)

H5_LAYOUTS = {
    # name: (array, create_dataset options)
    "row_chunks_gzip9": (np.arange(3 * 7 * 5 * 2, dtype=np.float32).reshape(3, 7, 5, 2) / 7,
                         dict(chunks=(1, 7, 5, 2), compression="gzip", compression_opts=9)),
    "edge_chunks_two_rows": (np.arange(5 * 9 * 11, dtype=np.int16).reshape(5, 9, 11),
                             dict(chunks=(2, 4, 3), compression="gzip")),
    "bool_auto_chunks": (np.arange(3 * 64 * 70).reshape(3, 64, 70) % 3 == 0,
                         dict(chunks=True, compression="gzip", compression_opts=4)),
    "big_endian": (np.linspace(-1, 1, 4 * 6 * 3).astype(">f4").reshape(4, 6, 3),
                   dict(chunks=(1, 3, 3), compression="gzip")),
    "one_dimensional": (np.arange(10, dtype=np.uint8), dict(chunks=(4,), compression="gzip")),
    "uint8_image_split_rows": (np.random.default_rng(0).integers(0, 255, (2, 33, 17, 3), np.uint8),
                        dict(chunks=(1, 16, 17, 3), compression="gzip")),
    # h5py's path: another filter, no compression, contiguous
    "shuffle": (np.arange(24, dtype=np.float32).reshape(2, 3, 4),
                dict(chunks=(1, 3, 4), compression="gzip", shuffle=True)),
    "lzf": (np.arange(24, dtype=np.float32).reshape(2, 3, 4), dict(chunks=(1, 3, 4),
                                                                    compression="lzf")),
    "contiguous": (np.arange(24, dtype=np.float32).reshape(2, 3, 4), {}),
}


@pytest.mark.parametrize("layout", sorted(H5_LAYOUTS))
def test_h5_row_equals_h5py(tmp_path, layout):
  h5py = pytest.importorskip("h5py")
  array, options = H5_LAYOUTS[layout]
  path = tmp_path / "a.h5"
  with h5py.File(path, "w") as f:
    f.create_dataset("x", data=array, **options)
  with h5py.File(path, "r") as f:
    for i in range(len(array)):
      got, want = decode.h5_row(f["x"], i), f["x"][i]
      assert type(got) is type(want) and np.asarray(got).dtype == np.asarray(want).dtype
      np.testing.assert_array_equal(got, want)
      np.testing.assert_array_equal(got, array[i])


def test_h5_row_unwritten_chunks_read_the_fill_value(tmp_path):
  h5py = pytest.importorskip("h5py")
  path = tmp_path / "a.h5"
  with h5py.File(path, "w") as f:
    d = f.create_dataset("x", shape=(3, 8, 8), dtype=np.float32, chunks=(1, 4, 8),
                         compression="gzip", fillvalue=-1.5)
    d[1, :4] = 2.0     # one of row 1's two chunks written
  with h5py.File(path, "r") as f:
    np.testing.assert_array_equal(decode.h5_row(f["x"], 0), np.full((8, 8), -1.5, np.float32))
    np.testing.assert_array_equal(decode.h5_row(f["x"], 1), f["x"][1])


def test_h5_row_corrupt_chunk_names_the_file_and_dataset(tmp_path):
  h5py = pytest.importorskip("h5py")
  path = tmp_path / "a.h5"
  array = np.random.default_rng(1).random((2, 32, 32)).astype(np.float32)
  with h5py.File(path, "w") as f:
    f.create_dataset("flow", data=array, chunks=(1, 32, 32), compression="gzip")
  with h5py.File(path, "r") as f:
    ch = []
    f["flow"].id.chunk_iter(ch.append)
  buf = bytearray(path.read_bytes())
  start = ch[1].byte_offset + ch[1].size // 2
  buf[start:start + 64] = bytes(64)      # zero a stretch inside row 1's deflate stream
  path.write_bytes(bytes(buf))
  with h5py.File(path, "r") as f:
    np.testing.assert_array_equal(decode.h5_row(f["flow"], 0), array[0])
    with pytest.raises(ValueError, match=r"a\.h5: /flow: .*chunk at \(1, 0, 0\)"):
      decode.h5_row(f["flow"], 1, f"{path}: ")
