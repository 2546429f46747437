"""Official-checkpoint loader: key map, error reporting, other structures, convert CLI."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest
from safetensors.numpy import load_file

from ufm_jax import testing
from ufm_jax.runtime import model_io
from ufm_jax.models import dpt, ufm
from ufm_jax.official import dinov2_weights
from ufm_jax.official import config as official_config
from ufm_jax.official import keymap, snapshot

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fixture_dir(reference_dir):
  return reference_dir / "base"


@pytest.fixture(scope="module")
def loaded(fixture_dir):
  return snapshot.load_official(fixture_dir)


def _snapshot(tmp_path, config, state):
  return testing.write_snapshot(tmp_path / "snap", config, state)


def _fixture_files(fixture_dir):
  return (json.loads((fixture_dir / "config.json").read_text()),
          load_file(str(fixture_dir / "model.safetensors")))


def test_structure_from_config_and_shapes(loaded, fixture_dir):
  model, variables = loaded
  params = variables["params"]
  cfg = model.config
  # config.json cannot say the depth after keep_first_n_layers: it comes from the weights.
  assert cfg.encoder.depth == 2 and cfg.encoder.embed_dim == 384 and cfg.encoder.pos_grid == 37
  assert cfg.encoder.num_register_tokens == 0 and cfg.encoder.interpolate_offset == 0.1
  assert cfg.info_sharing.indices == (1, 2) and cfg.info_sharing.depth == 4
  assert cfg.inference_resolution == (168, 224)  # (H, W) from the official (W, H)
  assert cfg.flow_adaptor.base_shape == (120, 160)
  # every tensor of the file is a parameter or a checked buffer: counts must agree
  state = load_file(str(fixture_dir / "model.safetensors"))
  n_file = sum(v.size for k, v in state.items() if k not in official_config.ufm_buffers(cfg))
  n_params = sum(v.size for v in jax.tree.leaves(params))
  assert n_file == n_params


def test_key_map_names():
  # names from the official modules (timm/DINOv2/UniCeption), written out independently
  cases = {
      "encoder.model.blocks.3.attn.qkv.weight": ("encoder", "blocks_3", "attn", "qkv", "kernel"),
      "encoder.model.norm.weight": ("encoder", "norm", "scale"),
      "encoder.model.register_tokens": ("encoder", "register_tokens"),
      "info_sharing.self_attention_blocks.11.ls1.gamma":
          ("info_sharing", "self_attention_blocks_11", "ls1", "gamma"),
      "head1.0.0.scratch.layer2_rn.weight": ("head1_0_0", "input_process_1_1", "kernel"),
      "head1.0.0.scratch.layer_rn.3.weight": ("head1_0_0", "input_process_3_1", "kernel"),
      "uncertainty_head.0.1.conv2.2.bias": ("uncertainty_head_0_1", "conv2_2", "bias"),
  }
  for key, path in cases.items():
    ndim = 1 if key.endswith(("norm.weight", "bias", "gamma")) else 3 if "tokens" in key else 2
    assert keymap.torch_key_to_path(key, ndim) == path, key


def test_layouts():
  w = np.arange(2 * 3 * 4 * 5, dtype=np.float32).reshape(2, 3, 4, 5)
  # Conv2d OIHW -> HWIO
  got = keymap.torch_to_flax_array("x.conv1.weight", w)
  assert got.shape == (4, 5, 3, 2) and got[1, 2, 0, 1] == w[1, 0, 1, 2]
  # ConvTranspose2d [in, out, kh, kw] -> [kh, kw, in, out]
  got = keymap.torch_to_flax_array("head1.0.0.input_process.0.0.1.weight", w)
  assert got.shape == (4, 5, 2, 3) and got[1, 2, 0, 1] == w[0, 1, 1, 2]
  lin = np.arange(6, dtype=np.float32).reshape(2, 3)
  assert keymap.torch_to_flax_array("a.fc1.weight", lin).shape == (3, 2)


def test_conv_transpose_matches_definition():
  # torch ConvTranspose2d(k=s): out[o, i*s+a, j*s+b] = sum_c x[c, i, j] W[c, o, a, b] + bias[o]
  rng = np.random.default_rng(0)
  x = rng.normal(size=(1, 2, 3, 4)).astype(np.float32)  # NHWC
  wt = rng.normal(size=(4, 5, 2, 2)).astype(np.float32)  # torch [in, out, kh, kw]
  b = rng.normal(size=(5,)).astype(np.float32)
  ref = np.zeros((1, 4, 6, 5), np.float32)
  for i in range(2):
    for j in range(3):
      for a in range(2):
        for bb in range(2):
          ref[0, 2 * i + a, 2 * j + bb] = x[0, i, j] @ wt[:, :, a, bb] + b
  mod = dpt.ConvTranspose(5, 2)
  params = {"kernel": keymap.torch_to_flax_array("input_process.1.0.1.weight", wt), "bias": b}
  got = mod.apply({"params": params}, x)
  np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-6, atol=1e-6)


def test_deduplicated_aliases_accepted(tmp_path, fixture_dir, loaded):
  cj, state = _fixture_files(fixture_dir)
  # a state dict saved without safetensors' de-duplication has all three names of layer{k}_rn
  for head in ("head1", "uncertainty_head"):
    for k in range(4):
      w = state[f"{head}.0.0.input_process.{k}.1.weight"]
      state[f"{head}.0.0.scratch.layer{k + 1}_rn.weight"] = w.copy()
      state[f"{head}.0.0.scratch.layer_rn.{k}.weight"] = w.copy()
  _, params = snapshot.load_official(_snapshot(tmp_path, cj, state))
  jax.tree.map(np.testing.assert_array_equal, params, loaded[1])
  # ... but the aliases must agree
  state["head1.0.0.scratch.layer_rn.2.weight"] = state["head1.0.0.scratch.layer_rn.2.weight"] + 1
  with pytest.raises(ValueError, match=r"head1\.0\.0\.scratch\.layer_rn\.2\.weight: differs"):
    snapshot.load_official(_snapshot(tmp_path, cj, state))


def test_tampered_checkpoint_lists_every_problem(tmp_path, fixture_dir):
  cj, state = _fixture_files(fixture_dir)
  del state["info_sharing.self_attention_blocks.1.mlp.fc2.bias"]
  state["encoder.model.mask_token"] = np.zeros((1, 384), np.float32)
  state["head1.0.1.conv1.weight"] = np.zeros((24, 48, 5, 5), np.float32)
  state["info_sharing.view_pos_table"] = state["info_sharing.view_pos_table"] + 0.5
  d = _snapshot(tmp_path, cj, state)
  with pytest.raises(ValueError) as e:
    snapshot.load_official(d)
  msg = str(e.value)
  assert "model.safetensors" in msg
  assert "missing (1)" in msg and "info_sharing.self_attention_blocks.1.mlp.fc2.bias" in msg
  assert "unexpected (1)" in msg and "encoder.model.mask_token" in msg
  assert "mis-shaped (1)" in msg and "head1.0.1.conv1.weight" in msg and "(5, 5, 48, 24)" in msg
  assert "info_sharing.view_pos_table" in msg


def test_config_errors(tmp_path, fixture_dir):
  cj, state = _fixture_files(fixture_dir)
  bad = dict(cj, encoder_kwargs=dict(cj["encoder_kwargs"], keep_first_n_layers=3))
  with pytest.raises(ValueError, match="keep_first_n_layers=3.*2 encoder blocks"):
    snapshot.load_official(_snapshot(tmp_path, bad, state))
  bad = dict(cj, info_sharing_str="alternating_attention")
  with pytest.raises(ValueError, match="info_sharing_str"):
    snapshot.load_official(_snapshot(tmp_path, bad, state))
  with pytest.raises(FileNotFoundError, match="config.json"):
    snapshot.load_official(tmp_path / "nowhere")


# --------------------------------------------------------------------------- unseen structures


@pytest.mark.parametrize("name", ["identity_proj_coords", "registers_layerscale_qknorm"])
def test_loader_on_unseen_structure(tmp_path, name):
  """Flax params -> torch-named safetensors + official config.json -> load_official -> same
  model, same outputs. The loader has no fixture-specific constants."""
  cfg = testing.STRUCTURES[name]
  model = ufm.model_from_config(cfg)
  params = testing.perturbed_params(model, 3)
  state = keymap.state_dict_from_params(params, official_config.ufm_buffers(cfg))
  if cfg.encoder.num_register_tokens:
    assert state["encoder.model.register_tokens"].shape == (1, 4, 384)
  if cfg.info_sharing.qk_norm:
    assert "info_sharing.self_attention_blocks.0.attn.q_norm.weight" in state
    assert "info_sharing.self_attention_blocks.2.ls2.gamma" in state
  if cfg.info_sharing.input_embed_dim == cfg.info_sharing.dim:
    assert not any(k.startswith("info_sharing.proj_embed") for k in state)
  d = _snapshot(tmp_path, official_config.official_config_dict(cfg), state)
  model2, variables2 = snapshot.load_official(d)
  assert model2.config == cfg and set(variables2) == {"params"}
  jax.tree.map(np.testing.assert_array_equal, variables2["params"], params)
  rng = np.random.default_rng(0)
  h, w = cfg.inference_resolution
  a = rng.integers(0, 256, (2, h, w, 3), dtype=np.uint8)
  b = rng.integers(0, 256, (2, h, w, 3), dtype=np.uint8)
  assert model2 == model  # the module is fully determined by its config
  out = jax.jit(model2.apply)(variables2, a, b)
  assert out["flow"].shape == (2, h, w, 2) and out["covisibility"].shape == (2, h, w)
  for k in ("flow", "covisibility", "covisibility_logits"):
    assert np.isfinite(np.asarray(out[k])).all()


# --------------------------------------------------------------------------- orbax format, CLI


def test_convert_cli_round_trip(tmp_path, fixture_dir, loaded):
  out = tmp_path / "ckpt"
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
             JAX_PLATFORMS="cpu")
  res = subprocess.run([sys.executable, "-m", "ufm_jax", "convert", str(fixture_dir), str(out)],
                       capture_output=True, text=True, env=env, timeout=300)
  assert res.returncode == 0, res.stderr[-3000:]
  assert (out / model_io.CONFIG_FILE).is_file()
  assert [p.name for p in tmp_path.iterdir()] == ["ckpt"]  # no temp folder left behind
  model, variables = model_io.load_converted(out)
  assert model.config == loaded[0].config
  jax.tree.map(np.testing.assert_array_equal, variables, loaded[1])
  import ufm_jax
  model_b, _ = ufm_jax.load(out)  # the public entry point; same config + params => same outputs
  assert model_b == loaded[0]
  # an existing output folder is never overwritten
  with pytest.raises(FileExistsError):
    model_io.save(out, *loaded)


def test_load_errors(tmp_path):
  with pytest.raises(FileNotFoundError, match="model_config.json"):
    model_io.load_converted(tmp_path)
  (tmp_path / model_io.CONFIG_FILE).write_text(json.dumps({"class": "Nope", "config": {}}))
  with pytest.raises(ValueError, match="unknown model class 'Nope'"):
    model_io.load_converted(tmp_path)


def test_truncated_safetensors_says_so(fixture_dir, tmp_path):
  snap = tmp_path / "snap"
  snap.mkdir()
  (snap / "config.json").write_bytes((fixture_dir / "config.json").read_bytes())
  data = (fixture_dir / "model.safetensors").read_bytes()
  (snap / "model.safetensors").write_bytes(data[:len(data) // 3])
  with pytest.raises(ValueError, match=rf"looks truncated: its header describes {len(data):,} "
                                       rf"bytes, the file has {len(data) // 3:,}"):
    snapshot.load_official(snap)
  # DINOv2 weights for model_init are read by the same reader.
  with pytest.raises(ValueError, match=rf"model.safetensors: cannot read safetensors .*looks "
                                       rf"truncated: its header describes {len(data):,} bytes"):
    dinov2_weights.read_weights(snap / "model.safetensors")
