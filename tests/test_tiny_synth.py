"""The `tiny_synth` variant of configs/synthetic.py: 7 px patches and a sin-cos position table."""

import jax
import numpy as np
import pytest

from configs import models
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


def test_tiny_synth_init_and_forward():
  cfg = models.get("tiny_synth")
  assert cfg.encoder.patch_size == 7 and cfg.encoder.pos_grid == 8
  model = ufm.model_from_config(cfg)
  params = ufm.init_params(model, seed=0)
  np.testing.assert_allclose(params["encoder"]["pos_embed"],
                             dinov2.sincos_pos_embed(8, cfg.encoder.embed_dim))
  rng = np.random.default_rng(0)
  img = rng.integers(0, 256, (1, 56, 56, 3), dtype=np.uint8)
  out = model.apply({"params": params}, img, img)
  assert out["flow"].shape == (1, 56, 56, 2) and out["covisibility"].shape == (1, 56, 56)
  assert np.isfinite(np.asarray(out["flow"])).all()
  # The default `tiny` keeps DINOv2's random table; an unknown choice is an error.
  tiny = ufm.init_params(ufm.model_from_config(models.get("tiny")), seed=0)
  assert np.abs(np.asarray(tiny["encoder"]["pos_embed"])).max() <= 0.04
  bad = cfg.replace(encoder=cfg.encoder.__class__(**{**cfg.encoder.__dict__,
                                                     "pos_embed_init": "zeros"}))
  with pytest.raises(ValueError, match="pos_embed_init"):
    ufm.init_params(ufm.model_from_config(bad))


def test_flax_init_uses_the_configured_position_table():
  # train.py initialises through `model.init`; it must give the same sin-cos table as the
  # host-side `ufm.init_params` (it used to draw DINOv2's random table whatever the config said).
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
