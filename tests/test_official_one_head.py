"""The one-head `UniFlowMatch` class (train branch configs/model/uniflowmatch.yaml; UFM main
3732a50 + UniCeption ee7fa0b): no uncertainty head, the main head's adaptor map holds the flow
and optionally `non_occluded_mask` and `flow_cov`, its channels split in config.json's key order.

Every case folder of ufm_reference_one_head (UFM_ONE_HEAD_FIXTURES, else
UFM_FIXTURES/ufm_reference_one_head) against its official outputs at the other v2 cases'
tolerances, and its exact round trip; snapshots written here from random weights through
save_official for the adaptor maps {flow}, {flow, non_occluded_mask} and
{flow, flow_cov, non_occluded_mask} and every FlowAdaptor scale_strategy, against the adaptors
computed here from the head's channels; the tools on a model with and without covisibility."""

import dataclasses
import json

import jax
import numpy as np
import pytest

import ufm_jax
from ufm_jax import testing
from ufm_jax.data import io as data_io
from ufm_jax.models import covariance, ufm
from ufm_jax.official import config as official_config
from ufm_jax.runtime import model_io, outputs
from ufm_jax.tools import cli, demo, matching

ROOT, CASES = testing.reference_cases("ufm_reference_one_head", "UFM_ONE_HEAD_FIXTURES")


@pytest.fixture(scope="module", params=CASES or [None])
def case(request):
  d = testing.reference_case(ROOT, request.param, "UFM_ONE_HEAD_FIXTURES")
  return (d,) + testing.official_case(d)


def test_loads_as_uniflowmatch_without_an_uncertainty_head(case):
  d, model, variables, _, out = case
  cj = json.loads((d / "config.json").read_text())
  assert official_config.class_name(model) == "UniFlowMatch"
  assert model.config.covisibility_head is None
  assert "uncertainty_head_0_0" not in variables["params"]
  assert model.config.flow_head_adaptors == tuple(cj["adaptors_kwargs"])
  assert model.config.has_covisibility == ("non_occluded_mask" in cj["adaptors_kwargs"])
  assert ("covisibility" in out) == model.config.has_covisibility
  assert ("flow_covariance" in out) == ("flow_cov" in cj["adaptors_kwargs"])


def test_forward_matches_the_official_outputs(case):
  """testing.assert_forward_parity: flow 1e-3 px, logits 2e-4, mask 5e-5 (the v2 cases')."""
  _, _, _, io, out = case
  testing.assert_forward_parity(io, out)
  if "flow_covariance" in io:
    testing.assert_covariance_close("flow_covariance", out["flow_covariance"],
                                    testing.nhwc(io["flow_covariance"]), 1e-3)


@pytest.mark.parametrize("pair", ["hl0", "hl1", "hl2"])
def test_predict_matches_the_official_high_level_api(case, pair):
  """predict_correspondences_batched: hl*_flow within testing.HL_FLOW_ATOL, covisibility 5e-5,
  a covariance (when the map has one) within 5e-3, as tests/test_official_covariance.py."""
  _, model, variables, io, _ = case
  got = testing.assert_predict_parity(model, variables, io, pair)
  key = f"{pair}_flow_covariance"
  assert ("flow_covariance" in got) == model.config.has_flow_covariance
  if key in io:
    testing.assert_covariance_close(key, got["flow_covariance"], testing.nhwc(io[key])[0], 5e-3)


def test_round_trip_through_our_checkpoint_is_exact(case, tmp_path):
  """snapshot -> convert -> to-official: config.json and model.safetensors byte for byte."""
  d, model, variables, _, _ = case
  testing.assert_exact_official_round_trip(d, model, variables, tmp_path)


def test_an_unknown_scale_strategy_is_an_error_naming_it(case, tmp_path):
  def edit(cj):
    cj["adaptors_kwargs"]["flow"]["kwargs"]["scale_strategy"] = "scale_diagonal"
  snap = testing.snapshot_with_config(case[0], tmp_path / "snap", edit)
  with pytest.raises(ValueError, match=r"adaptors_kwargs\.flow\.kwargs\.scale_strategy="
                                       r"'scale_diagonal' is not a FlowAdaptor scale strategy"):
    ufm_jax.load_official(snap)


def test_a_main_head_mask_beside_an_uncertainty_head_is_refused(tmp_path):
  """UniFlowMatchConfidence reads covisibility from its uncertainty head only."""
  src = testing.random_snapshot(tmp_path / "base", testing.official_small_config())

  def edit(cj):
    cj["adaptors_kwargs"]["non_occluded_mask"] = {"class": "MaskAdaptor",
                                                  "kwargs": {"name": "non_occluded_mask"}}
  with pytest.raises(ValueError, match=r"adaptors_kwargs\.non_occluded_mask"):
    ufm_jax.load_official(testing.snapshot_with_config(src, tmp_path / "snap", edit))


# --------------------------------------------------------------------------- other adaptor maps


def _one_head_config(names, strategy):
  base = testing.official_small_config()
  cfg = base.replace(
      covisibility_head=None, flow_head_adaptors=tuple(names),
      flow_head=dataclasses.replace(base.flow_head, output_dim=2 + 3 * ("flow_cov" in names)
                                    + ("non_occluded_mask" in names)),
      flow_adaptor=dataclasses.replace(base.flow_adaptor, flow_mean=(1.5, -2.0),
                                       flow_std=(8.0, 6.0), scale_strategy=strategy),
      flow_covariance=covariance.CovarianceConfig(low_confidence_init=True)
      if "flow_cov" in names else None)
  return cfg


def _scale(strategy, h, w, base_hw):
  """UniCeption FlowAdaptor._get_xy_scale, written out."""
  return {"none": (1.0, 1.0), "scale_width": (w / base_hw[1],) * 2,
          "scale_height": (h / base_hw[0],) * 2,
          "scale_both": (w / base_hw[1], h / base_hw[0])}[strategy]


MAPS = [(("flow",), "none"), (("flow",), "scale_height"),
        (("flow", "non_occluded_mask"), "scale_width"),
        (("flow", "flow_cov", "non_occluded_mask"), "scale_both")]


@pytest.mark.parametrize("names,strategy", MAPS)
def test_other_maps_and_scale_strategies_load_run_and_round_trip(tmp_path, names, strategy):
  """A UniFlowMatch snapshot written through save_official from random weights: config.json has
  the constructor's keys only and the map in the given order; it loads back to the same config
  and params; the flow, covisibility and covariance are the adaptors of the head's channels
  taken here in that order; convert -> to-official is byte for byte."""
  cfg = _one_head_config(names, strategy)
  model = ufm.model_from_config(cfg)
  params = testing.perturbed_params(model, 5)
  snap = tmp_path / "snap"
  ufm_jax.save_official(model, {"params": params}, snap)
  cj = json.loads((snap / "config.json").read_text())
  assert set(cj) <= set(official_config.ONE_HEAD_KEYS)
  assert list(cj["adaptors_kwargs"]) == list(names)
  assert cj["adaptors_kwargs"]["flow"]["kwargs"]["scale_strategy"] == strategy
  back, variables = ufm_jax.load_official(snap)
  assert back.config == cfg and official_config.class_name(back) == "UniFlowMatch"
  jax.tree.map(np.testing.assert_array_equal, variables, {"params": params})

  h, w = 42, 70   # not the base shape (56, 56), and not square: the strategies differ
  rng = np.random.default_rng(0)
  x = rng.integers(0, 256, (1, h, w, 3), dtype=np.uint8)
  out, sown = jax.jit(lambda v, a, b: back.apply(v, a, b, mutable=["intermediates"]))(
      variables, x, x[:, :, ::-1])
  decoded = np.asarray(sown["intermediates"]["flow_decoded_channels"][0], np.float64)
  at, start = {}, 0
  for n in names:
    at[n] = slice(start, start + {"flow": 2, "flow_cov": 3, "non_occluded_mask": 1}[n])
    start = at[n].stop
  sx, sy = _scale(strategy, h, w, cfg.flow_adaptor.base_shape)
  want = decoded[..., at["flow"]] * np.array([8.0 * sx, 6.0 * sy]) + np.array([1.5 * sx, -2.0 * sy])
  np.testing.assert_allclose(np.asarray(out["flow"]), want, rtol=1e-5, atol=1e-4)
  assert ("covisibility" in out) == ("non_occluded_mask" in names)
  if "non_occluded_mask" in names:
    logits = decoded[..., at["non_occluded_mask"]][..., 0]
    np.testing.assert_allclose(np.asarray(out["covisibility_logits"]), logits, atol=1e-6)
    np.testing.assert_allclose(np.asarray(out["covisibility"]), 1 / (1 + np.exp(-logits)),
                               atol=1e-6)
  assert ("flow_covariance" in out) == ("flow_cov" in names)
  if "flow_cov" in names:
    cov = covariance.adaptor(decoded[..., at["flow_cov"]], cfg.flow_covariance)
    np.testing.assert_allclose(np.asarray(out["flow_covariance"]), cov["flow_covariance"],
                               rtol=1e-4)
  testing.assert_exact_official_round_trip(snap, back, variables, tmp_path / "rt")


@pytest.fixture(scope="module")
def models():
  """{name: (model, variables)}: a one-head model with covisibility and one without."""
  out = {}
  for key, names in (("mask", ("flow", "non_occluded_mask")), ("flow", ("flow",))):
    model = ufm.model_from_config(_one_head_config(names, "scale_width"))
    out[key] = (model, {"params": testing.perturbed_params(model, 2)})
  return out


@pytest.fixture(scope="module")
def images():
  rng = np.random.default_rng(3)
  src = rng.integers(0, 256, (50, 64, 3), dtype=np.uint8)
  return src, np.roll(src, 3, axis=1)


def test_tools_with_covisibility(models, images, tmp_path):
  """predict, match, infer (every file) and the demo on a one-head model with a mask."""
  model, variables = models["mask"]
  src, tgt = images
  pred = ufm_jax.predict(model, variables, src, tgt)
  assert pred["flow"].shape == (50, 64, 2) and pred["covisibility"].shape == (50, 64)
  m = matching.match(model, variables, src, tgt, num=50, min_covisibility=0.0)
  assert len(m["keypoints0"]) == 50
  assert outputs.predicted(model) == {"flow": True, "covisibility": True}
  data_io.write_image(tmp_path / "a.png", src)
  data_io.write_image(tmp_path / "b.png", tgt)
  written = cli.run_infer(model, variables, tmp_path / "a.png", tmp_path / "b.png", tmp_path / "o")
  assert any(str(p).endswith("_covisibility.npy") for p in written)
  views = demo.Analyser(model, variables, tmp_path / "demo")(src, tgt, 0.0, 20)
  assert views[1] is not None and views[3] is not None and "matches" in views[5]


def test_tools_without_covisibility_say_so(models, images, tmp_path):
  """The map {flow}: predictions carry no covisibility (none made up), match refuses naming why,
  infer writes the flow files only, the demo shows flow and warp and says why there are no
  matches, and a converted checkpoint keeps the class."""
  model, variables = models["flow"]
  src, tgt = images
  pred = ufm_jax.predict(model, variables, src, tgt)
  assert set(pred) == {"flow"}
  with pytest.raises(ValueError, match="predicts none.*non_occluded_mask"):
    matching.match(model, variables, src, tgt, num=50)
  assert outputs.predicted(model) == {"flow": True}
  data_io.write_image(tmp_path / "a.png", src)
  data_io.write_image(tmp_path / "b.png", tgt)
  written = cli.run_infer(model, variables, tmp_path / "a.png", tmp_path / "b.png", tmp_path / "o")
  assert written and not any("covisibility" in str(p) for p in written)
  assert all(p.is_file() for p in written)
  colours, covis, warped, drawing, npz, summary, _ = demo.Analyser(
      model, variables, tmp_path / "demo")(src, tgt, 0.5, 20)
  assert colours is not None and warped is not None
  assert covis is None and drawing is None and npz is None
  assert "predicts no covisibility" in summary
  model_io.save(tmp_path / "ckpt", model, variables)
  meta = json.loads((tmp_path / "ckpt" / model_io.CONFIG_FILE).read_text())
  assert meta["class"] == "UniFlowMatch"
  back, _ = ufm_jax.load(tmp_path / "ckpt")
  assert back.config == model.config


@pytest.mark.slow
def test_export_without_covisibility_exports_the_flow(models, tmp_path):
  """export (StableHLO) of the {flow} model: the artifact and its sidecar hold flow only and the
  class name; the artifact runs and gives predict's forward flow."""
  from ufm_jax.tools import export
  model, variables = models["flow"]
  paths = export.export(model, variables, (56, 56), tmp_path / "m.stablehlo")
  meta = json.loads(export.sidecar_path(tmp_path / "m.stablehlo").read_text())
  assert meta["model"]["class"] == "UniFlowMatch"
  run = export.load_exported(paths[0])
  x = np.random.default_rng(1).integers(0, 256, (1, 56, 56, 3), dtype=np.uint8)
  got = run(x, x[:, ::-1])
  assert set(got) == {"flow"}
  want = jax.jit(model.apply)(variables, x, x[:, ::-1])["flow"]
  np.testing.assert_allclose(np.asarray(got["flow"]), np.asarray(want), atol=1e-4)
