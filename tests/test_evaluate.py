"""Evaluators and evaluate.py on tiny in-memory / on-disk data with hand-known answers.

A stand-in "model" predicts a constant flow at the inference resolution; after the official unmap
that is a known constant at the native resolution, so every metric is computable by hand.
"""


import numpy as np
import pytest

from ufm_jax import evaluators
from ufm_jax.evaluators import metrics
from ufm_jax.data.io import read_flo
from ufm_jax.evaluators import base, report
from ufm_jax import testing
from ufm_jax.testing import wide_trees



class ConstantFlow:
  """apply() -> flow (u, v) everywhere and covisibility 1; works at any size."""

  def __init__(self, u=0.0, v=0.0, inference_resolution=(28, 42)):
    self.uv = np.array([u, v], np.float32)
    self.inference_resolution = inference_resolution

  def apply(self, variables, source, target):
    import jax.numpy as jnp
    b, h, w, _ = source.shape
    flow = jnp.broadcast_to(jnp.asarray(self.uv), (b, h, w, 2)) + 0 * target.mean()
    return {"flow": flow, "covisibility": jnp.ones((b, h, w))}


def _flow_sample(h=28, w=42, gt=(2.0, 0.0), seed=0, relpath=None):
  rng = np.random.default_rng(seed)
  flow = np.broadcast_to(np.array(gt, np.float32), (h, w, 2)).copy()
  occ = np.zeros((h, w), bool)
  occ[:, : w // 2] = True
  meta = dict(dataset="toy", scene="s", frame0="0001", frame1="0002", occlusion=occ,
              gt_relpath=relpath or f"clean/s/frame_{seed:04d}.flo")
  return dict(image0=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
              image1=rng.integers(0, 256, (h, w, 3), dtype=np.uint8), flow=flow,
              covisibility=~occ, flow_valid=np.ones((h, w), bool), covis_valid=np.ones((h, w), bool),
              meta=meta)


def test_flow_bench_with_zero_prediction(tmp_path):
  # zero prediction: EPE = |gt| = 2 everywhere -> px1 = 100 %, px3 = 0 %, covis EPE 2 too.
  samples = [_flow_sample(seed=i) for i in range(3)]
  runner = base.Runner(ConstantFlow(), {})
  writer = base.PredictionWriter(tmp_path / "preds", num_panels=1)
  res, n = evaluators.run_bench("sintel", runner, sources={"sintel_clean": samples,
                                                           "sintel_final": samples[:2]},
                                writer=writer, progress=False)
  assert n == {"sintel_clean": 3, "sintel_final": 2}
  assert res["sintel_clean/epe_all"] == pytest.approx(2.0, abs=1e-6)
  assert res["sintel_clean/epe_covis"] == pytest.approx(2.0, abs=1e-6)
  assert res["sintel_clean/px1"] == 100.0 and res["sintel_clean/px3"] == 0.0
  assert res["sintel_final/px5"] == 0.0
  assert res["sintel_clean/epe_s0-10"] == pytest.approx(2.0, abs=1e-6)
  assert "sintel_clean/epe_matched" in res and "sintel_clean/epe_d0-10" in res
  assert runner.ms_per_pair() > 0
  flo = tmp_path / "preds" / "sintel" / "clean" / "s" / "frame_0001.flo"
  np.testing.assert_array_equal(read_flo(flo), 0)
  assert (tmp_path / "preds" / "sintel" / "clean" / "s" / "frame_0001_covisibility.png").is_file()
  assert len(list((tmp_path / "preds" / "sintel" / "panels").glob("*.png"))) == 1


def test_kitti_fl_and_per_image_epe():
  # constant prediction (4, 0) at inference resolution 28x42 on 56x84 images -> (8, 0) px after
  # the unmap (scale 84/42 = 2); GT (0, 0) on image A, (100, 0) on image B (outside: |gt| big).
  model = ConstantFlow(4.0, 0.0)
  a = _flow_sample(56, 84, gt=(0.0, 0.0))
  b = _flow_sample(56, 84, gt=(100.0, 0.0), seed=1)
  b["flow_valid"][:28] = False   # only half of B has GT
  runner = base.Runner(model, {})
  res, _ = evaluators.run_bench("kitti", runner, sources={"kitti": [a, b]}, progress=False)
  # per-image means: A: 8, B: 92 -> 50; Fl: A all outliers (8 > 3, rel inf), B: 92/100 > 5% -> all
  assert res["kitti/epe_all"] == pytest.approx((8 + 92) / 2, abs=1e-4)
  assert res["kitti/fl_all"] == pytest.approx(100.0)


def test_dense_bench_pooled_over_covisible():
  s1, s2 = _flow_sample(gt=(1.0, 0.0)), _flow_sample(gt=(0.0, 3.0), seed=1)
  s2["covisibility"][:] = True
  runner = base.Runner(ConstantFlow(), {})
  res, _ = evaluators.run_bench("eth3d", runner, sources={"eth3d": [s1, s2]}, progress=False)
  n1, n2 = s1["covisibility"].sum(), s2["covisibility"].sum()
  assert res["eth3d/epe"] == pytest.approx((1 * n1 + 3 * n2) / (n1 + n2))
  assert res["eth3d/px1"] == pytest.approx(100 * n2 / (n1 + n2))   # 1 is not > 1
  assert res["eth3d/px5"] == 0.0


def test_pose_bench_on_exact_flow():
  """A model replaying the exact flow of a two-view scene recovers the pose (AUC ~ 100)."""
  flow, K, R, t = wide_trees.two_view_flow(h=56, w=84)

  class Exact:
    inference_resolution = (56, 84)

    def apply(self, variables, source, target):
      import jax.numpy as jnp
      return {"flow": jnp.asarray(flow, jnp.float32)[None] + 0 * source.mean(),
              "covisibility": jnp.ones((1, 56, 84))}

  c2w1 = np.eye(4)
  c2w1[:3, :3], c2w1[:3, 3] = R.T, -R.T @ t   # x1 = R x0 + t  <=>  cam1-to-world = [R^T | -R^T t]
  sample = _flow_sample(56, 84)
  sample["meta"].update(K0=K, K1=K, cam2world0=np.eye(4), cam2world1=c2w1)
  res, _ = evaluators.run_bench("eth3d_pose", base.Runner(Exact(), {}),
                                sources={"eth3d_pose": [sample]}, progress=False)
  assert res["eth3d_pose/auc5"] > 95


def test_resolution_modes():
  assert base.resolution_for(None, (436, 1024)) is None
  assert base.resolution_for(560, (436, 1024)) == (238, 560)
  assert base.resolution_for("native", (436, 1024)) == (434, 1022)
  assert base.resolution_for(980, (375, 1242)) == (294, 980)


def test_missing_data_names_layout_and_tool(tmp_path, run_evaluate):
  rc, _, err = run_evaluate("--bench", "sintel", "--data_root", str(tmp_path), "--out",
                            str(tmp_path / "o"))
  assert rc == 2 and "data/sintel/" in err and "training/" in err
  rc, _, err = run_evaluate("--bench", "kitti", "--out", str(tmp_path / "o"))
  assert rc == 2 and "--data_root" in err and "data/kitti2015/" in err
  rc, _, err = run_evaluate("--bench", "nope")
  assert rc == 2 and "unknown bench" in err


def test_markdown_table_layout():
  table = report.markdown_table({"sintel_clean/epe_all": 1.234, "sintel_clean/epe_covis": 0.5,
                                 "sintel_clean/px1": 10.0}, ["sintel"], {"sintel": 12.3})
  header = table.splitlines()[0]
  assert header.index("epe_covis") < header.index("epe_all") < header.index("px1")
  assert "| sintel_clean | 0.50 | 1.23 | 10.00 | 12.3 |" in table


def test_saved_predictions_reproduce_reported_epe(tmp_path):
  samples = [_flow_sample(gt=(1.5, -2.0), seed=i) for i in range(2)]
  runner = base.Runner(ConstantFlow(0.5, 0.25), {})
  writer = base.PredictionWriter(tmp_path, num_panels=0)
  res, _ = evaluators.run_bench("dtu", runner, sources={"dtu": samples}, writer=writer, progress=False)
  acc = metrics.Pooled()
  for i, s in enumerate(samples):
    flo, _ = base.predicted_paths(tmp_path, "dtu", s, i)
    acc.add("epe", metrics.endpoint_error(read_flo(flo), s["flow"]), s["covisibility"])
  assert acc.mean("epe") == pytest.approx(res["dtu/epe"], rel=1e-6)


def test_an_earlier_results_json_is_kept_not_replaced(tmp_path):
  import json
  evaluate = testing.load_script("evaluate.py")
  out = tmp_path / "results.json"
  assert evaluate.keep_previous(out) is None
  out.write_text(json.dumps({"date": "2026-12-07T10:11:12+00:00", "metrics": {"a": 1}}))
  kept = evaluate.keep_previous(out)
  assert kept == tmp_path / "results_20261207T101112.json" and not out.exists()
  assert json.loads(kept.read_text())["metrics"] == {"a": 1}
  out.write_text(json.dumps({"date": "2026-12-07T10:11:12+00:00"}))
  assert evaluate.keep_previous(out) == tmp_path / "results_20261207T101112_2.json"


def test_predictions_may_not_share_the_results_folder(tmp_path, run_evaluate):
  rc, _, err = run_evaluate("--save_predictions", str(tmp_path), "--out", str(tmp_path))
  assert rc == 2 and "--save_predictions and --out name the same folder" in err


def test_undefined_metric_gets_no_column():
  table = report.markdown_table({"synthetic/epe": 1.0, "synthetic/epe_occluded": float("nan"),
                                 "synthetic/px2": 5.0}, ["synthetic"], {"synthetic": 1.0})
  assert table.splitlines()[0] == "| split | epe | px2 | ms/pair |"
