"""The uncertainty head's cues (UFMConfig.uncertainty_cues, models/sampling.py): values worked by
hand, no gradient into the flow, and no official export."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.models import sampling, ufm, variants
from ufm_jax.official import config as official_config


def test_warp_residual_and_flow_edges_by_hand():
  # 1 x 2 x 3 images, one channel repeated 3 times; flow +1 px in x on the left two columns,
  # 0 on the right column.
  src = np.array([[1.0, 2.0, 4.0], [0.0, 5.0, 3.0]])
  tgt = np.array([[7.0, 1.0, 2.0], [6.0, 0.0, 8.0]])
  flow = np.zeros((1, 2, 3, 2), np.float32)
  flow[0, :, :2, 0] = 1.0
  rgb = lambda a: jnp.asarray(np.repeat(a[None, :, :, None], 3, -1), jnp.float32)  # noqa: E731
  out = np.asarray(sampling.uncertainty_cues(("warp_residual", "flow_edges"), rgb(src), rgb(tgt),
                                             jnp.asarray(flow)))
  assert out.shape == (1, 2, 3, 5)
  # source(p) - target(p + flow): row 0: |1 - 1|, |2 - 2|, |4 - 2|; row 1: |0 - 0|, |5 - 8|, |3 - 8|
  np.testing.assert_allclose(out[0, ..., 0], [[0, 0, 2], [0, 3, 5]])
  np.testing.assert_allclose(out[0, ..., 2], out[0, ..., 0])
  # The middle column lands on x = 2, inside [-0.5, 2.5]: nothing leaves the target.
  np.testing.assert_array_equal(out[0, ..., 3], 0)
  # Central differences of u along x with the edge extended: column 0 (1 - 1) / 2 = 0,
  # column 1 (0 - 1) / 2, column 2 (0 - 1) / 2; none along y.
  np.testing.assert_allclose(out[0, ..., 4], [[0, np.log1p(0.5), np.log1p(0.5)]] * 2, rtol=1e-6)
  flow[0, 0, 0, 0] = 3.0    # x = 3 > 2.5: leaves the target
  out = np.asarray(sampling.uncertainty_cues(("warp_residual",), rgb(src), rgb(tgt),
                                             jnp.asarray(flow)))
  assert out[0, 0, 0, 3] == 1 and out[0, ..., 3].sum() == 1
  with pytest.raises(ValueError, match="uncertainty cue 'edges'"):
    sampling.uncertainty_cues(("edges",), rgb(src), rgb(tgt), jnp.asarray(flow))


@pytest.mark.slow
def test_the_cues_pass_no_gradient_to_the_flow():
  cfg = ufm.with_flow_covariance(variants.get("tiny_synth")).replace(
      uncertainty_cues=("warp_residual", "flow_edges"))
  model = ufm.UFM(cfg)
  x = jnp.asarray(np.random.default_rng(0).integers(0, 256, (1, 56, 56, 3)), jnp.uint8)
  y = jnp.roll(x, 3, axis=2)
  params = model.init(jax.random.PRNGKey(0), x, y)["params"]
  kernel = params["uncertainty_head_0_1"]["conv2_0"]["kernel"]
  assert kernel.shape[2] == cfg.covisibility_head.feature_dim // 2 + 5
  grads = jax.grad(lambda p: model.apply({"params": p}, x, y)["flow_covariance_params"].sum())(
      params)
  flow_side = [g for k, g in grads.items() if not k.startswith("uncertainty_head")]
  assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(flow_side)) == 0
  assert float(jnp.abs(grads["uncertainty_head_0_1"]["conv2_0"]["kernel"]).max()) > 0
  with pytest.raises(ValueError, match="uncertainty_cues.*cannot be exported"):
    official_config.official_config_dict(cfg)
  with pytest.raises(ValueError, match="uncertainty_cues=\\('flow',\\)"):
    cfg.replace(uncertainty_cues=("flow",))


def test_the_synthetic_cov_recipe_reads_the_cues_and_clips_its_head_apart():
  """configs/synthetic.py:cov=True (the docs' demonstration) turns both on; without the
  covariance, or with it in the flow head, the recipe is the one of docs/synthetic_training.md."""
  from ufm_jax.training import config_lib
  c = config_lib.load_config("configs/synthetic.py:cov=True,pairs=layers")
  assert tuple(c.model.uncertainty_cues) == ("warp_residual", "flow_edges")
  assert tuple(c.optim.grad_clip_apart) == ("uncertainty_head",)
  for arg in ("pairs=layers", "cov=True,cov_head=main"):
    c = config_lib.load_config(f"configs/synthetic.py:{arg}")
    assert tuple(c.model.uncertainty_cues) == () and tuple(c.optim.grad_clip_apart) == (), arg
