"""The refinement model of the official training recipe (variants.ufm_refine_recipe): BatchNorm
in the U-Net with torch's train/eval semantics, "modulate" feature combination, no uncertainty
head, and its official snapshot both ways."""

import json

import jax
import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

import ufm_jax
from ufm_jax import testing
from ufm_jax.models import refine, ufm, variants
from ufm_jax.official import config as official_config
from ufm_jax.official import keymap


def test_batch_norm_follows_torch_batchnorm2d():
  """From torch.nn.BatchNorm2d's definition: training normalises with the batch mean and biased
  variance and moves the running mean / UNBIASED variance by momentum 0.1; eval uses the running
  statistics; num_batches_tracked counts the training calls."""
  rng = np.random.default_rng(0)
  x = rng.normal(2.0, 3.0, (4, 5, 6, 3)).astype(np.float32)
  bn = refine.BatchNorm()
  v = bn.init(jax.random.PRNGKey(0), x)
  v = {"params": {"scale": np.array([1.0, 2.0, 0.5], np.float32),
                  "bias": np.array([0.0, -1.0, 3.0], np.float32)},
       "batch_stats": {"running_mean": np.array([0.5, 0.0, -1.0], np.float32),
                       "running_var": np.array([2.0, 1.0, 4.0], np.float32),
                       "num_batches_tracked": np.int32(7)}}
  y, upd = bn.apply(v, x, True, mutable=["batch_stats"])
  m, var = x.mean((0, 1, 2)), x.var((0, 1, 2))
  n = x.size // 3
  np.testing.assert_allclose(np.asarray(y), (x - m) / np.sqrt(var + 1e-5) * v["params"]["scale"]
                             + v["params"]["bias"], atol=1e-5)
  s = upd["batch_stats"]
  np.testing.assert_allclose(s["running_mean"], 0.9 * v["batch_stats"]["running_mean"] + 0.1 * m,
                             rtol=1e-6)
  np.testing.assert_allclose(s["running_var"], 0.9 * v["batch_stats"]["running_var"]
                             + 0.1 * var * n / (n - 1), rtol=1e-5)
  assert int(s["num_batches_tracked"]) == 8
  y_eval = bn.apply(v, x)   # train=False: the running statistics, nothing updated
  np.testing.assert_allclose(
      np.asarray(y_eval), (x - v["batch_stats"]["running_mean"]) /
      np.sqrt(v["batch_stats"]["running_var"] + 1e-5) * v["params"]["scale"] + v["params"]["bias"],
      atol=1e-5)


def _variables(model, seed):
  """Random params (shapes by eval_shape: no init compile) and the initial batch statistics."""
  stats = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype),
                       ufm.variable_shapes(model)["batch_stats"])
  stats = jax.tree_util.tree_map_with_path(
      lambda path, v: v + 1 if path[-1].key == "running_var" else v, stats)
  return {"params": testing.perturbed_params(model, seed), "batch_stats": stats}


@pytest.fixture(scope="module")
def tiny():
  model = ufm.model_from_config(variants.tiny_refine_recipe())
  x = np.random.default_rng(1).integers(0, 255, (2, 28, 42, 3), np.uint8)
  return model, _variables(model, 0), x, np.roll(x, 2, axis=2)


def test_tiny_recipe_trains_batch_stats_and_infers_from_them(tiny):
  model, variables, src, tgt = tiny
  assert set(ufm.variable_shapes(model)) == {"params", "batch_stats"}
  assert model.config.covisibility_head is None and "uncertainty_head_0_0" not in variables["params"]
  assert model.config.feature_combine_method == "modulate" and model.config.encoder.indices == (0, 1)
  train = jax.jit(lambda v, s, t: model.apply(v, s, t, train=True, mutable=["batch_stats"]))
  out, upd = train(variables, src, tgt)
  assert "covisibility" not in out and out["flow"].shape == (2, 28, 42, 2)
  counts = {int(c) for c in jax.tree.leaves(upd["batch_stats"]) if np.ndim(c) == 0}
  assert counts == {2}   # one U-Net call per view, as the official forward does
  before = jax.tree.leaves(variables["batch_stats"])
  after = jax.tree.leaves(upd["batch_stats"])
  assert any(not np.array_equal(a, b) for a, b in zip(before, after))
  evaluate = jax.jit(lambda v, s, t: model.apply(v, s, t))
  old, new = evaluate(variables, src, tgt), evaluate({**variables, **upd}, src, tgt)
  assert not np.allclose(old["feature_map_0"], new["feature_map_0"])  # eval reads running stats
  again, _ = train({**variables, **upd}, src, tgt)   # train reads batch stats only
  np.testing.assert_allclose(np.asarray(again["flow"]), np.asarray(out["flow"]), atol=1e-5)


def test_recipe_snapshot_both_ways(tmp_path):
  """Random variables -> official state dict + config.json -> load_official (same config,
  params and batch statistics) -> save_official (the same tensors, batch counts as int64)."""
  cfg = testing.official_small_refine_recipe_config()
  model = ufm.model_from_config(cfg)
  variables = _variables(model, 3)
  variables["batch_stats"] = jax.tree.map(lambda s: s + 41, variables["batch_stats"])
  state = keymap.state_dict_from_params(variables, official_config.ufm_buffers(cfg))
  assert state["unet_feature.downs.0.conv.2.num_batches_tracked"].dtype == np.int64
  assert state["unet_feature.downs.0.conv.3.weight"].shape == (8, 8, 3, 3)   # conv after the BN
  assert state["conv1.weight"].shape == (16, 16, 1, 1) and state["conv2.weight"].shape == (8, 8, 1, 1)
  assert not any(k.startswith("uncertainty_head") for k in state)
  cj = official_config.official_config_dict(cfg)
  assert cj["use_unet_batchnorm"] is True and cj["feature_combine_method"] == "modulate"
  assert cj["uncertainty_head_kwargs"] == {} and cj["encoder_kwargs"]["indices"] == [0, 1]
  snap = tmp_path / "snap"   # as save_pretrained writes it (0-d batch counts stay 0-d)
  snap.mkdir()
  (snap / "config.json").write_text(json.dumps(cj))
  save_file(state, str(snap / "model.safetensors"))
  back, back_vars = ufm_jax.load_official(snap)
  assert back.config == cfg and set(back_vars) == {"params", "batch_stats"}
  for a, b in zip(jax.tree.leaves(back_vars), jax.tree.leaves(variables)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  ufm_jax.save_official(back, back_vars, tmp_path / "out")
  got = load_file(str(tmp_path / "out" / "model.safetensors"))
  assert sorted(got) == sorted(state)
  for k, v in state.items():
    assert got[k].dtype == (np.int64 if k.endswith("num_batches_tracked") else np.float32), k
    np.testing.assert_array_equal(got[k], v, err_msg=k)
  assert json.loads((tmp_path / "out" / "config.json").read_text()) == cj


def test_recipe_variant_is_the_official_recipe():
  cfg = variants.ufm_refine_recipe()
  assert cfg.encoder.indices == (6, 23) and cfg.covisibility_head is None
  assert cfg.use_unet_batchnorm and cfg.feature_combine_method == "modulate"
  assert cfg.unet_features == (64, 128, 256, 512) and cfg.refinement_range == 7
  assert (cfg.refine_feature_dim, cfg.refine_mlp_ratio) == (16, 2.0)
  assert cfg.flow_adaptor.flow_std == (25.0, 25.0) and cfg.flow_adaptor.base_shape == (224, 224)
  # what the official classes would be given for it
  cj = official_config.official_config_dict(cfg)
  assert cj["classification_head_kwargs"]["input_feature_dim"] == "1024 + 768"
  assert cj["info_sharing_kwargs"]["indices"] == [5, 8]
