"""model_init pieces: DINOv2 (HF safetensors / original .pth) key maps, merge report, pos-embed
resize; the orbax manager with a grain iterator (save, keep-K, restore mid-stream)."""

import logging

import grain
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from safetensors.numpy import save_file

from ufm_jax.runtime import checkpoint
from ufm_jax.training import model_init, optim
from ufm_jax.models import dinov2
from ufm_jax.official import dinov2_weights
from ufm_jax import testing


def test_hf_dinov2_to_original_names(tmp_path):
  sd = testing.hf_dinov2()
  save_file(sd, str(tmp_path / "model.safetensors"))
  orig = dinov2_weights.read_weights(tmp_path)  # the folder, as downloaded from the Hub
  expected = {"cls_token", "mask_token", "pos_embed", "patch_embed.proj.weight",
              "patch_embed.proj.bias", "norm.weight", "norm.bias"}
  for i in range(2):
    expected |= {f"blocks.{i}.{n}" for n in (
        "norm1.weight", "norm1.bias", "norm2.weight", "norm2.bias", "attn.qkv.weight",
        "attn.qkv.bias", "attn.proj.weight", "attn.proj.bias", "ls1.gamma", "ls2.gamma",
        "mlp.fc1.weight", "mlp.fc1.bias", "mlp.fc2.weight", "mlp.fc2.bias")}
  assert set(orig) == expected
  # The original fused qkv Linear is [q; k; v] stacked on the output dimension.
  q = sd["encoder.layer.1.attention.attention.query.weight"]
  k = sd["encoder.layer.1.attention.attention.key.weight"]
  v = sd["encoder.layer.1.attention.attention.value.weight"]
  np.testing.assert_array_equal(orig["blocks.1.attn.qkv.weight"][:8], q)
  np.testing.assert_array_equal(orig["blocks.1.attn.qkv.weight"][8:16], k)
  np.testing.assert_array_equal(orig["blocks.1.attn.qkv.weight"][16:], v)
  np.testing.assert_array_equal(orig["blocks.0.ls2.gamma"], sd["encoder.layer.0.layer_scale2.lambda1"])
  np.testing.assert_array_equal(orig["pos_embed"], sd["embeddings.position_embeddings"])


def test_dinov2_errors_name_the_problem(tmp_path):
  sd = testing.hf_dinov2()
  del sd["encoder.layer.0.attention.attention.key.weight"]
  save_file(sd, str(tmp_path / "x.safetensors"))
  with pytest.raises(ValueError, match="incomplete q/k/v"):
    dinov2_weights.read_weights(tmp_path / "x.safetensors")
  (tmp_path / "empty").mkdir()
  with pytest.raises(FileNotFoundError, match="no \\*.safetensors"):
    dinov2_weights.read_weights(tmp_path / "empty")


def test_original_pth_needs_torch_or_reads_it(tmp_path):
  torch = pytest.importorskip("torch")
  sd = {"blocks.0.attn.qkv.weight": np.ones((6, 2), np.float32), "cls_token": np.zeros((1, 1, 2),
                                                                                     np.float32)}
  torch.save({k: torch.from_numpy(v) for k, v in sd.items()}, tmp_path / "d.pth")
  got = dinov2_weights.read_weights(tmp_path / "d.pth")
  np.testing.assert_array_equal(got["blocks.0.attn.qkv.weight"], 1.0)


def test_resize_pos_embed_keeps_cls_and_is_bicubic_on_smooth_grid():
  g, d = 4, 3
  yy, xx = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
  grid = np.stack([np.ones((g, g)) * 5.0, 0 * xx, 0 * yy], -1).reshape(1, g * g, d)
  pe = np.concatenate([np.full((1, 1, d), 7.0), grid], 1).astype(np.float32)
  out = dinov2.resize_pos_embed(pe, (1, 1 + 8 * 8, d))
  assert out.shape == (1, 65, 3)
  np.testing.assert_array_equal(out[0, 0], 7.0)
  np.testing.assert_allclose(out[0, 1:, 0], 5.0, rtol=1e-6)  # constants stay constant


def test_merge_report():
  template = {"enc": {"pos_embed": jnp.zeros((1, 1 + 4, 2)), "w": jnp.zeros((2, 2))},
              "head": {"b": jnp.zeros((3,))}}
  loaded = {"enc/pos_embed": np.ones((1, 1 + 9, 2), np.float32), "enc/w": np.full((2, 2), 2.0),
            "extra/x": np.zeros(1)}
  params, rep = model_init.merge_into(template, loaded, "test")
  assert rep.loaded == ["enc/w"] and rep.left_at_init == ["head/b"] and rep.unused == ["extra/x"]
  assert rep.resized == ["enc/pos_embed (1, 10, 2)->(1, 5, 2)"]
  np.testing.assert_allclose(params["enc"]["pos_embed"], 1.0, rtol=1e-6)
  np.testing.assert_array_equal(params["enc"]["w"], 2.0)
  with pytest.raises(ValueError, match="enc/w: checkpoint \\(3,\\) vs model \\(2, 2\\)"):
    model_init.merge_into(template, {"enc/w": np.zeros(3)}, "test")


def _iterator(n=40):
  return iter(grain.MapDataset.range(n).map(lambda i: {"x": np.int64(i)})
              .batch(2).to_iter_dataset())


def test_manager_saves_state_and_iterator_keeps_last_k(tmp_path):
  params = {"w": jnp.arange(4.0)}
  tx = optim.optax.adam(1e-3)
  state = optim.TrainState.create(params, tx)
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=2, keep=2)
  it = _iterator()
  seen = []
  for step in range(1, 8):
    seen.append(int(next(it)["x"][0]))
    state = state.replace(step=jnp.int32(step), params={"w": params["w"] + step})
    checkpoint.save(mngr, step, state, it)
  mngr.wait_until_finished()
  assert checkpoint.checkpoint_steps(tmp_path) == [4, 6]
  # Restore into a fresh iterator: the stream continues after the saved step's batch.
  it2 = _iterator()
  abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype,
                                                         sharding=jax.sharding.SingleDeviceSharding(
                                                             jax.devices()[0])), state)
  restored, step = checkpoint.restore_latest(mngr, abstract, it2)
  assert step == 6 and int(restored.step) == 6
  np.testing.assert_array_equal(restored.params["w"], np.arange(4.0) + 6)
  assert int(next(it2)["x"][0]) == 12  # batches 0..5 consumed (x = 0, 2, ..., 10)
  mngr.close()
  raw, s = checkpoint.read_state_numpy(tmp_path)
  assert s == 6 and isinstance(raw["params"]["w"], np.ndarray)


def test_reading_a_workdir_logs_no_missing_metadata_warning(tmp_path, caplog):
  """infer/evaluate read train.py's checkpoints (state + data items, written by make_manager):
  no "Metadata file does not exist: .../_CHECKPOINT_METADATA" warning, the state comes back."""
  state = optim.TrainState.create({"w": jnp.arange(3.0)}, optim.optax.adam(1e-3))
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=1, keep=1, async_save=False)
  it = _iterator()
  next(it)
  checkpoint.save(mngr, 2, state.replace(step=jnp.int32(2)), it, force=True)
  mngr.wait_until_finished()
  mngr.close()
  assert (tmp_path / "checkpoints" / "2" / "data").is_dir()
  caplog.clear()
  with caplog.at_level(logging.INFO):
    raw, step = checkpoint.read_state_numpy(tmp_path)
  assert step == 2 and int(raw["step"]) == 2
  np.testing.assert_array_equal(raw["params"]["w"], np.arange(3.0))
  noisy = [r.getMessage() for r in caplog.records
           if r.levelno >= logging.WARNING or "_CHECKPOINT_METADATA" in r.getMessage()]
  assert noisy == []
