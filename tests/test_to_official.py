"""Export to official snapshots (`ufm_jax.save_official`, `python -m ufm_jax to-official`): the
exact inverse of the loader on the public fixtures, on other structures, and for a trained model."""

import dataclasses
import json
import pathlib
import struct

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest
from safetensors.numpy import load_file

import ufm_jax
from ufm_jax import testing
from ufm_jax.runtime import checkpoint
from ufm_jax.tools import cli
from ufm_jax.training import losses, optim, trainer
from ufm_jax.data import synthetic
from ufm_jax.models import dinov2, ufm
from ufm_jax.official import config as official_config
from ufm_jax.official import keymap, snapshot


def _header_metadata(path):
  """The safetensors header's __metadata__ (the alias -> kept-name map save_pretrained writes)."""
  raw = pathlib.Path(path).read_bytes()
  n = struct.unpack("<Q", raw[:8])[0]
  return json.loads(raw[8:8 + n]).get("__metadata__")


def _assert_same_tensors(got_path, want):
  got = load_file(str(got_path))
  assert sorted(got) == sorted(want)
  for k, v in want.items():
    assert got[k].dtype == np.float32 and got[k].shape == v.shape, k
    assert got[k].tobytes() == np.ascontiguousarray(v, np.float32).tobytes(), k  # bitwise


@pytest.mark.parametrize("kind", ["base", "refine"])
def test_fixture_snapshot_round_trip(reference_dir, tmp_path, kind):
  """official snapshot -> load_official -> save_official gives back the same files."""
  src = reference_dir / kind
  model, variables = snapshot.load_official(src)
  notes = ufm_jax.save_official(model, variables, tmp_path / "out", source=str(src))
  out = tmp_path / "out"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp folder left
  _assert_same_tensors(out / "model.safetensors", load_file(str(src / "model.safetensors")))
  # save_pretrained's file: the de-duplicated names of the shared DPT convolutions in metadata
  meta = _header_metadata(out / "model.safetensors")
  assert meta == _header_metadata(src / "model.safetensors") and len(meta) == 16
  # byte for byte: the header as the source file has it (its alias order), the same data
  assert (out / "model.safetensors").read_bytes() == (src / "model.safetensors").read_bytes()
  assert meta["head1.0.0.scratch.layer1_rn.weight"] == "head1.0.0.input_process.0.1.weight"
  # config.json: the same kwargs, values and types, written as save_pretrained writes it
  assert json.loads((out / "config.json").read_text()) == json.loads((src / "config.json").read_text())
  assert (out / "config.json").read_text() == (src / "config.json").read_text()
  card = (out / "README.md").read_text()
  assert str(src) in card and f"ufm_jax {ufm_jax.__version__}" in card
  assert "config.json: the source snapshot's, key for key" in notes
  unet = [n for n in notes if "U-Net widths" in n]   # the refine fixture's small U-Net
  assert len(unet) == (kind == "refine") and (not unet or "[8, 16, 32, 64]" in unet[0])


# Official names and torch layouts that the exported file must hold, written out from the module
# definitions (timm / DINOv2 hub / UniCeption / ufm.py), not from the key map.
EXPECTED_TENSORS = {
    "registers_layerscale_qknorm": {
        "encoder.model.register_tokens": (1, 4, 384),
        "encoder.model.patch_embed.proj.weight": (384, 3, 14, 14),   # Conv2d OIHW
        "info_sharing.proj_embed.weight": (64, 384),                  # Linear [out, in]
        "info_sharing.self_attention_blocks.0.attn.q_norm.weight": (32,),  # head dim 64 / 2
        "info_sharing.self_attention_blocks.2.ls2.gamma": (64,),
        "head1.0.1.conv1.weight": (12, 16, 3, 3),                     # processor hidden dims
    },
    "identity_proj_coords": {"encoder.model.blocks.1.mlp.fc1.weight": (1536, 384)},
    "giant_swiglu": {
        # SwiGLUFFNFused: hidden (int(4 * 1536 * 2 / 3) + 7) // 8 * 8 = 4096
        "encoder.model.blocks.0.mlp.w12.weight": (8192, 1536),
        "encoder.model.blocks.0.mlp.w3.weight": (1536, 4096),
        "encoder.model.blocks.0.ls1.gamma": (1536,),
    },
    "ufm980": {"encoder.model.pos_embed": (1, 1 + 37 * 37, 1024),
               "info_sharing.self_attention_blocks.11.mlp.fc2.weight": (32, 128)},
    "refine_window5": {
        "unet_feature.ups.0.weight": (32, 16, 2, 2),                  # ConvTranspose2d [in, out]
        "unet_feature.downs.0.conv.0.weight": (8, 3, 3, 3),
        "classification_head.mlp.fc1.weight": (624, 416),             # (384 + 32) * 1.5
        "classification_head.linear.weight": (8 * 14 * 14, 416, 1, 1),
        "classification_bias": (25,),
    },
}


@pytest.mark.parametrize("name", sorted(testing.STRUCTURES))
def test_round_trip_other_structures(tmp_path, name):
  cfg = testing.STRUCTURES[name]
  model = ufm.model_from_config(cfg)
  params = testing.perturbed_params(model, 5)
  # the snapshot as a saver without de-duplication writes it: every name of a shared tensor
  kept = keymap.state_dict_from_params(params, official_config.ufm_buffers(cfg))
  aliases = {a: k for k in kept for a in keymap.alias_keys(k)}
  assert aliases and all(".scratch.layer" in a for a in aliases)
  state = dict(kept, **{a: kept[k] for a, k in aliases.items()})
  config = official_config.official_config_dict(cfg)
  snap = testing.write_snapshot(tmp_path / "snap", config, state)

  loaded_model, loaded_variables = snapshot.load_official(snap)
  ufm_jax.save_official(loaded_model, loaded_variables, tmp_path / "out")
  out = tmp_path / "out"
  _assert_same_tensors(out / "model.safetensors", kept)
  assert _header_metadata(out / "model.safetensors") == aliases
  assert json.loads((out / "config.json").read_text()) == config
  for key, shape in EXPECTED_TENSORS[name].items():
    assert kept[key].shape == shape, key
  if name == "identity_proj_coords":
    assert not any(k.startswith("info_sharing.proj_embed") for k in kept)
  if name == "ufm980":
    assert config["inference_resolution"] == [980, 742]   # official order (W, H)
  # and the export reads back to the model and params it came from
  back_model, back_variables = snapshot.load_official(out)
  back_params = back_variables["params"]
  assert back_model.config == cfg
  jax.tree.map(np.testing.assert_array_equal, back_params, params)


# --------------------------------------------------------------------------- a trained model


def _shift_batch(seeds, size=56):
  """Pairs of configs/synthetic.py's default task (`pairs=shift`, max_shift 10)."""
  scfg = synthetic.SyntheticConfig(size=(size, size), pair_type="shift", max_shift=10)
  samples = [synthetic.generate_pair(s, scfg, directions=(0,))[0] for s in seeds]
  keys = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")
  return {k: jnp.asarray(np.stack([s[k] for s in samples])) for k in keys}


@pytest.mark.slow
def test_trained_workdir_exports_and_loads_back(tmp_path, capsys):
  """A few optimizer steps on the synthetic task, checkpointed as train.py does; `to-official`
  of the workdir (newest step, and --step) loads back with load_official to the same outputs."""
  model = testing.official_small_model()
  # Only the DPT processors are trained (the rest enters through stop_gradient, as train.py's
  # step does for frozen params): a full backward pass takes minutes to compile on 2 CPU cores.
  ocfg = ml_collections.ConfigDict({"lr": {"default": 1e-3}, "warmup_frac": 0.0,
                                    "grad_clip_norm": 1.0,
                                    "trainable": r"^(head1_0_1|uncertainty_head_0_1)/"})
  init = trainer.random_params(model, 0)
  tx, labels, _ = optim.make_optimizer(ocfg, init, total_steps=3)
  state = optim.TrainState.create(init, tx)

  recipe = losses.Recipe((("robust_epe", losses.FlowRegression(alpha=1.0, c=0.01)),
                          ("covisibility_ce", losses.CovisibilityBCE())))

  @jax.jit
  def train_step(state, batch):
    def loss_fn(trainable, frozen):   # the synthetic config's loss (loss=l1: alpha 1, c 0.01)
      p = optim.merge_params(trainable, jax.lax.stop_gradient(frozen))
      out = model.apply({"params": p}, batch["image0"], batch["image1"])
      return recipe(out, batch)[0]
    trainable, frozen = optim.split_trainable(state.params, labels)
    loss, g = jax.value_and_grad(loss_fn)(trainable, frozen)
    grads = optim.merge_params(g, jax.tree.map(jnp.zeros_like, frozen))
    return optim.apply_gradients(state, grads, loss, tx)[0]

  workdir = tmp_path / "wd"
  manager = checkpoint.make_manager(workdir, save_interval_steps=1, keep=3, async_save=False)
  trained = {}
  for step in (1, 2, 3):
    state = train_step(state, _shift_batch([2 * step, 2 * step + 1]))
    checkpoint.save(manager, step, state, force=True)
    trained[step] = jax.tree.map(np.asarray, state.params)
  manager.wait_until_finished()
  (workdir / "config.json").write_text(json.dumps(
      {"model_fn": "ufm_jax.testing:official_small_model", "model": {}}))
  assert int(state.skipped) == 0

  assert cli.main(["to-official", str(workdir), str(tmp_path / "latest")]) == 0
  printed = capsys.readouterr().out
  assert "step 3" in printed and "pretrained_checkpoint_path = null" in printed
  assert cli.main(["to-official", str(workdir), str(tmp_path / "s2"), "--step", "2"]) == 0
  capsys.readouterr()
  assert cli.main(["to-official", str(workdir), str(tmp_path / "s7"), "--step", "7"]) == 2
  assert "no checkpoint step 7" in capsys.readouterr().err and not (tmp_path / "s7").exists()
  assert "Step: 3" in (tmp_path / "latest" / "README.md").read_text()
  assert str(workdir) in (tmp_path / "latest" / "README.md").read_text()

  held_out = _shift_batch([1000, 1001])
  predict = jax.jit(lambda m, p: m.apply({"params": p}, held_out["image0"], held_out["image1"]),
                    static_argnums=0)
  for folder, step in (("latest", 3), ("s2", 2)):
    back_model, back_variables = ufm_jax.load_official(tmp_path / folder)
    back_params = back_variables["params"]
    assert back_model.config == model.config
    jax.tree.map(np.testing.assert_array_equal, back_params, trained[step])
    want = predict(model, trained[step])
    got = predict(back_model, back_params)
    for k in ("flow", "covisibility", "covisibility_logits"):
      np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(want[k]))
  # the steps differ, so the two exports are not the same snapshot
  assert not np.array_equal(trained[2]["head1_0_1"]["conv2_2"]["bias"],
                            trained[3]["head1_0_1"]["conv2_2"]["bias"])


# --------------------------------------------------------------------------- errors, options


@pytest.fixture(scope="module")
def small():
  model = testing.official_small_model()
  return model, testing.perturbed_params(model, 0)


def test_unrepresentable_models_are_refused(tmp_path, small):
  # an encoder width that no DINOv2 hub model has (the `tiny`/`synth` training variants)
  cfg = testing.official_small_config(
      encoder=dinov2.DinoV2Config(embed_dim=64, depth=1, num_heads=2, indices=(0,)))
  with pytest.raises(ValueError, match="not a DINOv2 hub size"):
    ufm_jax.save_official(ufm.model_from_config(cfg), {}, tmp_path / "a")
  # a value config.json cannot carry (the loader ties the interpolation offset to registers)
  model, params = small
  cfg = model.config.replace(
      encoder=dataclasses.replace(model.config.encoder, interpolate_offset=0.0))
  with pytest.raises(ValueError, match=r"encoder\.interpolate_offset=0\.0"):
    ufm_jax.save_official(ufm.model_from_config(cfg), params, tmp_path / "b")
  assert not list(tmp_path.iterdir())


def test_jax_only_options_are_dropped_and_listed(tmp_path, small):
  model, params = small
  cfg = model.config.replace(dtype="bfloat16", remat=True)
  # (the variables dict that model.apply takes is accepted too)
  notes = ufm_jax.save_official(ufm.model_from_config(cfg), {"params": params}, tmp_path / "out")
  assert "not written (JAX-only option): dtype='bfloat16'" in notes
  assert "not written (JAX-only option): remat=True" in notes
  back, _ = ufm_jax.load_official(tmp_path / "out")
  assert back.config == model.config   # float32, no remat: what a snapshot describes


def test_never_overwrites_and_leaves_nothing_half_written(tmp_path, small, monkeypatch):
  model, params = small
  (tmp_path / "exists").mkdir()
  with pytest.raises(FileExistsError):
    ufm_jax.save_official(model, params, tmp_path / "exists")
  import safetensors.numpy

  def fail(*a, **k):
    raise OSError("disk full")

  monkeypatch.setattr(safetensors.numpy, "save_file", fail)
  with pytest.raises(OSError, match="disk full"):
    ufm_jax.save_official(model, params, tmp_path / "new")
  assert sorted(p.name for p in tmp_path.iterdir()) == ["exists"]


def test_cli_convert_then_to_official(reference_dir, tmp_path, capsys):
  """The command-line round trip: snapshot -> `convert` -> `to-official` -> the same file."""
  src = reference_dir / "base"
  assert cli.main(["convert", str(src), str(tmp_path / "ckpt")]) == 0
  assert cli.main(["to-official", str(tmp_path / "ckpt"), str(tmp_path / "out")]) == 0
  _assert_same_tensors(tmp_path / "out" / "model.safetensors",
                       load_file(str(src / "model.safetensors")))
  assert (tmp_path / "out" / "config.json").read_text() == (src / "config.json").read_text()
  capsys.readouterr()
  assert cli.main(["to-official", str(tmp_path / "ckpt"), str(tmp_path / "out")]) == 2
  assert "already exists" in capsys.readouterr().err
  assert cli.main(["to-official", str(tmp_path / "ckpt"), str(tmp_path / "o2"), "--step", "1"]) == 2
  assert "not a train.py workdir" in capsys.readouterr().err
