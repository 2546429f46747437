"""Snapshots with UniCeption's Covariance2DAdaptor (ufm_reference_cov, made by UFM main 3732a50 +
UniCeption ee7fa0b) against their official outputs, every case folder found (UFM_COV_FIXTURES,
else UFM_FIXTURES/ufm_reference_cov); their exact round trip; the config.json rules of the
adaptor maps (channel order = key order, unknown parametrisations refused by name); a head the
fixtures do not cover (the covariance in the main head, low_confidence_init off)."""

import json
import pathlib

import jax
import numpy as np
import pytest

import ufm_jax
from ufm_jax import testing
from ufm_jax.models import covariance
from ufm_jax.models import ufm
from ufm_jax.official import config as official_config
from ufm_jax.official import keymap

ROOT, CASES = testing.reference_cases("ufm_reference_cov", "UFM_COV_FIXTURES")


def _case_dir(name) -> pathlib.Path:
  return testing.reference_case(ROOT, name, "UFM_COV_FIXTURES")


# The official adaptor computes 1 - tanh(s)^2 in float32: where |rho| nears 1 the difference keeps
# few digits (its tanh is within ~1 ulp of 1, 6e-8; at rho = 0.99999 that is ~0.2% of 1 - rho^2),
# so the log-determinant and the inverse are compared to 1e-3 plus that cancellation, 5e-7 /
# (1 - rho^2) (measured on flow_cov: 2.3e-3 at 1 - rho^2 = 2.5e-5, where the bound is 2.1e-2;
# 2e-5 where 1 - rho^2 > 0.01). Ours takes it as sech(s)^2 and agrees with float64 to 2e-6.
CANCELLATION = 5e-7


def _one_minus_rho2(cov):
  cov = np.asarray(cov, np.float64)
  return 1 - cov[..., 2] ** 2 / (cov[..., 0] * cov[..., 1]) + covariance.OFFICIAL_EPS


@pytest.fixture(scope="module", params=CASES or [None])
def case(request):
  d = _case_dir(request.param)
  return (d,) + testing.official_case(d)


def test_forward_matches_the_official_outputs(case):
  """flow 1e-3 px (5e-3 after refinement), logits 2e-4, mask 5e-5 (the older fixtures',
  testing.assert_forward_parity); the covariance: variances within 1e-3 of themselves, cov_xy
  within 1e-3 of sqrt(var_x var_y)."""
  _, model, _, io, out = case
  testing.assert_forward_parity(io, out)
  # (ufm_jax also returns a main-head covariance, which UniFlowMatchConfidence computes and drops)
  if "flow_covariance" not in io:
    return
  assert "flow_covariance" in out, "the official model predicts a flow covariance; ours none"
  want = testing.nhwc(io["flow_covariance"])
  assert out["flow_covariance"].dtype == np.float32
  testing.assert_covariance_close("flow_covariance", out["flow_covariance"], want, 1e-3)
  slack = CANCELLATION / _one_minus_rho2(want)
  err = np.abs(out["flow_covariance_log_det"] - io["flow_covariance_log_det"][:, 0])
  assert (err <= 1e-3 + slack).all(), f"log det: max |diff| {err.max():.3g}"
  testing.assert_covariance_close("flow_covariance_inv", out["flow_covariance_inv"],
                    testing.nhwc(io["flow_covariance_inv"]), 1e-3, slack)


@pytest.mark.parametrize("pair", ["hl0", "hl1", "hl2"])
def test_predict_matches_the_official_high_level_api(case, pair):
  """predict_correspondences_batched: hl*_flow at ~1e-2 px, the covariance at the source size
  (unmapped, scaled by the source's ratios) within 5e-3."""
  _, model, variables, io, _ = case
  got = testing.assert_predict_parity(model, variables, io, pair)
  key = f"{pair}_flow_covariance"
  if key in io:
    assert "flow_covariance" in got
    want = testing.nhwc(io[key])[0]
    testing.assert_covariance_close(key, got["flow_covariance"], want, 5e-3)
    # the precision the same way, exact inverse of the official covariance aside from rounding
    inv = covariance.inverse(np.asarray(got["flow_covariance"], np.float64))
    ok = _one_minus_rho2(want) > 1e-2      # the triplet's own inverse cancels beyond that
    np.testing.assert_allclose(got["flow_covariance_inv"][ok], inv[ok], rtol=5e-3,
                               atol=5e-3 * np.abs(inv[ok]).max())


def test_round_trip_through_our_checkpoint_is_exact(case, tmp_path):
  """snapshot -> convert -> to-official, exactly (testing.assert_exact_official_round_trip)."""
  d, model, variables, _, _ = case
  testing.assert_exact_official_round_trip(d, model, variables, tmp_path)


# --------------------------------------------------------------------------- config.json rules


@pytest.fixture(scope="module")
def cov_case():
  return _case_dir("flow_cov" if "flow_cov" in CASES else (CASES[0] if CASES else None))


def _cov_head(cj):
  return "uncertainty_adaptors_kwargs" if "flow_cov" in cj["uncertainty_adaptors_kwargs"] \
      else "adaptors_kwargs"


def test_an_unknown_parametrization_is_an_error_naming_the_key(cov_case, tmp_path):
  def edit(cj):
    cj[_cov_head(cj)]["flow_cov"]["kwargs"]["parametrization"] = "cholesky"
  snap = testing.snapshot_with_config(cov_case, tmp_path / "snap", edit)
  with pytest.raises(ValueError, match=r"adaptors_kwargs\.flow_cov\.kwargs\.parametrization="
                                       r"'cholesky' is not supported"):
    ufm_jax.load_official(snap)


@pytest.mark.parametrize("edit,match", [
    (lambda cj: cj["uncertainty_adaptors_kwargs"].update(keypoint_confidence={
        "class": "ConfidenceAdaptor", "kwargs": {"name": "keypoint_confidence"}}),
     r"uncertainty_adaptors_kwargs\.keypoint_confidence: not an adaptor"),
    (lambda cj: cj[_cov_head(cj)]["flow_cov"].update({"class": "MaskAdaptor"}),
     r"flow_cov\.class='MaskAdaptor'"),
    (lambda cj: cj[_cov_head(cj)]["flow_cov"]["kwargs"].update(scale=2.0),
     r"flow_cov\.kwargs\.scale: not an option"),
])
def test_adaptor_map_errors_name_the_key(cov_case, tmp_path, edit, match):
  snap = testing.snapshot_with_config(cov_case, tmp_path / "snap", edit)
  with pytest.raises(ValueError, match=match):
    ufm_jax.load_official(snap)


def test_channel_order_is_the_key_order_and_exports_only_sorted(cov_case, tmp_path):
  """The adaptor map hands out the head's channels in config.json's key order: the same weights
  listed in the other order are another model (the flow_cov channels move), and save_official
  refuses it, since save_pretrained sorts the keys and the reload would split them differently."""
  model, variables = ufm_jax.load_official(cov_case)
  head = _cov_head(json.loads((cov_case / "config.json").read_text()))
  if head != "uncertainty_adaptors_kwargs":
    pytest.skip("the order test uses an uncertainty head with two adaptors")

  def reverse(cj):
    cj[head] = dict(reversed(list(cj[head].items())))
  snap = testing.snapshot_with_config(cov_case, tmp_path / "snap", reverse, sort_keys=False)
  swapped, swapped_variables = ufm_jax.load_official(snap)
  assert swapped.config.uncertainty_head_adaptors == tuple(
      reversed(model.config.uncertainty_head_adaptors))
  io = dict(np.load(cov_case / "io.npz"))
  a = jax.jit(model.apply)(variables, io["img1_uint8"][:1], io["img2_uint8"][:1])
  b = jax.jit(swapped.apply)(swapped_variables, io["img1_uint8"][:1],
                             io["img2_uint8"][:1])
  # the swapped model's mask reads channel 0, which the sorted one's covariance reads as c1
  offset = covariance.LOW_CONFIDENCE_OFFSET * model.config.flow_covariance.low_confidence_init
  np.testing.assert_allclose(np.asarray(b["covisibility_logits"]),
                             np.asarray(a["flow_covariance_params"])[..., 0] - offset, atol=1e-5)
  with pytest.raises(ValueError, match="cannot be exported"):
    ufm_jax.save_official(swapped, swapped_variables, tmp_path / "out")
  assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- other heads


@pytest.mark.parametrize("structure,head,low", [
    ("small", "main", False), ("small", "uncertainty", False), ("small", "main", True),
    ("refine_window5", "uncertainty", True)])
def test_other_heads_load_export_and_match_the_adaptor(tmp_path, structure, head, low):
  """The covariance in the main head (the train branch's adaptor_map/efficient_combined.yaml) or
  the uncertainty head, low_confidence_init either way, also in the refinement class: an
  official snapshot written from random weights loads back to the same config and params, its
  covariance is the exp_tanh of its head's channels (split in the sorted key order), and
  save_official writes it back exactly."""
  base = testing.official_small_config() if structure == "small" else \
      testing.STRUCTURES[structure]
  cfg = ufm.with_flow_covariance(base, head=head, low_confidence_init=low)
  model = ufm.model_from_config(cfg)
  params = testing.perturbed_params(model, 11)
  state = keymap.state_dict_from_params(params, official_config.ufm_buffers(cfg))
  cj = official_config.official_config_dict(cfg)
  where = "adaptors_kwargs" if head == "main" else "uncertainty_adaptors_kwargs"
  assert cj[where]["flow_cov"] == {"class": "Covariance2DAdaptor", "kwargs": {
      "low_confidence_init": low, "name": "flow_cov", "parametrization": "exp_tanh"}}
  snap = testing.write_snapshot(tmp_path / "snap", cj, state)
  back, back_variables = ufm_jax.load_official(snap)
  assert back.config == cfg
  jax.tree.map(np.testing.assert_array_equal, back_variables, {"params": params})
  rng = np.random.default_rng(0)
  h, w = cfg.inference_resolution
  x = rng.integers(0, 256, (1, h, w, 3), dtype=np.uint8)
  fwd = jax.jit(lambda p, a, b: back.apply(ufm.variables(p), a, b, mutable=["intermediates"]))
  out, sown = fwd(back_variables, x, x[:, ::-1])
  assert out["flow_covariance"].shape == (1, h, w, 3)
  if head == "main":
    decoded = np.asarray(sown["intermediates"]["flow_decoded_channels"][0])
    assert decoded.shape[-1] == 5       # flow (2) then flow_cov (3): sorted keys
    want = covariance.adaptor(decoded[..., 2:5].astype(np.float64), cfg.flow_covariance)
    np.testing.assert_allclose(np.asarray(out["flow_covariance"]), want["flow_covariance"],
                               rtol=1e-5)
  ufm_jax.save_official(back, back_variables, tmp_path / "out")
  assert json.loads((tmp_path / "out" / "config.json").read_text()) == cj
