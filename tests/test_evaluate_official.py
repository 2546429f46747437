"""evaluate.py end to end under each protocol, on tiny trees and the small random model.

The model is whatever evaluate.py picks without --checkpoint (a randomly initialised `tiny`), so
the numbers are arbitrary: each reported figure is recomputed here from the files written by
--save_predictions and the masks each protocol defines (docs/benchmarks.md).
"""

import json

import numpy as np
import pytest

from ufm_jax.evaluators import metrics
from ufm_jax.data import get_source, io
from ufm_jax.evaluators import base
from ufm_jax.testing import bench_trees, wide_trees

OFFICIAL_BENCHES = "sintel,kitti,eth3d,dtu,tawb"


def write_official_root(root):
  """The branch's dataset_root: Sintel/, KITTI/, eth3d_processed/, dtu_processed/,
  anymap_data_pairs/, TA-WB/."""
  rng = np.random.default_rng(3)
  bench_trees.write_official_bench_root(root, wide_trees.PlaneScene(hw0=(45, 60)), [dict(
      img0=rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),
      img1=rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),
      flow_fwd=rng.normal(0, 4, (2, 48, 64)).astype(np.float32),
      non_occluded_fwd=rng.random((48, 64)) < 0.7, fov_mask_fwd=rng.random((48, 64)) < 0.9,
      occlusion_supervision_mask_fwd=np.ones((48, 64), bool)) for _ in range(3)])


def _pooled(preds, bench, src, n, mask_of):
  acc = metrics.Pooled()
  for i in range(n):
    s = src[i]
    flo, _ = base.predicted_paths(preds, bench, s, i)
    epe = metrics.endpoint_error(io.read_flo(flo), s["flow"])
    for name, m in mask_of(s).items():
      acc.add(name, epe, m)
  return acc


@pytest.mark.slow
def test_official_protocol_end_to_end(tmp_path, run_evaluate):
  root, preds, out = tmp_path / "data", tmp_path / "preds", tmp_path / "out"
  write_official_root(str(root))
  rc, printed, err = run_evaluate("--bench", OFFICIAL_BENCHES, "--data_root", str(root),
                                  "--max_pairs", "2", "--save_predictions", str(preds),
                                  "--num_panels", "0", "--out", str(out), "--no_progress")
  assert rc == 0, err[-3000:]
  res = json.loads((out / "results.json").read_text())
  assert res["protocol"] == "official" and res["skipped"] == {}
  assert res["bench_protocols"] == {b: "official" for b in OFFICIAL_BENCHES.split(",")}
  assert res["n_pairs"] == {"sintel_clean": 2, "sintel_final": 2, "kitti": 2, "eth3d": 2,
                            "dtu": 2, "tawb": 2}
  m = res["metrics"]
  assert "| eth3d |" in printed and "epe_occluded" in printed

  # The wide-baseline benches: the branch's masks (valid & covisible, valid & ~covisible).
  for bench, source, sub in (("eth3d", "eth3d_official", "eth3d_processed"),
                             ("dtu", "dtu_official", "dtu_processed"),
                             ("tawb", "tawb_official", "TA-WB")):
    src = get_source(source, str(root / sub))
    acc = _pooled(preds, bench, src, 2, lambda s: {
        "epe": s["flow_valid"] & s["covisibility"], "occ": s["flow_valid"] & ~s["covisibility"]})
    assert acc.mean("epe") == pytest.approx(m[f"{bench}/epe"], rel=1e-5), bench
    assert acc.mean("occ") == pytest.approx(m[f"{bench}/epe_occluded"], rel=1e-5), bench
    assert src[0]["image0"].shape == (420, 560, 3)

  # Sintel [covis]: not occluded, read straight from the occlusion PNGs (the branch's mask).
  src = get_source("sintel_clean", str(root / "Sintel"))
  occ = [io.read_mask(str(root / "Sintel" / "training" / "occlusions" / "alley_1" /
                          f"frame_{k:04d}.png")) for k in (1, 2)]
  acc = _pooled(preds, "sintel", src, 2, lambda s: {"covis": ~occ[int(s["meta"]["frame0"]) - 1]})
  assert acc.mean("covis") == pytest.approx(m["sintel_clean/epe_covis"], rel=1e-5)

  rc, _, err = run_evaluate("--bench", "eth3d", "--data_root", str(root), "--resolution", "560")
  assert rc == 2 and "native protocol only" in err


@pytest.mark.slow
def test_native_protocol_end_to_end(tmp_path, run_evaluate):
  root, preds, out = tmp_path / "data", tmp_path / "preds", tmp_path / "out"
  bench_trees.write_sintel(str(root / "sintel"))
  pair = wide_trees.write_eth3d_prepared(str(root / "eth3d"), wide_trees.PlaneScene())
  (root / "eth3d" / "pairs_test.txt").write_text(" ".join(pair) + "\n")
  write_official_root(str(root / "official"))   # present, but not what the native protocol reads
  rc, _, err = run_evaluate("--bench", "sintel,eth3d", "--protocol", "native", "--data_root",
                            str(root), "--resolution", "native", "--save_predictions", str(preds),
                            "--num_panels", "0", "--out", str(out), "--no_progress")
  assert rc == 0, err[-3000:]
  res = json.loads((out / "results.json").read_text())
  assert res["protocol"] == "native" and res["resolution"] == "native"
  assert res["bench_protocols"] == {"sintel": "native", "eth3d": "native"}
  m = res["metrics"]
  src = get_source("eth3d", str(root / "eth3d"))
  acc = _pooled(preds, "eth3d", src, 1, lambda s: {
      "epe": s["flow_valid"] & s["covisibility"] & s["covis_valid"]})
  assert acc.mean("epe") == pytest.approx(m["eth3d/epe"], rel=1e-5)
  assert src[0]["image0"].shape == (36, 48, 3)            # the dataset's resolution, no crop
  src = get_source("sintel_clean", str(root / "sintel"))   # covisible = not occluded, in image 1
  acc = _pooled(preds, "sintel", src, 2, lambda s: {"covis": s["covisibility"]})
  assert acc.mean("covis") == pytest.approx(m["sintel_clean/epe_covis"], rel=1e-5)

  rc, _, err = run_evaluate("--bench", "eth3d", "--protocol", "native", "--data_root",
                            str(root / "official"))
  assert rc == 2 and "data/eth3d/" in err
