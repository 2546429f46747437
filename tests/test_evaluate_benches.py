"""evaluate.py end to end on tiny trees in each dataset's real on-disk format (the native
protocol; the official one: tests/test_evaluate_official.py).

One `--bench all --protocol native` run with the public fixture snapshot (random weights: the numbers are arbitrary,
so the checks are structural plus an independent recomputation of the reported EPE from the
files written by --save_predictions). The fixture's fixed inference resolution (168x224) means a
single compiled forward serves every dataset.
"""

import json
import os

import numpy as np
import pytest

from ufm_jax.testing import bench_trees, wide_trees as trees
from ufm_jax import evaluators
from ufm_jax.evaluators import metrics
from ufm_jax.data import get_source, io
from ufm_jax.evaluators import base



def write_all(root):
  bench_trees.write_sintel(os.path.join(root, "sintel"))
  bench_trees.write_kitti(os.path.join(root, "kitti2015"))
  scene = trees.PlaneScene()
  trees.write_dtu(os.path.join(root, "dtu"), scene)
  pair = trees.write_eth3d_prepared(os.path.join(root, "eth3d"), scene)
  with open(os.path.join(root, "eth3d", "pairs_test.txt"), "w") as f:
    f.write(" ".join(pair) + "\n")
  trees.write_tawb(os.path.join(root, "tawb"), trees.tartanair_scene())
  trees.write_scannet1500(os.path.join(root, "scannet1500"), trees.PlaneScene(hw0=(48, 64)), (48, 64))


@pytest.fixture(scope="module")
def snapshot(reference_dir):
  return str(reference_dir / "base")


@pytest.mark.slow
def test_bench_all_on_tiny_trees(snapshot, tmp_path_factory, run_evaluate):
  root = tmp_path_factory.mktemp("data")
  write_all(str(root))
  preds, out = root / "preds", root / "out"
  rc, printed, err = run_evaluate("--bench", "all", "--protocol", "native", "--snapshot", snapshot,
                                  "--data_root", str(root), "--max_pairs", "2",
                                  "--save_predictions", str(preds), "--num_panels", "1", "--out",
                                  str(out), "--no_progress")
  assert rc == 0, err[-3000:]
  res = json.loads((out / "results.json").read_text())
  assert res["skipped"] == {} and sorted(res["benches_run"]) == sorted(evaluators.BENCHES)
  assert res["protocol"] == "native" and set(res["bench_protocols"].values()) == {"native"}
  assert res["n_pairs"]["sintel_clean"] == 2 and res["n_pairs"]["kitti"] == 2
  assert res["n_pairs"]["eth3d"] == 1 and res["n_pairs"]["scannet1500"] == 1
  m = res["metrics"]
  for key in ("sintel_clean/epe_all", "sintel_final/epe_covis", "sintel_clean/px1", "kitti/fl_all",
              "kitti/fl_fg", "eth3d/px2", "dtu/epe", "tawb/px5", "eth3d_pose/auc5",
              "scannet1500/auc15", "tawb_pose/auc30", "synthetic/epe"):
    assert key in m and np.isfinite(m[key]), key
  assert all(v > 0 for v in res["runtime_ms_per_pair"].values())
  assert "| sintel_clean |" in printed and "| eth3d_pose |" in printed
  assert set(res["versions"]) >= {"jax", "flax", "numpy", "ufm_jax"}

  # Recompute figures from the saved prediction files (native resolution, GT relative paths).
  src = get_source("sintel_clean", str(root / "sintel"))
  acc = metrics.Pooled()
  for i in range(2):
    s = src[i]
    flo, png = base.predicted_paths(preds, "sintel", s, i)
    assert flo.relative_to(preds / "sintel").as_posix() == f"clean/alley_1/frame_{i + 1:04d}.flo"
    assert png.is_file()
    acc.add("epe", metrics.endpoint_error(io.read_flo(flo), s["flow"]), s["flow_valid"])
  assert acc.mean("epe") == pytest.approx(m["sintel_clean/epe_all"], rel=1e-5)

  src = get_source("kitti2015", str(root / "kitti2015"))
  per_image = metrics.PerImage()
  for i in range(2):
    s = src[i]
    flo, _ = base.predicted_paths(preds, "kitti", s, i)
    assert flo.relative_to(preds / "kitti").as_posix() == f"flow/{i:06d}_10.flo"
    per_image.add("epe", metrics.endpoint_error(io.read_flo(flo), s["flow"]), s["flow_valid"])
  assert per_image.mean("epe") == pytest.approx(m["kitti/epe_all"], rel=1e-5)

  s = get_source("eth3d", str(root / "eth3d"))[0]
  flo, _ = base.predicted_paths(preds, "eth3d", s, 0)
  e = metrics.endpoint_error(io.read_flo(flo), s["flow"])
  covis = s["covisibility"] & s["flow_valid"] & s["covis_valid"]
  assert e[covis].mean() == pytest.approx(m["eth3d/epe"], rel=1e-5)
  assert len(list((preds / "sintel" / "panels").glob("*.png"))) == 1


@pytest.mark.slow
def test_bench_all_skips_missing_data(snapshot, tmp_path, run_evaluate):
  rc, out, err = run_evaluate("--bench", "all", "--snapshot", snapshot, "--data_root",
                              str(tmp_path), "--max_pairs", "1", "--out", str(tmp_path / "o"),
                              "--no_progress")
  assert rc == 0, err[-3000:]
  res = json.loads((tmp_path / "o" / "results.json").read_text())
  assert res["benches_run"] == ["synthetic"]
  assert "data/sintel/" in res["skipped"]["sintel"] and "data/dtu/" in res["skipped"]["dtu"]
  assert "skipped kitti:" in out
