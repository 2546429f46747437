import numpy as np
import pytest

from ufm_jax.data import io


def test_flo_roundtrip_and_layout(tmp_path):
  flow = np.stack(np.meshgrid(np.arange(5.0), -np.arange(3.0)), -1).astype(np.float32)
  path = tmp_path / "a.flo"
  io.write_flo(path, flow)
  raw = path.read_bytes()
  # Header: tag, width, height; then u,v interleaved row-major.
  assert raw[:4] == b"PIEH"
  assert np.frombuffer(raw[4:12], "<i4").tolist() == [5, 3]
  assert np.frombuffer(raw[12:20], "<f4").tolist() == [0.0, 0.0]
  assert np.frombuffer(raw[20:28], "<f4").tolist() == [1.0, 0.0]
  np.testing.assert_array_equal(io.read_flo(path), flow)


def test_flo_errors_name_the_file(tmp_path):
  bad = tmp_path / "bad.flo"
  bad.write_bytes(b"NOPE" + b"\0" * 8)
  with pytest.raises(ValueError, match="bad.flo"):
    io.read_flo(bad)
  short = tmp_path / "short.flo"
  short.write_bytes(b"PIEH" + np.array([4, 4], "<i4").tobytes() + b"\0" * 8)
  with pytest.raises(ValueError, match="short.flo.*expected"):
    io.read_flo(short)
