"""The fast decoding paths give exactly what the plain decoders give.

Expected values come from independent straightforward code written here: the written depth for
an EXR round trip, h5py's own full read for .flo5, a dict lookup for palette
segmentation, a per-pixel 4x4 transform for rigid objects.
"""

import numpy as np
import pytest

from ufm_jax.data import io
from ufm_jax.data.sources import exr, kubric4d
from ufm_jax.geometry import rigid


@pytest.mark.parametrize("half", [False, True])
def test_exr_zip_roundtrip_with_partial_last_chunk(tmp_path, half):
  depth = np.random.default_rng(1).uniform(0.5, 9, (37, 23)).astype(np.float32)  # 37 = 2*16 + 5
  depth[3, 4] = np.nan
  path = str(tmp_path / "d.exr")
  exr.write_exr(path, depth, half=half, compression="ZIP")
  want = depth.astype(np.float16).astype(np.float32) if half else depth
  np.testing.assert_array_equal(exr.read_exr(path), want)


@pytest.mark.parametrize("hw", [(1, 1), (5, 7), (107, 141)])
@pytest.mark.parametrize("chunks", [None, (13, 17, 1), (10, 10, 2)])
def test_flo5_strided_equals_full_read(tmp_path, hw, chunks):
  import h5py
  flow = np.random.default_rng(2).normal(size=hw + (2,)).astype(np.float32)
  flow[:hw[0] // 2, :hw[1] // 3] = np.nan
  path = str(tmp_path / "f.flo5")
  if chunks is None:
    io.write_flo5(path, flow)
  else:
    with h5py.File(path, "w") as f:
      f.create_dataset("flow", data=flow, chunks=tuple(min(c, n) for c, n in
                                                       zip(chunks, hw + (2,))),
                       compression="gzip")
  for step in (1, 2, 3):
    got, full_hw = io.read_flo5_strided(path, step)
    assert full_hw == hw and got.flags.c_contiguous
    np.testing.assert_array_equal(got, flow[::step, ::step])


def test_flo5_strided_errors_name_the_file(tmp_path):
  path = tmp_path / "bad.flo5"
  path.write_bytes(b"not hdf5")
  with pytest.raises(ValueError, match="bad.flo5"):
    io.read_flo5_strided(str(path), 2)


def test_palette_segmentation_matches_dict_lookup(tmp_path):
  rng = np.random.default_rng(3)
  palette = rng.integers(0, 256, (40, 3)).astype(np.uint8)
  palette[39] = palette[5]  # duplicate colour: the first index wins
  ids = rng.integers(0, 40, (29, 31))
  path = str(tmp_path / "seg.png")
  kubric4d.write_index_png(path, ids, palette)
  first = {}
  for i, c in enumerate(map(tuple, palette)):
    first.setdefault(c, i)
  want = np.array([[first[tuple(palette[k])] for k in row] for row in ids], np.int32)
  got = kubric4d.read_index_png(path)
  assert got.dtype == np.int32
  np.testing.assert_array_equal(got, want)


def test_rigid_objects_match_per_pixel_transform():
  rng = np.random.default_rng(4)
  h, w = 9, 12
  K = np.array([[20.0, 0, 6], [0, 21, 4], [0, 0, 1]])
  depth0 = rng.uniform(2, 4, (h, w))
  seg = rng.integers(0, 4, (h, w))
  poses0 = np.tile(np.eye(4), (4, 1, 1))
  poses1 = np.tile(np.eye(4), (4, 1, 1))
  poses1[1:, :3, 3] = rng.normal(size=(3, 3)) * 0.05  # objects 1..3 translate
  c2w0, c2w1 = np.eye(4), np.eye(4)
  c2w1[0, 3] = 0.1
  out = rigid.correspondence_from_rigid_objects(depth0, K, c2w0, seg, poses0, depth0, K, c2w1,
                                                poses1, 0.1, 0.0)
  # Reference: each pixel's point moved by its object's translation, then projected.
  v, u = np.mgrid[0:h, 0:w].astype(np.float64)
  p = np.stack([(u - 6) / 20 * depth0, (v - 4) / 21 * depth0, depth0], -1)
  p = p + poses1[seg][..., :3, 3] - c2w1[:3, 3]
  uu, vv = 20 * p[..., 0] / p[..., 2] + 6, 21 * p[..., 1] / p[..., 2] + 4
  np.testing.assert_allclose(out["flow"][..., 0], uu - u, atol=1e-4)
  np.testing.assert_allclose(out["flow"][..., 1], vv - v, atol=1e-4)
