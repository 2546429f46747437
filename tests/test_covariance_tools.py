"""The flow covariance through the tools, on the ufm_reference_cov snapshot: `infer` writes it and
its uncertainty panel, `match` gives each match its covariance and precision (target pixels) and
ranks them, `export` (StableHLO and ONNX) carries it, the demo shows it, `evaluate.py` reports
its calibration and saves it with --save_predictions; a model without the head
behaves as before (its files, matches and exports have no covariance)."""

import json

import jax
import numpy as np
import pytest

import ufm_jax
from ufm_jax import testing
from ufm_jax.evaluators import metrics
from ufm_jax.runtime import outputs, viz
from ufm_jax.tools import cli, demo, export, matching
from ufm_jax.data import io
from ufm_jax.models import covariance, ufm

ROOT, CASES = testing.reference_cases("ufm_reference_cov", "UFM_COV_FIXTURES")


@pytest.fixture(scope="module")
def snap():
  if not CASES:
    testing.skip_or_fail(f"no flow covariance snapshot under {ROOT} (UFM_COV_FIXTURES, "
                         "UFM_FIXTURES)", "CI=true: the covariance tools may not be skipped")
  d = ROOT / ("flow_cov" if "flow_cov" in CASES else CASES[0])
  model, params = ufm_jax.load_official(d)
  return d, model, params, dict(np.load(d / "io.npz"))


@pytest.fixture(scope="module")
def images(snap, tmp_path_factory):
  """The hl1 pair (source 150x210, target 112x168: different sizes) as PNG files + predict."""
  _, model, params, io_ = snap
  d = tmp_path_factory.mktemp("pair")
  src, tgt = io_["hl1_src_uint8"], io_["hl1_tgt_uint8"]
  io.write_image(d / "src.png", src)
  io.write_image(d / "tgt.png", tgt)
  return d / "src.png", d / "tgt.png", src, tgt, ufm_jax.predict(model, params, src, tgt)


def test_infer_writes_the_covariance_and_the_uncertainty_panel(snap, images, tmp_path):
  d = snap[0]
  src_png, tgt_png, src, _, pred = images
  assert cli.main(["infer", str(src_png), str(tgt_png), "--checkpoint", str(d),
                   "--out", str(tmp_path)]) == 0
  cov = np.load(tmp_path / "forward_flow_covariance.npy")
  assert cov.shape == (150, 210, 3) and cov.dtype == np.float32
  np.testing.assert_allclose(cov, pred["flow_covariance"], rtol=1e-6)
  panel = io.read_image(tmp_path / "forward_panel.png")
  # five tiles (the fifth: sigma_max on the fixed scale) over a 40 px legend row, 320 px wide
  assert panel.shape == (150 + 40, 5 * 210, 3)
  np.testing.assert_array_equal(panel[:150, 4 * 210:], viz.uncertainty_to_image(cov))
  np.testing.assert_array_equal(panel[150:, -320:], viz.uncertainty_legend(320))


def test_uncertainty_image_scale():
  """sigma_max 0.25 px is the colour map's first colour, 64 px its last; the scale is log2."""
  sig = np.array([[0.25, 4.0, 64.0, 1000.0]])
  cov = np.stack([sig ** 2, (sig / 2) ** 2, np.zeros_like(sig)], -1)
  img = viz.uncertainty_to_image(cov)
  import cv2
  cmap = cv2.cvtColor(cv2.applyColorMap(np.array([[0, 128, 255]], np.uint8),
                                        cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)[0]
  np.testing.assert_array_equal(img[0, [0, 1, 2, 3]], cmap[[0, 1, 2, 2]])   # 4 px: log2 mid-way


def test_match_returns_covariance_precision_and_ranks(snap, images):
  _, model, params, _ = snap
  _, _, src, tgt, pred = images
  m = matching.match(model, params, src, tgt, num=300, min_covisibility=0.0)
  n = len(m["keypoints0"])
  assert n > 0 and m["covariance"].shape == (n, 2, 2) and m["precision"].shape == (n, 2, 2)
  assert (np.diff(m["sigma"]) >= 0).all()                      # most certain first
  eye = np.einsum("nij,njk->nik", m["covariance"].astype(np.float64),
                  m["precision"].astype(np.float64))
  ok = m["sigma"] > 0
  # inverse of each other where the matrix is well conditioned
  cond = np.linalg.cond(m["covariance"].astype(np.float64)) < 1e3
  np.testing.assert_allclose(eye[ok & cond], np.broadcast_to(np.eye(2), eye[ok & cond].shape),
                             atol=1e-3)
  # in target pixels: the official (source-ratio) covariance times (tw / sw)^2 ...
  x, y = m["keypoints0"][:, 0].astype(int), m["keypoints0"][:, 1].astype(int)
  sx, sy = 168 / 210, 112 / 150
  want = covariance.rescale(pred["flow_covariance"][y, x].astype(np.float64), sx, sy)
  np.testing.assert_allclose(m["covariance"][:, 0, 0], want[:, 0], rtol=1e-5)
  np.testing.assert_allclose(m["covariance"][:, 1, 1], want[:, 1], rtol=1e-5)
  np.testing.assert_allclose(m["sigma"], covariance.sigma_max(want), rtol=1e-5)
  cut = float(np.median(m["sigma"]))
  kept = matching.match(model, params, src, tgt, num=300, min_covisibility=0.0, max_sigma=cut)
  assert 0 < len(kept["sigma"]) < n and (kept["sigma"] <= cut).all()


def test_match_cli_writes_covariance_and_precision(snap, images, tmp_path):
  """`python -m ufm_jax match --out m.npz --max-sigma PX`: the file holds each kept match's
  covariance, precision and sigma, most certain first, none above the cut."""
  d = snap[0]
  src_png, tgt_png, *_ = images
  out = tmp_path / "m.npz"
  assert cli.main(["match", str(src_png), str(tgt_png), "--checkpoint", str(d), "--out", str(out),
                   "--num", "200", "--min-covisibility", "0", "--max-sigma", "1e9"]) == 0
  m = np.load(out)
  n = len(m["keypoints0"])
  assert n > 0 and m["covariance"].shape == (n, 2, 2) and m["precision"].shape == (n, 2, 2)
  assert m["sigma"].shape == (n,) and (np.diff(m["sigma"]) >= 0).all()
  cut = float(np.median(m["sigma"]))
  assert cli.main(["match", str(src_png), str(tgt_png), "--checkpoint", str(d), "--out", str(out),
                   "--num", "200", "--min-covisibility", "0", "--max-sigma", str(cut)]) == 0
  kept = np.load(out)
  assert 0 < len(kept["sigma"]) < n and (kept["sigma"] <= cut).all()


@pytest.mark.slow
def test_models_without_the_head_are_unchanged(reference_dir, tmp_path):
  """The base fixture (no flow covariance): no covariance files, no fifth tile, no match
  covariance, exports flow + covisibility only; --max-sigma is refused naming why."""
  d = reference_dir / "base"
  base_io = dict(np.load(d / "io.npz"))
  src, tgt = base_io["hl1_src_uint8"], base_io["hl1_tgt_uint8"]
  io.write_image(tmp_path / "s.png", src)
  io.write_image(tmp_path / "t.png", tgt)
  assert cli.main(["infer", str(tmp_path / "s.png"), str(tmp_path / "t.png"), "--checkpoint",
                   str(d), "--out", str(tmp_path / "o")]) == 0
  assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [
      "forward.flo", "forward_covisibility.npy", "forward_covisibility.png", "forward_flow.npy",
      "forward_panel.png"]
  h, w = src.shape[:2]
  assert io.read_image(tmp_path / "o" / "forward_panel.png").shape == (h, 4 * w, 3)
  model, params = ufm_jax.load_official(d)
  m = matching.match(model, params, src, tgt, num=100)
  assert set(m) == {"keypoints0", "keypoints1", "confidence", "eligible"}
  with pytest.raises(ValueError, match="max_sigma.*predicts none"):
    matching.match(model, params, src, tgt, num=100, max_sigma=1.0)
  assert export.resolve_outputs(None, {"flow": 0, "covisibility": 0}) == ("flow", "covisibility")
  assert outputs.written(outputs.paths(tmp_path, "x"), {"flow": 0, "covisibility": 0}).keys() == {
      "npy", "cnpy", "cpng", "panel", "flo"}


@pytest.mark.slow
def test_stablehlo_export_carries_the_covariance(snap, tmp_path):
  d, model, params, io_ = snap
  src, tgt = io_["img1_uint8"][:1], io_["img2_uint8"][:1]
  out = tmp_path / "m.stablehlo"
  assert cli.main(["export", "--checkpoint", str(d), "--size", "84x126", "--out", str(out)]) == 0
  side = json.loads(export.sidecar_path(out).read_text())
  assert list(side["outputs"]) == ["flow", "covisibility", "flow_covariance"]
  assert side["outputs"]["flow_covariance"]["shape"] == [1, 84, 126, 3]
  got = ufm_jax.load_exported(out)(src, tgt)
  ref = jax.jit(lambda a, b: model.apply(ufm.variables(params), a, b))(src, tgt)
  testing.assert_covariance_close("stablehlo", got["flow_covariance"], ref["flow_covariance"],
                                  1e-4)


@pytest.mark.slow
def test_onnx_export_carries_the_covariance(snap, tmp_path):
  """ONNX through jax2onnx and onnxruntime, on the covariance snapshot itself."""
  testing.require_extra("onnx", ("jax2onnx", "onnxruntime"))
  _, model, params, _ = snap
  out = tmp_path / "m.onnx"
  export.export(model, params, (28, 42), out, fmt="onnx")
  rng = np.random.default_rng(0)
  src, tgt = (rng.integers(0, 256, (1, 28, 42, 3), dtype=np.uint8) for _ in range(2))
  got = ufm_jax.load_exported(out)(src, tgt)
  assert list(got) == ["flow", "covisibility", "flow_covariance"]
  ref = jax.jit(lambda a, b: model.apply(ufm.variables(params), a, b))(src, tgt)
  # onnxruntime's kernels round differently from XLA's: the parity bound
  testing.assert_covariance_close("onnx", got["flow_covariance"], ref["flow_covariance"], 1e-3)
  np.testing.assert_allclose(got["flow"], np.asarray(ref["flow"]), atol=1e-3)


def test_evaluate_reports_the_calibration(snap, tmp_path, run_evaluate):
  """evaluate.py on the covariance snapshot: the synthetic bench's results.json and report carry
  every calibration column, and the NLLs and coverages recomputed from the files
  --save_predictions writes (the .flo and the covariance .npy) with the bench's ground truth
  agree with them (the formulas themselves: tests/test_covariance.py)."""
  from ufm_jax.data import get_source
  from ufm_jax.evaluators import base, report
  preds, out = tmp_path / "preds", tmp_path / "out"
  rc, printed, err = run_evaluate("--bench", "synthetic", "--snapshot", str(snap[0]),
                                  "--max_pairs", "2", "--save_predictions", str(preds),
                                  "--num_panels", "0", "--out", str(out), "--no_progress")
  assert rc == 0, err[-3000:]
  m = json.loads((out / "results.json").read_text())["metrics"]
  for k in report.CALIBRATION_COLUMNS:
    assert np.isfinite(m[f"synthetic/{k}"]), (k, m)
    assert f" {k} |" in printed, k
  src = get_source("synthetic", None, split="test")
  acc = metrics.Pooled()
  areas = []
  for i in range(2):
    s = src[i]
    flo, _ = base.predicted_paths(preds, "synthetic", s, i)
    cov = np.load(flo.with_name(flo.stem + "_flow_covariance.npy"))
    assert cov.shape == s["flow"].shape[:2] + (3,) and cov.dtype == np.float32
    mask = s["flow_valid"] & s["covisibility"] & s["covis_valid"]
    flow = io.read_flo(flo)
    metrics.add_calibration(acc, metrics.Sparsification(), flow, s["flow"], cov, mask)
    areas.append(_per_image_ause(flow, s["flow"], cov, mask))
  for k in ("nll", "nll_laplace", "coverage_1sigma", "coverage_2sigma", "coverage_3sigma"):
    assert acc.mean(k) == pytest.approx(m[f"synthetic/{k}"], rel=1e-5), k
  ause, ause_random = np.mean(areas, 0)
  assert m["synthetic/ause"] == pytest.approx(ause, rel=1e-9)
  assert m["synthetic/ause_random"] == pytest.approx(ause_random, rel=1e-9)


def _per_image_ause(flow, flow_gt, cov, mask):
  """(AUSE, random AUSE) of one image written out from Ilg et al.'s definition, pixel by pixel:
  at f = i / 100 drop the floor(f n) pixels of largest trace (or EPE, the oracle), average the
  rest, and integrate the differences with the trapezoid rule."""
  epe = np.sqrt(((flow.astype(np.float64) - flow_gt) ** 2).sum(-1))[mask]
  trace = (cov[..., 0].astype(np.float64) + cov[..., 1])[mask]
  n = epe.size
  by_trace = epe[np.argsort(-trace, kind="stable")]
  by_epe = np.sort(epe)[::-1]
  model, oracle = [], []
  for i in range(100):
    k = int(np.floor(i / 100 * n))
    model.append(by_trace[k:].mean())
    oracle.append(by_epe[k:].mean())
  model, oracle = np.array(model), np.array(oracle)
  area = lambda d: sum((d[j] + d[j + 1]) / 2 * 0.01 for j in range(99))  # noqa: E731
  return area(model - oracle), area(epe.mean() - oracle)


def test_demo_shows_the_uncertainty(snap, images, tmp_path):
  _, model, params, _ = snap
  _, _, src, tgt, pred = images
  analyser = demo.Analyser(model, params, tmp_path)
  *_, npz, summary, uncertainty = analyser(src, tgt, 0.0, 200)
  np.testing.assert_array_equal(uncertainty, viz.uncertainty_view(pred["flow_covariance"]))
  assert uncertainty.shape[1] == max(210, viz.LEGEND_MIN_WIDTH) and uncertainty.shape[0] > 150
  assert "median match sigma" in summary
  saved = np.load(npz)
  assert saved["covariance"].shape == (len(saved["keypoints0"]), 2, 2)
  assert (np.diff(saved["sigma"]) >= 0).all()
