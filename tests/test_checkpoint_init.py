"""model_init end to end on real UFM structures: DINOv2 (HF safetensors) into the encoder of a
tiny UFM, the official fixture snapshot, and a training checkpoint."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from safetensors.numpy import save_file

from ufm_jax.models import variants as model_variants
from ufm_jax.runtime import checkpoint
from ufm_jax.training import model_init, optim
from ufm_jax.models import ufm

from ufm_jax import testing


@pytest.fixture(scope="module")
def tiny():
  model = ufm.model_from_config(model_variants.get("tiny"))
  x = jnp.zeros((1, 28, 28, 3), jnp.uint8)
  params = jax.jit(lambda r: model.init(r, x, x)["params"])(jax.random.PRNGKey(0))
  return model, jax.tree.map(np.asarray, params)


@pytest.mark.slow
def test_dinov2_hf_into_ufm_encoder(tmp_path, tiny):
  _, template = tiny
  enc = template["encoder"]
  dim = enc["cls_token"].shape[-1]
  depth = sum(k.startswith("blocks_") for k in enc)
  sd = testing.hf_dinov2(depth=depth, dim=dim, grid=4, seed=1)
  save_file(sd, str(tmp_path / "model.safetensors"))
  (tmp_path / "config.json").write_text('{"model_type": "dinov2"}')
  params, rep = model_init.load_init_params(str(tmp_path), template)  # kind guessed: dinov2
  assert rep.source.startswith("dinov2:")
  assert rep.unused == []
  assert [r.split(" ")[0] for r in rep.resized] == ["encoder/pos_embed"]
  assert all(k.startswith("encoder/") for k in rep.loaded)
  n_enc = len(model_init.flatten({"encoder": enc}))
  assert len(rep.loaded) + len(rep.resized) == n_enc
  assert rep.left_at_init and not any(k.startswith("encoder/") for k in rep.left_at_init)
  # Linear: torch [out, in] -> flax kernel [in, out]; qkv = [q; k; v] on the output axis.
  q = sd["encoder.layer.0.attention.attention.query.weight"]
  np.testing.assert_array_equal(params["encoder"]["blocks_0"]["attn"]["qkv"]["kernel"][:, :dim], q.T)
  np.testing.assert_array_equal(params["encoder"]["blocks_1"]["ls2"]["gamma"],
                                sd["encoder.layer.1.layer_scale2.lambda1"])
  np.testing.assert_array_equal(params["encoder"]["cls_token"], sd["embeddings.cls_token"])
  # Untouched parts keep their init values exactly.
  np.testing.assert_array_equal(params["info_sharing"]["norm"]["scale"],
                                template["info_sharing"]["norm"]["scale"])


def test_snapshot_init_loads_everything(reference_dir):
  model, official = __import__("ufm_jax").load_official(reference_dir / "base")
  official = official["params"]
  x = jnp.zeros((1, 28, 28, 3), jnp.uint8)
  template = jax.eval_shape(lambda r: model.init(r, x, x)["params"], jax.random.PRNGKey(0))
  template = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), template)
  params, rep = model_init.load_init_params(f"snapshot:{reference_dir / 'base'}", template)
  assert rep.left_at_init == [] and rep.resized == [] and rep.unused == []
  for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(official)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_ckpt_init_from_training_workdir(tmp_path, tiny):
  _, template = tiny
  trained = jax.tree.map(lambda p: p + 1.0, template)
  tx = optim.optax.adam(1e-3)
  mngr = checkpoint.make_manager(tmp_path, 1, 1)
  checkpoint.save(mngr, 3, optim.TrainState.create(trained, tx), None, force=True)
  mngr.wait_until_finished()
  mngr.close()
  params, rep = model_init.load_init_params(str(tmp_path), template)  # kind guessed: ckpt
  assert rep.source.endswith("@3") and rep.left_at_init == []
  for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(trained)):
    np.testing.assert_array_equal(np.asarray(a), b)
