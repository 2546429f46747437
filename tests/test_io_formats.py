"""Byte-level tests of the file decoders/encoders against the layouts their docstrings give.

Files are produced here independently of ufm_jax (hand-packed bytes, a tiny pure-python PNG
encoder/decoder), so a channel-order, endianness or row-order mistake in ufm_jax.data.io fails.
"""

import struct
import zlib

import h5py
import numpy as np
import pytest

from ufm_jax.data import io


# -- an independent minimal PNG codec (no OpenCV) --------------------------------------------------

def _png_chunk(kind, data):
  return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_encode(arr):
  """uint8/uint16 [H, W] or [H, W, C] (C=3: RGB in file order) -> PNG bytes, filter 0."""
  arr = np.asarray(arr)
  h, w = arr.shape[:2]
  c = 1 if arr.ndim == 2 else arr.shape[2]
  depth = 16 if arr.dtype == np.uint16 else 8
  color = {1: 0, 3: 2, 4: 6}[c]
  raw = arr.astype(">u2" if depth == 16 else "u1").reshape(h, -1).view(np.uint8).reshape(h, -1)
  body = b"".join(b"\0" + row.tobytes() for row in raw)
  ihdr = struct.pack(">IIBBBBB", w, h, depth, color, 0, 0, 0)
  return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(body))
          + _png_chunk(b"IEND", b""))


def png_decode(data):
  """PNG bytes -> array in file channel order (supports the 5 filter types, no interlace)."""
  assert data[:8] == b"\x89PNG\r\n\x1a\n"
  pos, idat = 8, b""
  while pos < len(data):
    n, kind = struct.unpack(">I4s", data[pos:pos + 8])
    chunk = data[pos + 8:pos + 8 + n]
    if kind == b"IHDR":
      w, h, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", chunk)
      assert interlace == 0
    elif kind == b"IDAT":
      idat += chunk
    pos += 12 + n
  c = {0: 1, 2: 3, 6: 4}[color]
  bpp = c * depth // 8
  stride = w * bpp
  raw = zlib.decompress(idat)
  out = np.zeros((h, stride), np.int64)
  prev = np.zeros(stride, np.int64)
  for y in range(h):
    f = raw[y * (stride + 1)]
    line = np.frombuffer(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)], np.uint8).astype(np.int64)
    cur = np.zeros(stride, np.int64)
    for x in range(stride):
      a = cur[x - bpp] if x >= bpp else 0
      b = prev[x]
      cc = prev[x - bpp] if x >= bpp else 0
      if f == 0:
        pred = 0
      elif f == 1:
        pred = a
      elif f == 2:
        pred = b
      elif f == 3:
        pred = (a + b) // 2
      else:
        p = a + b - cc
        pa, pb, pc = abs(p - a), abs(p - b), abs(p - cc)
        pred = a if pa <= pb and pa <= pc else (b if pb <= pc else cc)
      cur[x] = (line[x] + pred) & 0xFF
    out[y] = cur
    prev = cur
  out = out.astype(np.uint8)
  if depth == 16:
    out = out.reshape(h, -1).view(">u2").astype(np.uint16)
  return out.reshape(h, w, c) if c > 1 else out.reshape(h, w)


# -- KITTI PNG ------------------------------------------------------------------------------------

def test_kitti_png_read_known_values(tmp_path):
  # Pixel (0,0): u=1.5, v=-2.25 valid; pixel (0,1): invalid; pixel (1,2): u=-512, v=511.984375.
  rgb = np.zeros((2, 3, 3), np.uint16)
  rgb[..., 0] = rgb[..., 1] = 32768
  rgb[0, 0] = [32768 + 96, 32768 - 144, 1]
  rgb[0, 1] = [40000, 40000, 0]
  rgb[1, 2] = [0, 65535, 1]
  rgb[1, 0, 2] = 1  # valid zero flow
  path = tmp_path / "000000_10.png"
  path.write_bytes(png_encode(rgb))
  flow, valid = io.read_kitti_flow(path)
  assert flow.dtype == np.float32 and flow.shape == (2, 3, 2)
  np.testing.assert_array_equal(valid, [[True, False, False], [True, False, True]])
  np.testing.assert_array_equal(flow[0, 0], [1.5, -2.25])
  np.testing.assert_array_equal(flow[1, 2], [-512.0, 511.984375])
  np.testing.assert_array_equal(flow[1, 0], [0.0, 0.0])


def test_kitti_png_write_file_layout(tmp_path):
  flow = np.array([[[1.5, -2.25], [3.0, 0.0]]], np.float32)
  valid = np.array([[True, False]])
  path = tmp_path / "out.png"
  io.write_kitti_flow(path, flow, valid)
  rgb = png_decode(path.read_bytes())  # file channel order: u, v, valid
  assert rgb.dtype == np.uint16
  np.testing.assert_array_equal(rgb[0, 0], [32768 + 96, 32768 - 144, 1])
  np.testing.assert_array_equal(rgb[0, 1, 2], 0)
  back, v = io.read_kitti_flow(path)
  np.testing.assert_array_equal(back[0, 0], flow[0, 0])
  np.testing.assert_array_equal(v, valid)


def test_kitti_png_errors(tmp_path):
  with pytest.raises(FileNotFoundError, match="missing.png"):
    io.read_kitti_flow(tmp_path / "missing.png")
  bad = tmp_path / "gray8.png"
  bad.write_bytes(png_encode(np.zeros((2, 2), np.uint8)))
  with pytest.raises(ValueError, match="gray8.png.*3-channel uint16"):
    io.read_kitti_flow(bad)
  junk = tmp_path / "junk.png"
  junk.write_bytes(b"not a png")
  with pytest.raises(ValueError, match="junk.png"):
    io.read_kitti_flow(junk)


# -- PFM ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("endian,scale", [("<", b"-1.0"), (">", b"1.0")])
def test_pfm_read_rows_bottom_to_top_and_endianness(tmp_path, endian, scale):
  # File rows are stored bottom row first: file row 0 = image row H-1.
  img = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3) + 0.5
  body = img[::-1].astype(endian + "f4").tobytes()
  path = tmp_path / "OpticalFlowIntoFuture_0006_L.pfm"
  path.write_bytes(b"PF\n3 2\n" + scale + b"\n" + body)
  np.testing.assert_array_equal(io.read_pfm(path), img)
  gray = img[..., 0]
  path1 = tmp_path / "0006.pfm"
  path1.write_bytes(b"Pf\n3 2\n" + scale + b"\n" + gray[::-1].astype(endian + "f4").tobytes())
  np.testing.assert_array_equal(io.read_pfm(path1), gray)


def test_pfm_crlf_header(tmp_path):
  p = tmp_path / "crlf.pfm"
  p.write_bytes(b"Pf\r\n2 1\r\n-1.0\r\n" + np.array([1.0, 2.0], "<f4").tobytes())
  np.testing.assert_array_equal(io.read_pfm(p), [[1.0, 2.0]])


def test_pfm_write_layout(tmp_path):
  img = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)
  path = tmp_path / "d.pfm"
  io.write_pfm(path, img)
  raw = path.read_bytes()
  assert raw.startswith(b"Pf\n2 2\n-1\n")
  body = np.frombuffer(raw[len(b"Pf\n2 2\n-1\n"):], "<f4")
  np.testing.assert_array_equal(body, [3.0, 4.0, 1.0, 2.0])  # bottom row first
  io.write_pfm(path, img, little_endian=False)
  np.testing.assert_array_equal(io.read_pfm(path), img)


def test_pfm_errors(tmp_path):
  p = tmp_path / "bad.pfm"
  p.write_bytes(b"P6\n3 2\n255\n")
  with pytest.raises(ValueError, match="bad.pfm.*not a PFM"):
    io.read_pfm(p)
  p.write_bytes(b"Pf\n3 2\n-1\n" + b"\0" * 8)
  with pytest.raises(ValueError, match="bad.pfm.*expected 3\\*2\\*1\\*4"):
    io.read_pfm(p)


# -- Spring HDF5 ----------------------------------------------------------------------------------

def test_flo5_dsp5_read_and_write(tmp_path):
  flow = np.arange(4 * 6 * 2, dtype=np.float32).reshape(4, 6, 2)
  flow[0, 0] = np.nan
  p = tmp_path / "flow_FW_left_0001.flo5"
  with h5py.File(p, "w") as f:  # as the Spring writer: dataset "flow", gzip
    f.create_dataset("flow", data=flow, compression="gzip", compression_opts=5)
  np.testing.assert_array_equal(io.read_flo5(p), flow)
  d = tmp_path / "disp1_left_0001.dsp5"
  with h5py.File(d, "w") as f:
    f.create_dataset("disparity", data=flow[..., 0])
  np.testing.assert_array_equal(io.read_dsp5(d), flow[..., 0])
  out = tmp_path / "w.flo5"
  io.write_flo5(out, flow)
  with h5py.File(out, "r") as f:
    np.testing.assert_array_equal(f["flow"][()], flow)
  io.write_dsp5(tmp_path / "w.dsp5", flow[..., 1])
  np.testing.assert_array_equal(io.read_dsp5(tmp_path / "w.dsp5"), flow[..., 1])


def test_flo5_errors(tmp_path):
  p = tmp_path / "wrongkey.flo5"
  with h5py.File(p, "w") as f:
    f.create_dataset("disparity", data=np.zeros((2, 2), np.float32))
  with pytest.raises(ValueError, match="wrongkey.flo5.*no dataset 'flow'"):
    io.read_flo5(p)
  q = tmp_path / "junk.flo5"
  q.write_bytes(b"garbage")
  with pytest.raises(ValueError, match="junk.flo5.*HDF5"):
    io.read_flo5(q)
  r = tmp_path / "shape.dsp5"
  with h5py.File(r, "w") as f:
    f.create_dataset("disparity", data=np.zeros((2, 2, 2), np.float32))
  with pytest.raises(ValueError, match="shape.dsp5.*expected \\(H, W\\)"):
    io.read_dsp5(r)


# -- LMB float3 -----------------------------------------------------------------------------------

def test_float3_layout(tmp_path):
  arr = np.arange(6, dtype=np.float32).reshape(2, 3)  # H=2, W=3
  p = tmp_path / "0006.float3"
  p.write_bytes(b"float\n2\n3\n2\n" + arr.astype("<f4").tobytes())  # dims listed W then H
  np.testing.assert_array_equal(io.read_float3(p), arr)
  io.write_float3(tmp_path / "w.float3", arr)
  assert (tmp_path / "w.float3").read_bytes() == p.read_bytes()
  p.write_bytes(b"float\n2\n3\n2\n" + b"\0" * 5)
  with pytest.raises(ValueError, match="0006.float3.*payload"):
    io.read_float3(p)
  p.write_bytes(b"double\n")
  with pytest.raises(ValueError, match="0006.float3.*not an LMB"):
    io.read_float3(p)


# -- images, masks, depth -------------------------------------------------------------------------

def test_read_image_ppm_and_png_are_rgb(tmp_path):
  rgb = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [10, 20, 30]]], np.uint8)
  ppm = tmp_path / "00001_img1.ppm"
  ppm.write_bytes(b"P6\n2 2\n255\n" + rgb.tobytes())  # PPM stores RGB
  np.testing.assert_array_equal(io.read_image(ppm), rgb)
  png = tmp_path / "frame_0001.png"
  png.write_bytes(png_encode(rgb))
  np.testing.assert_array_equal(io.read_image(png), rgb)
  io.write_image(tmp_path / "w.png", rgb)
  np.testing.assert_array_equal(png_decode((tmp_path / "w.png").read_bytes()), rgb)
  with pytest.raises(FileNotFoundError, match="nothere.png"):
    io.read_image(tmp_path / "nothere.png")
  (tmp_path / "broken.png").write_bytes(b"\x89PNG broken")
  with pytest.raises(ValueError, match="broken.png"):
    io.read_image(tmp_path / "broken.png")


def test_mask_and_depth16(tmp_path):
  m = tmp_path / "occ.png"
  m.write_bytes(png_encode(np.array([[0, 255], [1, 0]], np.uint8)))
  np.testing.assert_array_equal(io.read_mask(m), [[False, True], [True, False]])
  io.write_mask(tmp_path / "w.png", np.array([[True, False]]))
  np.testing.assert_array_equal(png_decode((tmp_path / "w.png").read_bytes()), [[255, 0]])
  d = tmp_path / "depth.png"
  d.write_bytes(png_encode(np.array([[0, 1500], [65535, 1]], np.uint16)))
  np.testing.assert_allclose(io.read_png_depth16(d, 1000.0), [[0, 1.5], [65.535, 0.001]], rtol=1e-6)
  io.write_png_depth16(tmp_path / "wd.png", np.array([[1.5, np.nan], [-1.0, 70.0]]), 1000.0)
  np.testing.assert_array_equal(png_decode((tmp_path / "wd.png").read_bytes()), [[1500, 0], [0, 0]])
  with pytest.raises(ValueError, match="occ.png.*uint16"):
    io.read_png_depth16(m, 1000.0)


def test_writers_are_atomic(tmp_path):
  # A failing write leaves neither a partial target nor a temp file behind.
  with pytest.raises(ValueError):
    io.write_flo(tmp_path / "x.flo", np.zeros((2, 2, 3)))
  assert list(tmp_path.iterdir()) == []
  io.write_flo(tmp_path / "x.flo", np.zeros((2, 2, 2)))
  assert [p.name for p in tmp_path.iterdir()] == ["x.flo"]
