"""Full-size configs checked without compute (jax.eval_shape) against closed-form counts."""

import json

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util
import pytest

from ufm_jax.official import snapshot
from ufm_jax.models import dinov2, ufm, variants
from ufm_jax.testing.param_counts import dinov2_count, dpt_count, linear, vit_block


def _count(model):
  return sum(int(np.prod(s)) for s in snapshot.expected_param_shapes(model).values())


def test_ufm_base_parameter_count():
  cfg = variants.ufm_base()
  enc = dinov2_count(1024, 24)
  fusion = linear(1024, 768) + 12 * vit_block(768, 3072, layerscale=False) + 2 * 768
  heads = sum(dpt_count((1024, 768, 768, 768), (96, 192, 384, 768), 256, o) for o in (2, 1))
  want = enc + fusion + heads
  got = _count(ufm.model_from_config(cfg))
  assert got == want
  assert round(got / 1e6, 1) == 428.3  # "the official structure has about 428.3M parameters"


def test_ufm_base_structure():
  cfg = variants.ufm_base()
  assert cfg.encoder.embed_dim == 1024 and cfg.encoder.depth == 24 and cfg.encoder.patch_size == 14
  s = cfg.info_sharing
  assert (s.dim, s.depth, s.num_heads) == (768, 12, 12)
  assert s.indices == (5, 8)  # layers 6 and 9 of 12 (1-based), then the final layer
  assert cfg.flow_head.layer_dims == (96, 192, 384, 768) and cfg.flow_head.feature_dim == 256
  shapes = snapshot.expected_param_shapes(ufm.model_from_config(cfg))
  assert shapes[("encoder", "pos_embed")] == (1, 1370, 1024)
  assert shapes[("info_sharing", "self_attention_blocks_11", "mlp", "fc1", "kernel")] == (768, 3072)
  assert shapes[("head1_0_0", "input_process_3_0_1", "kernel")] == (3, 3, 768, 768)
  # full-size forward shape inference at 420 x 560 without compute
  x = jax.ShapeDtypeStruct((1, 420, 560, 3), jnp.uint8)
  p = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s, jnp.float32),
                   traverse_util.unflatten_dict(shapes), is_leaf=lambda s: isinstance(s, tuple))
  out = jax.eval_shape(lambda p, a, b: ufm.model_from_config(cfg).apply({"params": p}, a, b), p, x, x)
  assert out["flow"].shape == (1, 420, 560, 2) and out["covisibility"].shape == (1, 420, 560)


@pytest.mark.parametrize("size,d,depth,swiglu", [
    ("small", 384, 12, None), ("base", 768, 12, None), ("large", 1024, 24, None),
    ("giant", 1536, 40, 4096)])
def test_dinov2_sizes(size, d, depth, swiglu):
  cfg = dinov2.dinov2_config(size)
  model = dinov2.DinoV2(cfg)
  x = jax.ShapeDtypeStruct((1, 28, 28, 3), jnp.float32)
  shapes = jax.eval_shape(lambda a: model.init(jax.random.PRNGKey(0), a), x)["params"]
  got = sum(int(np.prod(v.shape)) for v in jax.tree.leaves(shapes))
  assert got == dinov2_count(d, depth, swiglu)
  # the DINOv2 paper's sizes: 21M, 86M, 300M, 1.1B
  assert round(got / 1e6) in {"small": (22,), "base": (86, 87), "large": (304,),
                              "giant": (1136,)}[size]


def test_fixture_small_is_the_fixture_structure(reference_dir):
  model, variables = snapshot.load_official(reference_dir / "base")
  params = variables["params"]
  assert model.config == variants.fixture_small()
  assert _count(model) == sum(v.size for v in jax.tree.leaves(params))


def test_variants_build():
  cm = variants
  from ufm_jax.models import refine
  for name in cm.VARIANTS:
    cfg = cm.get(name)
    text = ufm.config_to_json(cfg)
    # Each config class has its own reader; the refine one extends the base keys.
    if isinstance(cfg, refine.UFMRefineConfig):
      assert refine.refine_config_from_dict(json.loads(text)) == cfg
    else:
      assert ufm.config_from_json(text) == cfg
  with pytest.raises(ValueError, match="unknown model variant"):
    cm.get("ufm_huge")


def test_config_json_errors():
  d = ufm.config_to_dict(variants.tiny())
  with pytest.raises(ValueError, match="unknown model config key 'depth'"):
    ufm.config_from_dict({**d, "depth": 3})
  with pytest.raises(ValueError, match=r"unknown keys \['width'\] in model config section 'encoder'"):
    ufm.config_from_dict({**d, "encoder": {**d["encoder"], "width": 3}})
  with pytest.raises(ValueError, match="UFMConfig.dtype 'float16'"):
    ufm.config_from_dict({**d, "dtype": "float16"})
