"""The model as the official recipes initialise it (`UFMConfig.param_init="official"`): the
fusion transformer's Linear weights xavier_uniform with zero biases, every other Linear / Conv /
ConvTranspose with PyTorch's defaults (U(+-1/sqrt(fan_in)) for weight and bias, the fan-in of a
transposed conv counted over its output channels), norms at 1 / 0, the encoder untouched; and the
training configs' partial sub-config overrides (the flow adaptor normalisation)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from ufm_jax.training import trainer
from ufm_jax.models import dpt, info_sharing, ufm, variants


def _flat(params):
  return {"/".join(k): np.asarray(v) for k, v in traverse_util.flatten_dict(params).items()}


def _check_uniform(x, bound, what):
  assert np.abs(x).max() <= bound * (1 + 1e-6), (what, np.abs(x).max(), bound)
  if x.size >= 256:   # a uniform draw: std bound / sqrt(3), spread over the whole range
    assert abs(x.std() / (bound / math.sqrt(3)) - 1) < 0.15, (what, x.std(), bound)
    assert np.abs(x).max() > 0.9 * bound, what


@pytest.mark.parametrize("variant,scan", [("tiny_refine", False), ("tiny_refine", True),
                                          ("tiny_refine_recipe", True)])
@pytest.mark.slow
def test_official_init_draws_as_the_official_modules(variant, scan):
  """tiny_refine_recipe: BatchNorm scale 1 / bias 0 (torch's), the up-convolutions still found
  by name among the BatchNorm DoubleConvs (`unet_feature/ups_{even}`)."""
  model = variants.build_model(variant, param_init="official", scan_blocks=scan)
  flax_model = variants.build_model(variant, scan_blocks=scan)
  p, q = _flat(trainer.random_params(model, 0)), _flat(trainer.random_params(flax_model, 0))
  assert p.keys() == q.keys()
  seen = {"xavier": 0, "torch": 0, "transposed": 0}
  for k, v in p.items():
    top, leaf = k.split("/")[0], k.split("/")[-1]
    module = k.rsplit("/", 1)[0]
    if top == "encoder":
      np.testing.assert_array_equal(v, q[k], err_msg=k)
    elif leaf in ("scale", "gamma"):
      np.testing.assert_array_equal(v, 1.0, err_msg=k)
    elif top == "info_sharing" and leaf == "kernel":
      fan_in, fan_out = v.shape[-2], v.shape[-1]
      _check_uniform(v, math.sqrt(6 / (fan_in + fan_out)), k)
      seen["xavier"] += 1
    elif top == "info_sharing" or k == "classification_bias" or \
        (leaf == "bias" and module + "/kernel" not in p):
      np.testing.assert_array_equal(v, 0.0, err_msg=k)     # Linear biases, norms, the bias
    elif leaf in ("kernel", "bias"):
      kernel = p[module + "/kernel"]
      transposed = module.split("/")[-1] in dpt.CONV_TRANSPOSE or (
          top == "unet_feature" and module.split("/")[-1] in ("ups_0", "ups_2"))
      fan_in = (int(np.prod(kernel.shape[:-2])) * kernel.shape[-1] if transposed
                else int(np.prod(kernel.shape[:-1])))
      _check_uniform(v, 1 / math.sqrt(fan_in), k)
      seen["transposed" if transposed else "torch"] += 1
    else:
      raise AssertionError(f"unexpected parameter {k}")
  assert seen["xavier"] >= 4 and seen["torch"] > 40 and seen["transposed"] >= 4, seen
  # The U-Net's up-convolution has in != out (the fan-in rule matters): 2x2x16->8 in tiny.
  assert p["unet_feature/ups_0/kernel"].shape[-2] != p["unet_feature/ups_0/kernel"].shape[-1]


@pytest.mark.slow
def test_official_init_is_deterministic_and_differs_from_flax():
  model = variants.build_model("tiny", param_init="official")
  a, b = _flat(trainer.random_params(model, 0)), _flat(trainer.random_params(model, 0))
  c = _flat(trainer.random_params(model, 1))
  key = "head1_0_1/conv1/kernel"
  np.testing.assert_array_equal(a[key], b[key])
  assert not np.array_equal(a[key], c[key])


def test_official_init_excludes_the_tied_query_key_init():
  cfg = variants.tiny()
  with pytest.raises(ValueError, match="tied_qk_init"):
    cfg.replace(param_init="official",
                info_sharing=info_sharing.InfoSharingConfig(
                    input_embed_dim=64, dim=64, depth=3, num_heads=2, indices=(0, 1),
                    tied_qk_init=2.0))
  with pytest.raises(ValueError, match="param_init"):
    cfg.replace(param_init="torch")


def test_partial_flow_adaptor_override_scales_the_output():
  """The recipes' normalisation: std 25 at a 224 x 224 base shape, scale_both; as a training
  config's `model` block gives it (a mapping, lists from JSON)."""
  cfg = variants.tiny().replace(flow_adaptor={"flow_std": [25.0, 25.0], "base_shape": [224, 224]})
  assert cfg.flow_adaptor == dpt.FlowAdaptorConfig((0.0, 0.0), (25.0, 25.0), (224, 224),
                                                   "scale_both")
  x = jnp.ones((1, 448, 672, 2))
  out = np.asarray(dpt.flow_adaptor(x, cfg.flow_adaptor))
  np.testing.assert_allclose(out[0, 0, 0], [25 * 672 / 224, 25 * 448 / 224])
  assert ufm.config_from_dict(ufm.config_to_dict(cfg)) == cfg


@pytest.mark.slow
def test_official_init_model_exports_to_an_official_snapshot(tmp_path):
  """param_init is an initializer option, not structure: a model trained from it exports (the
  snapshot has no such key and reads back as the same structure)."""
  from ufm_jax import testing
  from ufm_jax.official import snapshot
  model = testing.official_small_model({"param_init": "official"})
  notes = snapshot.save_official(model, trainer.random_params(model, 0), tmp_path / "export")
  assert "not written (JAX-only option): param_init='official'" in notes
