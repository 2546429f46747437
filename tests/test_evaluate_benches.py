"""evaluate.py end to end on tiny trees in each dataset's real on-disk format.

One `--bench all` run with the public fixture snapshot (random weights: the numbers are arbitrary,
so the checks are structural plus an independent recomputation of the reported EPE from the
files written by --save_predictions). The fixture's fixed inference resolution (168x224) means a
single compiled forward serves every dataset.
"""

import json
import os

import numpy as np
import pytest

from ufm_jax.testing import wide_trees as trees
from ufm_jax import evaluators, metrics
from ufm_jax.data import get_source, io
from ufm_jax.evaluators import base



def write_sintel(root, h=28, w=42, frames=3, scene="alley_1"):
  rng = np.random.default_rng(0)
  tr = os.path.join(root, "training")
  for sub in ("clean", "final", "flow", "occlusions", "invalid"):
    os.makedirs(os.path.join(tr, sub, scene))
  for k in range(1, frames + 1):
    for p in ("clean", "final"):
      io.write_image(os.path.join(tr, p, scene, f"frame_{k:04d}.png"),
                     rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    if k < frames:
      io.write_flo(os.path.join(tr, "flow", scene, f"frame_{k:04d}.flo"),
                   rng.normal(0, 3, (h, w, 2)).astype(np.float32))
      occ = np.zeros((h, w), bool)
      occ[:, :5] = True
      io.write_mask(os.path.join(tr, "occlusions", scene, f"frame_{k:04d}.png"), occ)
      io.write_mask(os.path.join(tr, "invalid", scene, f"frame_{k:04d}.png"), np.zeros((h, w), bool))


def write_kitti(root, h=30, w=50, n=2):
  rng = np.random.default_rng(1)
  tr = os.path.join(root, "training")
  for sub in ("image_2", "flow_occ", "flow_noc", "obj_map"):
    os.makedirs(os.path.join(tr, sub))
  for i in range(n):
    for f in (10, 11):
      io.write_image(os.path.join(tr, "image_2", f"{i:06d}_{f}.png"),
                     rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    flow = rng.normal(0, 20, (h, w, 2)).astype(np.float32)
    valid = rng.random((h, w)) < 0.6
    io.write_kitti_flow(os.path.join(tr, "flow_occ", f"{i:06d}_10.png"), flow, valid)
    io.write_kitti_flow(os.path.join(tr, "flow_noc", f"{i:06d}_10.png"), flow, valid & (rng.random((h, w)) < 0.8))
    obj = np.zeros((h, w), np.uint8)
    obj[10:20, 10:30] = 1
    io.write_image(os.path.join(tr, "obj_map", f"{i:06d}_10.png"), np.repeat(obj[..., None], 3, -1))


def write_all(root):
  write_sintel(os.path.join(root, "sintel"))
  write_kitti(os.path.join(root, "kitti2015"))
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
  rc, printed, err = run_evaluate("--bench", "all", "--snapshot", snapshot, "--data_root",
                                  str(root), "--max_pairs", "2", "--save_predictions", str(preds),
                                  "--num_panels", "1", "--out", str(out), "--no_progress")
  assert rc == 0, err[-3000:]
  res = json.loads((out / "results.json").read_text())
  assert res["skipped"] == {} and sorted(res["benches_run"]) == sorted(evaluators.BENCHES)
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
