"""pairs_folder: the project's pair-folder format, written by the test and by the synthetic CLI."""

import json
import logging
import os

import cv2
import numpy as np
import pytest

from ufm_jax import data
from ufm_jax.data import synthetic as S
from ufm_jax.data.io import write_flo


def write_png(path, arr):
  arr = np.asarray(arr)
  assert cv2.imwrite(str(path), arr[..., ::-1] if arr.ndim == 3 else arr)


def make_pair(folder, h=6, w=8, masks=True):
  os.makedirs(folder)
  rng = np.random.default_rng(0)
  im0 = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
  im1 = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
  im0[0, 0] = (255, 0, 0)  # pure red in RGB
  write_png(folder / "image0.png", im0)
  write_png(folder / "image1.png", im1)
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = 2.0  # the two right-most columns leave the image (target u >= w - 0.5)
  write_flo(folder / "flow.flo", flow)
  covis = np.ones((h, w), np.uint8) * 255
  covis[:, -2:] = 0
  if masks:
    write_png(folder / "covisibility.png", covis)
    write_png(folder / "flow_valid.png", np.full((h, w), 255, np.uint8))
    cv = np.full((h, w), 255, np.uint8)
    cv[0] = 0
    write_png(folder / "covis_valid.png", cv)
  return im0, im1, flow


def test_reads_the_format(tmp_path):
  im0, im1, flow = make_pair(tmp_path / "a")
  (tmp_path / "a" / "meta.json").write_text(json.dumps({"K0": np.eye(3).tolist(), "note": "x"}))
  make_pair(tmp_path / "b", masks=False)
  (tmp_path / "not_a_pair").mkdir()
  make_pair(tmp_path / ".c.tmp123")  # a pair folder still being written
  src = data.get_source("pairs_folder", str(tmp_path), split="train")  # flat folder: any split
  assert len(src) == 2
  s = src[0]
  np.testing.assert_array_equal(s["image0"], im0)
  assert tuple(s["image0"][0, 0]) == (255, 0, 0)
  np.testing.assert_array_equal(s["flow"], flow)
  assert s["covisibility"][:, :-2].all() and not s["covisibility"][:, -2:].any()
  assert s["flow_valid"].all() and not s["covis_valid"][0].any() and s["covis_valid"][1:].all()
  assert s["meta"]["K0"].shape == (3, 3) and s["meta"]["note"] == "x"
  assert s["meta"]["dataset"] == "pairs_folder" and s["meta"]["scene"] == "a"
  # Without masks: FoV proxy for covisibility, never supervised.
  t = src[1]
  assert t["covisibility"][:, :-2].all() and not t["covisibility"][:, -2:].any()
  assert not t["covis_valid"].any() and t["flow_valid"].all()


def test_errors_name_the_path(tmp_path):
  with pytest.raises(FileNotFoundError, match="no pair folders"):
    data.get_source("pairs_folder", str(tmp_path))
  with pytest.raises(FileNotFoundError, match="missing_root"):
    data.get_source("pairs_folder", str(tmp_path / "missing_root"))
  make_pair(tmp_path / "p")
  (tmp_path / "p" / "flow.flo").write_bytes(b"junk")
  src = data.get_source("pairs_folder", str(tmp_path))
  with pytest.raises(ValueError, match=r"p/flow\.flo"):
    src[0]
  write_flo(tmp_path / "p" / "flow.flo", np.zeros((5, 8, 2), np.float32))
  with pytest.raises(ValueError, match="flow.flo: flow shape"):
    src[0]
  write_flo(tmp_path / "p" / "flow.flo", np.zeros((6, 8, 2), np.float32))
  write_png(tmp_path / "p" / "covisibility.png", np.zeros((3, 3), np.uint8))
  with pytest.raises(ValueError, match="covisibility.png: mask shape"):
    src[0]
  with pytest.raises(ValueError, match="reverse"):
    src.backward(0)


def test_synthetic_cli_round_trip(tmp_path):
  out = tmp_path / "syn"
  assert S.main(["--out", str(out), "--pairs", "2", "--seed", "5", "--size", "28x42"]) == 0
  assert sorted(os.listdir(out)) == ["000000", "000001"]  # no temp folders left behind
  src = data.get_source("pairs_folder", str(out))
  gen = data.get_source("synthetic", None, split="train", seed=5, num_pairs=2, size=(28, 42))
  for i in range(2):
    disk, ref = src[i], gen[i]
    for k in ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid"):
      np.testing.assert_array_equal(disk[k], ref[k], err_msg=k)
    np.testing.assert_allclose(disk["meta"]["cam2world1"], ref["meta"]["cam2world1"])
    np.testing.assert_array_equal(disk["meta"]["depth0"], ref["meta"]["depth0"])
    back, ref_back = src.backward(i), gen.backward(i)
    np.testing.assert_array_equal(back["image0"], ref_back["image0"])
    np.testing.assert_array_equal(back["flow"], ref_back["flow"])
    np.testing.assert_array_equal(back["covis_valid"], ref_back["covis_valid"])
    np.testing.assert_allclose(back["meta"]["K0"], ref_back["meta"]["K0"])


def test_both_equals_forward_and_backward_and_decodes_each_file_once(tmp_path, monkeypatch):
  out = tmp_path / "syn"
  assert S.main(["--out", str(out), "--pairs", "1", "--seed", "2", "--size", "28x42"]) == 0
  src = data.get_source("pairs_folder", str(out))
  fwd, bwd = src.both(0)
  for got, want in ((fwd, src[0]), (bwd, src.backward(0))):
    for k in ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid"):
      np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert sorted(got["meta"]) == sorted(want["meta"])
    for k, v in want["meta"].items():
      np.testing.assert_array_equal(got["meta"][k], v, err_msg=k)
  # Symmetrized training calls `both`: each PNG and the depth archive are decoded once per pair.
  from ufm_jax.data import decode
  reads = []
  real_imread, real_load = decode.imread_unchanged, np.load
  monkeypatch.setattr(decode, "imread_unchanged", lambda p, **kw: reads.append(os.path.basename(
      p)) or real_imread(p, **kw))
  monkeypatch.setattr(np, "load", lambda p, *a, **kw: reads.append(os.path.basename(p)) or
                      real_load(p, *a, **kw))
  src.both(0)
  assert sorted(reads) == sorted(["image0.png", "image1.png", "depth.npz"] +
                                 ["covisibility.png", "flow_valid.png", "covis_valid.png"] * 2)


def test_no_flow_where_flow_valid_says_valid_is_a_corrupt_sample(tmp_path):
  make_pair(tmp_path / "a")
  make_pair(tmp_path / "b", masks=False)
  src = data.get_source("pairs_folder", str(tmp_path))
  for marker in (np.nan, np.inf, 1e10):
    flow = np.full((6, 8, 2), 2.0, np.float32)
    flow[1, 2] = marker
    for pair in ("a", "b"):
      write_flo(tmp_path / pair / "flow.flo", flow)
    with pytest.raises(ValueError, match=r"a/flow\.flo: no flow .* at 1 pixels that "
                                         r"flow_valid\.png marks valid"):
      src[0]
    t = src[1]  # without flow_valid.png the marker just means "no flow here"
    assert not t["flow_valid"][1, 2] and t["flow_valid"].sum() == 47
    assert np.isfinite(t["flow"]).all() and not t["covisibility"][1, 2]


def test_pipeline_skips_and_counts_an_all_nan_flow_file(tmp_path, caplog):
  from ufm_jax.data import pipeline
  out = tmp_path / "syn"
  assert S.main(["--out", str(out), "--pairs", "4", "--seed", "1", "--size", "28x28",
                 "--pair-type", "shift", "--no-reverse"]) == 0
  bad = out / "000002" / "flow.flo"
  write_flo(bad, np.full((28, 28, 2), np.nan, np.float32))
  cfg = {"datasets": {"pairs_folder": {"quota": 4, "root": str(out)}}, "batch_size": 4,
         "symmetrize": False, "longest_side": 28, "aspect_ratios": (1.0,), "read_threads": 1,
         "augment": {"enabled": False},
         "max_skip_fraction": 0.5, "skip_check_min_samples": 1}
  it = iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1))
  with caplog.at_level(logging.WARNING, logger="ufm_jax.data.pipeline"):
    next(it)
  assert it.skipped >= 1 and it.attempted == 4 + it.skipped
  assert f"{bad}: no flow" in caplog.text
