"""UFM-Refine parity against the official PyTorch fixture (../shared/fixtures/ufm_reference/refine)."""

import jax.numpy as jnp
import numpy as np
import pytest
from safetensors.numpy import load_file

from ufm_jax.models import refine


def nhwc(a):
  return np.transpose(a, (0, 2, 3, 1))


@pytest.fixture(scope="module")
def fx(reference_dir):
  d = reference_dir / "refine"
  tensors = load_file(str(d / "model.safetensors"))
  params, used = refine.refiner_params_from_torch(tensors)
  return dict(dir=d, tensors=tensors, params=params, used=used,
              io=dict(np.load(d / "io.npz")), it=dict(np.load(d / "intermediates.npz")))


@pytest.fixture(scope="module")
def refiner(fx):
  import json
  cfg = json.loads((fx["dir"] / "config.json").read_text())
  head = cfg["classification_head_kwargs"]
  return refine.Refiner(unet_features=refine.unet_widths(fx["tensors"]),
                        feature_dim=head["output_dim"], patch_size=head["patch_size"],
                        mlp_ratio=head["mlp_ratio"], use_unet_feature=cfg["use_unet_feature"],
                        feature_combine_method=cfg["feature_combine_method"],
                        refinement_range=cfg["refinement_range"], temperature=cfg["temperature"])


def test_unet_widths_from_weights(fx):
  assert refine.unet_widths(fx["tensors"]) == (8, 16, 32, 64)


def test_unet_matches_fixture(fx, refiner):
  io, it = fx["io"], fx["it"]
  imgs = np.concatenate([nhwc(io["img1_norm"]), nhwc(io["img2_norm"])])
  out = refiner.apply({"params": fx["params"]}, imgs, method=lambda m, x: m.unet_feature(x))
  ref = np.concatenate([nhwc(it["unet_out_view1"]), nhwc(it["unet_out_view2"])])
  np.testing.assert_allclose(np.asarray(out), ref, atol=2e-4)


def test_classification_head_matches_fixture(fx, refiner):
  it = fx["it"]
  tokens = nhwc(it["cls_head_in"])
  mlp = refiner.apply({"params": fx["params"]}, tokens,
                      method=lambda m, x: m.classification_head(x, return_mlp=True))
  np.testing.assert_allclose(np.asarray(mlp), it["cls_mlp_out_nhwc"], atol=1e-4)
  out = refiner.apply({"params": fx["params"]}, tokens, method=lambda m, x: m.classification_head(x))
  np.testing.assert_allclose(np.asarray(out), nhwc(it["cls_head_out"]), atol=1e-4)


def test_feature_maps_match_fixture(fx, refiner):
  io, it = fx["io"], fx["it"]
  tokens = nhwc(it["cls_head_in"])
  imgs = np.concatenate([nhwc(io["img1_norm"]), nhwc(io["img2_norm"])])
  feats = np.asarray(refiner.apply({"params": fx["params"]}, tokens, imgs,
                                   method=lambda m, t, x: m.features(t, x)))
  np.testing.assert_allclose(feats[:2], nhwc(io["feature_map_0"]), atol=2e-4)
  np.testing.assert_allclose(feats[2:], nhwc(io["feature_map_1"]), atol=2e-4)


@pytest.mark.parametrize("chunk", [None, 16])
def test_local_refinement_matches_fixture(fx, chunk):
  """The official features and regressed flow in; residual, log_softmax, refined flow out."""
  io = fx["io"]
  flow0 = nhwc(io["flow_before_refinement"])
  res, log_p = refine.local_refinement(
      jnp.asarray(nhwc(io["feature_map_0"])), jnp.asarray(nhwc(io["feature_map_1"])),
      jnp.asarray(flow0), jnp.asarray(fx["params"]["classification_bias"]), temperature=4.0,
      radius=3, chunk=chunk)
  np.testing.assert_allclose(np.asarray(res), nhwc(io["residual"]), atol=5e-3)
  np.testing.assert_allclose(np.asarray(log_p), io["log_softmax"], atol=1e-2)
  np.testing.assert_allclose(flow0 + np.asarray(res), nhwc(io["flow"]), atol=5e-3)
  # The official `regression_flow_output` holds the refined flow too.
  np.testing.assert_allclose(flow0 + np.asarray(res), nhwc(io["regression_flow_output"]), atol=5e-3)
