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


def test_batch_norm_group_rows_takes_each_gpus_statistics():
  """group_rows: the statistics of each group of consecutive rows on its own (DDP without
  sync_batchnorm, each GPU its rows), the running ones from the first group's (rank 0's)."""
  rng = np.random.default_rng(1)
  x = rng.normal(1.0, 2.0, (6, 5, 4, 3)).astype(np.float32)
  x[2:4] *= 3.0   # groups with different statistics
  v = refine.BatchNorm().init(jax.random.PRNGKey(0), x)
  y, upd = refine.BatchNorm(group_rows=2).apply(v, x, True, mutable=["batch_stats"])
  for g in range(3):
    want, ref = refine.BatchNorm().apply(v, x[2 * g:2 * g + 2], True, mutable=["batch_stats"])
    np.testing.assert_allclose(np.asarray(y[2 * g:2 * g + 2]), np.asarray(want), atol=1e-5)
    if g == 0:
      jax.tree.map(lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b),
                                                           rtol=1e-6),
                   upd["batch_stats"], ref["batch_stats"])
  whole, _ = refine.BatchNorm().apply(v, x, True, mutable=["batch_stats"])
  assert not np.allclose(np.asarray(whole), np.asarray(y), atol=1e-3)
  with pytest.raises(ValueError, match=r"per 4 rows \(model.unet_batchnorm_group_rows\) do not "
                                       r"divide a batch of 6 rows"):
    refine.BatchNorm(group_rows=4).apply(v, x, True, mutable=["batch_stats"])


_PER_DEVICE = r"""
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from ufm_jax.planning import hlo_stats
from ufm_jax.models import refine
assert jax.device_count() == 8
mesh = Mesh(np.array(jax.devices()), ("data",))
x = np.random.default_rng(0).normal(0.0, 1.0, (16, 12, 10, 4)).astype(np.float32)
x *= np.arange(1, 17, dtype=np.float32)[:, None, None, None]
v = refine.BatchNorm().init(jax.random.PRNGKey(0), x[:1])
xs = jax.device_put(x, NamedSharding(mesh, P("data")))
step = jax.jit(lambda v, x: refine.BatchNorm(group_rows=2).apply(v, x, True,
                                                               mutable=["batch_stats"]))
y, upd = step(v, xs)
# Each device on its own rows, as each GPU of the official DDP run.
per_device = jax.jit(jax.shard_map(
    lambda x: refine.BatchNorm().apply(v, x, True, mutable=["batch_stats"])[0], mesh=mesh,
    in_specs=P("data"), out_specs=P("data")))(xs)
np.testing.assert_allclose(np.asarray(y), np.asarray(per_device), atol=1e-5)
_, rank0 = refine.BatchNorm().apply(v, x[:2], True, mutable=["batch_stats"])
for k in ("running_mean", "running_var"):
  np.testing.assert_allclose(np.asarray(upd["batch_stats"][k]), np.asarray(rank0["batch_stats"][k]),
                             rtol=1e-6)
assert y.sharding.spec == P("data"), y.sharding
# Statistics stay on their device: no collective moves the activations, only a C-sized
# broadcast of the first group's statistics for the running ones.
colls = hlo_stats.collectives(step.lower(v, xs).compile().as_text())
assert hlo_stats.total_bytes(colls) <= 1024, colls
print("ok", len(colls))
"""


def test_batch_norm_groups_are_per_device_statistics_on_8_fake_devices():
  """On a mesh of 8 fake CPU devices, the jitted BatchNorm with group_rows = rows per device
  equals each device normalising its own rows (shard_map), keeps the output batch-sharded and
  moves no activations between devices."""
  import subprocess
  import sys
  r = subprocess.run([sys.executable, "-c", _PER_DEVICE], env=testing.fake_devices_env(8),
                     capture_output=True, text=True, timeout=600)
  assert r.returncode == 0 and "ok" in r.stdout, r.stderr[-3000:]


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


@pytest.mark.slow
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
