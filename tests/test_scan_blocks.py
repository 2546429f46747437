"""Model options of the training path: scanned blocks (stacked params, loaders, remat, the
activation hook, workdirs), bf16 DPT heads and the attention implementation choice. Parity of the
scan model against the official run is in test_model_parity.py / test_refine_parity.py."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util
from safetensors.numpy import save_file

from ufm_jax.runtime import checkpoint, model_io
from ufm_jax.training import model_init, trainer
from ufm_jax.models import layers, scan, ufm
from ufm_jax.official import keymap, snapshot


@pytest.fixture(scope="module")
def official(reference_dir):
  model, variables = snapshot.load_official(reference_dir / "base")
  params = variables["params"]
  io = dict(np.load(reference_dir / "base" / "io.npz"))
  return model, jax.tree.map(np.asarray, params), io


def _scan(model, **kw):
  return model.clone(config=model.config.replace(scan_blocks=True, **kw))


def _flat(tree):
  return traverse_util.flatten_dict(dict(tree))


def _assert_trees_equal(a, b):
  fa, fb = _flat(a), _flat(b)
  assert set(fa) == set(fb), sorted(set(fa) ^ set(fb))[:10]
  for k in fa:
    np.testing.assert_array_equal(np.asarray(fa[k]), np.asarray(fb[k]), err_msg="/".join(k))


def test_stacked_layout_round_trip(official):
  model, params, _ = official
  cfg = _scan(model).config
  stacked = scan.stack_blocks(params, cfg)
  # The stacked tree is exactly what the scan model declares.
  assert {k: v.shape for k, v in _flat(stacked).items()} == snapshot.expected_param_shapes(
      _scan(model))
  assert stacked["encoder"]["blocks"]["attn"]["qkv"]["kernel"].shape[0] == cfg.encoder.depth
  np.testing.assert_array_equal(stacked["info_sharing"]["self_attention_blocks"]["mlp"]["fc1"]
                                ["kernel"][2],
                                params["info_sharing"]["self_attention_blocks_2"]["mlp"]["fc1"]
                                ["kernel"])
  _assert_trees_equal(scan.stack_blocks(stacked, cfg), stacked)   # idempotent
  _assert_trees_equal(scan.unstack_blocks(stacked, cfg), params)
  _assert_trees_equal(scan.unstack_blocks(params, cfg), params)
  # A tree missing one block is not stacked: the merge then names the gap.
  partial = {**params, "info_sharing": {k: v for k, v in params["info_sharing"].items()
                                        if k != "self_attention_blocks_1"}}
  assert "self_attention_blocks_3" in scan.stack_blocks(partial, cfg)["info_sharing"]
  with pytest.raises(ValueError, match="depth"):
    scan.unstack_blocks(stacked, cfg.replace(encoder=cfg.encoder.__class__(
        **{**cfg.encoder.__dict__, "depth": 3})))


def _hook(c):
  # A channel-dependent scale: LayerNorm does not undo it, so outputs show where it was applied.
  w = jnp.linspace(0.5, 1.5, c)
  return lambda x: x * w.astype(x.dtype)


@pytest.mark.slow
def test_remat_scan_gradients_and_activation_hook_match_unrolled(official):
  """remat inside the scan, with the activation hook at every block boundary: forward and
  gradients equal the unrolled remat model's with the same hook."""
  model, params, io = official
  src, tgt = io["img1_uint8"][:1, :56, :70], io["img2_uint8"][:1, :56, :70]
  cfg = model.config.replace(remat=True)

  def hook_any(x):  # encoder (384) and fusion (96) tokens alike
    return _hook(x.shape[-1])(x)

  unrolled = ufm.UFM(cfg, activation_sharding=hook_any)
  scanned = ufm.UFM(cfg.replace(scan_blocks=True), activation_sharding=hook_any)
  plain = ufm.UFM(cfg)

  def loss(m, p):
    out = m.apply({"params": p}, src, tgt)
    return jnp.sum(out["flow"] ** 2) + jnp.sum(out["covisibility_logits"]), out

  (l_u, out_u), g_u = jax.jit(jax.value_and_grad(lambda p: loss(unrolled, p), has_aux=True))(
      params)
  (l_s, out_s), g_s = jax.jit(jax.value_and_grad(lambda p: loss(scanned, p), has_aux=True))(
      scan.stack_blocks(params, scanned.config))
  out_p = jax.jit(lambda p: plain.apply({"params": p}, src, tgt))(params)
  assert float(np.abs(np.asarray(out_p["flow"]) - np.asarray(out_u["flow"])).max()) > 1e-2
  np.testing.assert_allclose(np.asarray(out_s["flow"]), np.asarray(out_u["flow"]), atol=1e-4)
  np.testing.assert_allclose(float(l_s), float(l_u), rtol=1e-5)
  g_s = _flat(scan.unstack_blocks(jax.tree.map(np.asarray, g_s), scanned.config))
  g_u = _flat(jax.tree.map(np.asarray, g_u))
  assert set(g_s) == set(g_u)
  for k in g_u:
    scale = max(1e-3, float(np.abs(g_u[k]).max()))
    np.testing.assert_allclose(g_s[k], g_u[k], rtol=0, atol=1e-4 * scale, err_msg="/".join(k))
  # Blocks the encoder never runs (none here: taps [0, 1] of 2) and all fusion blocks train.
  assert float(np.abs(g_s[("info_sharing", "self_attention_blocks_3", "mlp", "fc2",
                           "kernel")]).max()) > 0


@pytest.mark.slow
def test_model_init_puts_any_layout_into_the_model(official, reference_dir, tmp_path):
  """Per-layer sources (snapshot, DINOv2 weights) into a scan template, and a scan run's
  checkpoint into a per-layer template."""
  model, params, _ = official
  m = _scan(model)
  template = trainer.random_params(m)
  got, rep = model_init.load_init_params(f"snapshot:{reference_dir / 'base'}", template, m.config)
  assert rep.left_at_init == [] and rep.unused == [] and rep.resized == []
  _assert_trees_equal(got, scan.stack_blocks(params, m.config))

  # DINOv2 weights in the original names (the fixture encoder's), as a safetensors file.
  state = keymap.state_dict_from_params({"encoder": params["encoder"]}, {})
  dino = {k[len("encoder.model."):]: v for k, v in state.items()}
  save_file(dino, str(tmp_path / "dinov2.safetensors"))
  got, rep = model_init.load_init_params(str(tmp_path / "dinov2.safetensors"), template, m.config)
  assert rep.source.startswith("dinov2:") and rep.unused == []
  assert not any(k.startswith("encoder/") for k in rep.left_at_init)
  _assert_trees_equal(got["encoder"], scan.stack_blocks(params, m.config)["encoder"])
  _assert_trees_equal(got["info_sharing"], template["info_sharing"])

  # A scan run's training checkpoint into the per-layer model.
  from ufm_jax.training import optim
  trained = jax.tree.map(lambda p: np.asarray(p) + 1.0, scan.stack_blocks(params, m.config))
  mngr = checkpoint.make_manager(tmp_path / "run", 1, 1, async_save=False)
  checkpoint.save(mngr, 5, optim.TrainState.create(trained, optim.optax.sgd(1.0)), force=True)
  mngr.wait_until_finished()
  mngr.close()
  got, rep = model_init.load_init_params(f"ckpt:{tmp_path / 'run'}", params, model.config)
  assert rep.left_at_init == [] and rep.unused == []
  _assert_trees_equal(got, jax.tree.map(lambda p: p + 1.0, params))
  # Without the config the layouts must already agree: nothing is silently loaded.
  _, rep = model_init.load_init_params(f"ckpt:{tmp_path / 'run'}", params)
  assert rep.unused and any("blocks_0" in k for k in rep.left_at_init)


@pytest.mark.slow
def test_workdir_of_a_scan_run_loads_as_a_usable_model(tmp_path):
  """model_io.load_workdir rebuilds the scan model from config.json; its stacked params run and
  equal the per-layer model on the unstacked params."""
  from ufm_jax.models import variants
  model = variants.build_model("fixture_small", scan_blocks=True)
  params = trainer.random_params(model, seed=3)
  manager = checkpoint.make_manager(tmp_path, save_interval_steps=1, keep=1, async_save=False)
  checkpoint.save(manager, 7, {"params": params, "step": 7}, force=True)
  manager.wait_until_finished()
  (tmp_path / "config.json").write_text(json.dumps(
      {"model_name": "fixture_small", "model": {"scan_blocks": True, "attention_impl": None}}))
  loaded_model, variables = model_io.load_model(tmp_path)
  loaded = variables["params"]
  assert loaded_model.config.scan_blocks
  x = np.random.default_rng(0).integers(0, 255, (1, 56, 70, 3), np.uint8)
  y = np.roll(x, 3, axis=2)
  out = jax.jit(loaded_model.apply)(variables, x, y)
  per_layer = loaded_model.clone(config=loaded_model.config.replace(scan_blocks=False))
  ref = jax.jit(per_layer.apply)({"params": scan.unstack_blocks(loaded, loaded_model.config)}, x, y)
  for k in ref:
    np.testing.assert_allclose(np.asarray(out[k]), np.asarray(ref[k]), atol=1e-5, err_msg=k)


def test_bf16_heads_close_to_float32(official):
  """head_dtype=bfloat16 runs the DPT heads in bf16. bf16 rounds to 2^-9 relative per op; the
  ~15 sequential convs of a head compound that to a few percent at worst (random-walk ~1.5%),
  so the relative L2 error of flow and logits is bounded by 5%."""
  model, params, io = official
  m16 = model.clone(config=model.config.replace(head_dtype="bfloat16"))
  fwd = lambda m: jax.jit(lambda p, a, b: m.apply(  # noqa: E731
      {"params": p}, a, b, mutable=["intermediates"]))
  ref, _ = fwd(model)(params, io["img1_uint8"], io["img2_uint8"])
  out, state = fwd(m16)(params, io["img1_uint8"], io["img2_uint8"])
  assert state["intermediates"]["head1_0_0"]["refinenet1_out"][0].dtype == jnp.bfloat16
  assert state["intermediates"]["uncertainty_head_0_0"]["layer0"][0].dtype == jnp.bfloat16
  for k in ("flow", "covisibility_logits", "covisibility"):
    assert out[k].dtype == jnp.float32, k
    a, b = np.asarray(ref[k], np.float64), np.asarray(out[k], np.float64)
    rel = np.linalg.norm(b - a) / np.linalg.norm(a)
    assert 0 < rel < 0.05, (k, rel)   # > 0: not float32 in disguise


def test_attention_implementation_by_platform(monkeypatch):
  choose = layers.attention_implementation
  assert choose(None, jnp.bfloat16, 64) == "auto"         # this CPU: cpu/xla per platform
  assert choose("cudnn", jnp.float32, 64) == "cudnn"      # forced
  assert choose("xla", jnp.bfloat16, 64) == "xla"
  assert choose("cpu", jnp.bfloat16, 64) == "cpu"
  with pytest.raises(ValueError, match="attention_impl"):
    choose("flash", jnp.bfloat16, 64)
  monkeypatch.setattr(layers.jax, "default_backend", lambda: "gpu")
  assert choose(None, jnp.bfloat16, 64) == "cudnn"
  assert choose("auto", jnp.float16, 128) == "cudnn"
  assert choose(None, jnp.float32, 64) == "auto"          # cuDNN flash takes bf16/f16 only
  assert choose(None, jnp.bfloat16, 100) == "auto"        # head dim not a multiple of 8
  assert choose(None, jnp.bfloat16, 160) == "auto"
  with pytest.raises(ValueError, match="attention_impl"):
    ufm.UFMConfig(attention_impl="flash")
