"""The `tiny_synth` variant of configs/synthetic.py: 7 px patches and a sin-cos position table."""

import dataclasses
import functools

import jax
import numpy as np
import pytest

from ufm_jax.models import variants as models
from ufm_jax.training import trainer
from ufm_jax.models import dinov2, ufm


def test_sincos_pos_embed_closed_form():
  t = dinov2.sincos_pos_embed(3, 8)  # dim 8: 2 frequencies (1 and 1/100) per axis
  assert t.shape == (1, 10, 8)
  np.testing.assert_array_equal(t[0, 0], 0.0)  # cls row
  # Token at row y=2, column x=1 -> index 1 + 2*3 + 1.
  x, y = 1.0, 2.0
  want = [np.sin(x), np.sin(x / 100), np.cos(x), np.cos(x / 100),
          np.sin(y), np.sin(y / 100), np.cos(y), np.cos(y / 100)]
  np.testing.assert_allclose(t[0, 8], want, rtol=1e-6)
  with pytest.raises(ValueError, match="divisible by 4"):
    dinov2.sincos_pos_embed(3, 6)


@pytest.mark.slow
def test_tiny_synth_init_and_forward():
  cfg = models.get("tiny_synth")
  assert cfg.encoder.patch_size == 7 and cfg.encoder.pos_grid == 8
  model = ufm.model_from_config(cfg)
  params = trainer.random_params(model, seed=0)
  np.testing.assert_allclose(params["encoder"]["pos_embed"],
                             dinov2.sincos_pos_embed(8, cfg.encoder.embed_dim))
  rng = np.random.default_rng(0)
  img = rng.integers(0, 256, (1, 56, 56, 3), dtype=np.uint8)
  out = model.apply({"params": params}, img, img)
  assert out["flow"].shape == (1, 56, 56, 2) and out["covisibility"].shape == (1, 56, 56)
  assert np.isfinite(np.asarray(out["flow"])).all()
  # An unknown table choice is an error of the initializer.
  bad = cfg.replace(encoder=cfg.encoder.__class__(**{**cfg.encoder.__dict__,
                                                     "pos_embed_init": "zeros"}))
  with pytest.raises(ValueError, match="pos_embed_init"):
    ufm.param_shapes(ufm.model_from_config(bad))


@pytest.mark.slow
def test_flax_init_uses_the_configured_position_table():
  # `model.init` (train.py's init) used to draw DINOv2's random table whatever the config said;
  # the default `tiny` keeps that random table.
  cfg = models.get("tiny_synth")
  model = ufm.model_from_config(cfg)
  img = np.zeros((1, 56, 56, 3), np.uint8)
  params = jax.jit(model.init)(jax.random.PRNGKey(0), img, img)["params"]
  np.testing.assert_array_equal(params["encoder"]["pos_embed"],
                                dinov2.sincos_pos_embed(8, cfg.encoder.embed_dim))
  tiny = ufm.model_from_config(models.get("tiny"))
  table = np.asarray(jax.jit(tiny.init)(jax.random.PRNGKey(0), img, img)["params"]["encoder"][
      "pos_embed"])
  assert 0.015 < table.std() < 0.025  # DINOv2's trunc_normal(std=0.02)


def _qkv_kernels(params):
  """{path: fused qkv kernel} of every attention block."""
  from flax import traverse_util
  flat = traverse_util.flatten_dict(params, sep="/")
  return {k: np.asarray(v) for k, v in flat.items() if k.endswith("attn/qkv/kernel")}


def _synth(tied: bool):
  cfg = models.get("synth")
  if not tied:
    cfg = cfg.replace(info_sharing=dataclasses.replace(cfg.info_sharing, tied_qk_init=None))
  return cfg


@functools.lru_cache(maxsize=None)
def _flax_params(tied: bool):
  """train.py's init (`model.init`) of `synth`, with or without the tie; shared by the tests."""
  return trainer.random_params(ufm.model_from_config(_synth(tied)), seed=0)


def test_tied_qk_init_only_in_the_fusion_blocks():
  cfg = models.get("synth")
  assert cfg.info_sharing.tied_qk_init == 2.0
  assert models.get("tiny").info_sharing.tied_qk_init is None
  params = _flax_params(True)
  kernels = _qkv_kernels(params)
  fusion = [k for k in kernels if k.startswith("info_sharing/")]
  assert len(fusion) == cfg.info_sharing.depth and len(kernels) > len(fusion)
  for path, w in kernels.items():
    c = w.shape[0]
    q, k, v = w[:, :c], w[:, c:2 * c], w[:, 2 * c:]
    assert np.abs(q).max() > 0 and not np.allclose(q, v), path
    assert np.array_equal(q, k) == path.startswith("info_sharing/"), path


def test_tied_qkv_init_rejects_an_unfused_kernel():
  from ufm_jax.models import layers
  with pytest.raises(ValueError, match=r"\[c, 3c\]"):
    layers.tied_qkv_init()(jax.random.PRNGKey(0), (8, 16))


def _twin_attention(tied: bool) -> float:
  """Mean attention weight (in units of uniform attention) that a view-1 token gives, in the
  first fusion block at init, to the view-2 token showing the same texture patch."""
  from ufm_jax.data import synthetic
  cfg = _synth(tied)
  model = ufm.model_from_config(cfg)
  params = _flax_params(tied)
  scfg = synthetic.SyntheticConfig(size=(56, 56), pair_type="shift", aligned_shift_frac=1.0)
  pairs = [synthetic.generate_pair(synthetic.pair_seed(0, "val", i), scfg, (0,))[0]
           for i in range(8)]
  im0, im1 = (np.stack([p[k] for p in pairs]) for k in ("image0", "image1"))
  # Only the fusion input is needed: run the backbone, not the DPT heads.
  _, state = jax.jit(lambda p, a, b: model.apply(
      {"params": p}, a, b, method=lambda m, x, y: m.backbone(x, y), mutable=["intermediates"]))(
          params, im0, im1)
  x = np.asarray(state["intermediates"]["info_sharing"]["tokens_in"][0], np.float64)
  block = jax.tree.map(lambda a: np.asarray(a, np.float64),
                       params["info_sharing"]["self_attention_blocks_0"])
  y = (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + 1e-6)
  y = y * block["norm1"]["scale"] + block["norm1"]["bias"]
  qkv = y @ block["attn"]["qkv"]["kernel"] + block["attn"]["qkv"]["bias"]
  b, n2, c3 = qkv.shape
  c, heads, n, g = c3 // 3, cfg.info_sharing.num_heads, n2 // 2, 8
  q = qkv[..., :c].reshape(b, n2, heads, -1)
  k = qkv[..., c:2 * c].reshape(b, n2, heads, -1)
  logits = np.einsum("bqhd,bkhd->bhqk", q, k) / np.sqrt(q.shape[-1])
  attn = np.exp(logits - logits.max(-1, keepdims=True))
  attn = (attn / attn.sum(-1, keepdims=True)).mean(1)  # [b, 2n, 2n], mean over heads
  weights = []
  for i, p in enumerate(pairs):
    dx, dy = (np.asarray(p["flow"][0, 0]) / 7).astype(int)  # whole-patch shifts
    for t in range(n):
      ty, tx = t // g + dy, t % g + dx
      if 0 <= ty < g and 0 <= tx < g:
        weights.append(attn[i, t, n + ty * g + tx])
  return float(np.mean(weights)) * n2


@pytest.mark.slow
def test_tied_qk_init_starts_attention_on_the_matching_token():
  # What the tie is for: at init a token already looks at its twin in the other view (measured
  # ~5x uniform attention) where independent q/k projections give no preference (~1x).
  assert _twin_attention(tied=True) > 3.0
  assert _twin_attention(tied=False) < 1.5


def test_the_layers_task_ties_query_and_key_at_three_times():
  """configs/synthetic.py: pairs=layers starts the fusion tie at 3x (at synth's 2x one seed stayed
  on the zero-flow plateau, docs/uncertainty.md); the shift task keeps the variant's 2x; `tie=`
  overrides either."""
  import pathlib

  from ufm_jax.training import config_lib
  config = pathlib.Path(__file__).resolve().parents[1] / "configs" / "synthetic.py"

  def tie(arg):
    c = config_lib.load_config(f"{config}:{arg}")
    return models.get(c.model_name, **c.model.to_dict()).info_sharing.tied_qk_init

  assert tie("pairs=layers") == tie("cov=True,pairs=layers") == 3.0
  assert tie("pairs=shift") == models.get("synth").info_sharing.tied_qk_init == 2.0
  assert tie("pairs=layers,tie=2.0") == 2.0 and tie("tie=1.5") == 1.5
