"""Refinement loss on hand-computed cases, and the frozen-base parameter filter."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ufm_jax import refine_training as rt


def _log_softmax_field(n_pix, seed=0):
  rng = np.random.default_rng(seed)
  logits = rng.normal(size=(1, 1, n_pix, 7, 7)) * 3
  flat = logits.reshape(1, 1, n_pix, 49)
  return (flat - np.log(np.exp(flat).sum(-1, keepdims=True))).reshape(logits.shape)


def test_target_exactly_on_a_tap():
  t, inside = rt.refinement_target(jnp.array([10.0, 5.0]), jnp.array([11.0, 3.0]), 3)
  expected = np.zeros((7, 7))
  expected[1, 4] = 1.0       # dy = -2 -> a = 1, dx = +1 -> b = 4
  assert bool(inside)
  np.testing.assert_allclose(np.asarray(t), expected, atol=1e-7)


def test_target_between_four_taps():
  t, inside = rt.refinement_target(jnp.array([0.0, 0.0]), jnp.array([0.25, 1.5]), 3)
  expected = np.zeros((7, 7))
  # gx = 3.25 (x0 = 3, alpha = 0.25), gy = 4.5 (y0 = 4, beta = 0.5)
  expected[4, 3], expected[4, 4] = 0.75 * 0.5, 0.25 * 0.5
  expected[5, 3], expected[5, 4] = 0.75 * 0.5, 0.25 * 0.5
  assert bool(inside)
  np.testing.assert_allclose(np.asarray(t), expected, atol=1e-7)


def test_target_outside_and_on_the_edge():
  t, inside = rt.refinement_target(jnp.array([2.0, 2.0]), jnp.array([5.5, 2.0]), 3)   # dx = 3.5
  assert not bool(inside)
  np.testing.assert_array_equal(np.asarray(t), 0.0)
  t, inside = rt.refinement_target(jnp.array([2.0, 2.0]), jnp.array([5.0, -1.0]), 3)  # (3, -3)
  expected = np.zeros((7, 7))
  expected[0, 6] = 1.0
  assert bool(inside)
  np.testing.assert_allclose(np.asarray(t), expected, atol=1e-7)


def test_loss_averages_over_supervised_pixels_only():
  lp = _log_softmax_field(5)
  reg = np.zeros((1, 1, 5, 2), np.float32)
  gt = np.array([[1.0, -2.0],     # on tap (1, 4)
                 [0.25, 1.5],     # between (4|5, 3|4)
                 [3.5, 0.0],      # outside the window: ignored
                 [0.0, 0.0],      # inside but not covisible: ignored
                 [3.0, -3.0]],    # on the window's corner tap (0, 6)
                np.float32)[None, None]
  covis = np.array([[[True, True, True, False, True]]])
  loss, aux = rt.refinement_loss(jnp.asarray(lp), jnp.asarray(reg), jnp.asarray(gt),
                                 jnp.asarray(covis))
  l = lp[0, 0]
  ce = [-l[0, 1, 4],
        -(0.375 * l[1, 4, 3] + 0.125 * l[1, 4, 4] + 0.375 * l[1, 5, 3] + 0.125 * l[1, 5, 4]),
        -l[4, 0, 6]]
  np.testing.assert_allclose(float(loss), np.mean(ce), rtol=1e-6)
  assert int(aux["refine_pixels"]) == 3
  np.testing.assert_allclose(float(aux["refine_inside_frac"]), 3 / 4)
  # valid mask drops pixel 0 as well
  valid = np.array([[[False, True, True, True, True]]])
  loss, aux = rt.refinement_loss(jnp.asarray(lp), jnp.asarray(reg), jnp.asarray(gt),
                                 jnp.asarray(covis), jnp.asarray(valid))
  np.testing.assert_allclose(float(loss), np.mean(ce[1:]), rtol=1e-6)
  # nothing supervised -> 0, not NaN
  loss, _ = rt.refinement_loss(jnp.asarray(lp), jnp.asarray(reg), jnp.asarray(gt),
                               jnp.zeros((1, 1, 5), bool))
  assert float(loss) == 0.0


def test_loss_gradient_is_softmax_minus_target():
  logits = jnp.asarray(np.random.default_rng(3).normal(size=(1, 1, 1, 7, 7)), jnp.float32)
  reg = jnp.zeros((1, 1, 1, 2))
  gt = jnp.array([0.25, 1.5]).reshape(1, 1, 1, 2)
  f = lambda z: rt.refinement_loss(jax.nn.log_softmax(z.reshape(1, 1, 1, 49)).reshape(z.shape),
                                   reg, gt, jnp.ones((1, 1, 1), bool))[0]
  g = np.asarray(jax.grad(f)(logits))[0, 0, 0]
  target = np.asarray(rt.refinement_target(reg[0, 0, 0], gt[0, 0, 0], 3)[0])
  prob = np.asarray(jax.nn.softmax(logits.reshape(49))).reshape(7, 7)
  np.testing.assert_allclose(g, prob - target, atol=1e-6)


def _toy_params():
  return {"encoder": {"w": jnp.ones((3, 3))}, "head1": {"b": jnp.ones(2)},
          "unet_feature": {"downs_0": {"conv_0": {"kernel": jnp.ones((3, 3, 3, 2))}}},
          "classification_head": {"linear": {"kernel": jnp.ones((1, 1, 2, 4))}},
          "conv1": {"kernel": jnp.ones((1, 1, 4, 4))}, "conv2": {"bias": jnp.ones(2)},
          "classification_bias": jnp.zeros(49)}


def test_trainable_mask_and_masked_optimizer():
  params = _toy_params()
  mask = rt.trainable_mask(params)
  assert mask["encoder"]["w"] is False and mask["head1"]["b"] is False
  assert mask["unet_feature"]["downs_0"]["conv_0"]["kernel"] is True
  assert mask["classification_bias"] is True and mask["conv2"]["bias"] is True
  tx = rt.masked_optimizer(optax.adam(1e-2), params)
  state = tx.init(params)
  # Adam keeps mu and nu for the 5 trainable leaves only (plus a step count): no state for the base.
  shapes = sorted(x.shape for x in jax.tree_util.tree_leaves(state) if hasattr(x, "shape") and x.ndim)
  trainable_shapes = sorted(x.shape for k, v in params.items() if k in rt.TRAINABLE
                            for x in jax.tree_util.tree_leaves(v))
  assert shapes == sorted(trainable_shapes * 2)
  grads = jax.tree_util.tree_map(jnp.ones_like, params)
  updates, _ = tx.update(grads, state, params)
  assert float(jnp.abs(updates["encoder"]["w"]).max()) == 0.0
  assert float(jnp.abs(updates["classification_bias"]).min()) > 0.0


def test_split_merge_differentiates_only_the_refiner():
  params = _toy_params()
  trainable, frozen = rt.split_params(params)
  assert set(trainable) == set(rt.TRAINABLE) and set(frozen) == {"encoder", "head1"}
  loss = lambda tr: sum(jnp.sum(x) for x in jax.tree_util.tree_leaves(rt.merge_params(tr, frozen)))
  g = jax.grad(loss)(trainable)
  assert set(g) == set(rt.TRAINABLE)
  assert jax.tree_util.tree_structure(rt.merge_params(trainable, frozen)) == \
      jax.tree_util.tree_structure(params)


def test_refine_stage_trains_only_the_refiner_end_to_end():
  """Tiny UFM-Refine: gradients w.r.t. the refiner only; a few Adam steps lower the loss on a
  fixed GT offset of (+0.5, -1.25) px from the regressed flow; the base params stay bitwise."""
  from ufm_jax.models import variants as models
  from ufm_jax.models import ufm
  model = ufm.model_from_config(models.tiny_refine())
  assert type(model).__name__ == "UFMRefine"
  rng = np.random.default_rng(0)
  x = jax.ShapeDtypeStruct((1, 28, 28, 3), jnp.uint8)
  shapes = jax.eval_shape(lambda a: model.init(jax.random.PRNGKey(0), a, a), x)["params"]
  params = jax.tree.map(lambda s: jnp.asarray(rng.normal(0, 0.1, s.shape), jnp.float32), shapes)
  src = rng.integers(0, 256, (1, 28, 42, 3), dtype=np.uint8)
  tgt = np.roll(src, 2, axis=2)
  trainable, frozen = rt.split_params(params)
  covis = jnp.ones((1, 28, 42), bool)
  tx = optax.adam(3e-3)
  offset = jnp.array([0.5, -1.25])

  def loss_fn(tr, fr):
    out = model.apply({"params": rt.merge_params(tr, fr)}, src, tgt)
    gt = jax.lax.stop_gradient(out["flow_before_refinement"]) + offset
    return rt.refinement_loss(out["log_softmax"], out["flow_before_refinement"], gt, covis)[0]

  @jax.jit
  def step(tr, fr, opt):
    loss, g = jax.value_and_grad(loss_fn)(tr, fr)
    upd, opt = tx.update(g, opt, tr)
    return optax.apply_updates(tr, upd), opt, loss

  opt = tx.init(trainable)
  losses = []
  for _ in range(8):
    trainable, opt, loss = step(trainable, frozen, opt)
    losses.append(float(loss))
  assert losses[-1] < losses[0] - 0.05, losses
  merged = rt.merge_params(trainable, frozen)
  for k in frozen:
    for a, b in zip(jax.tree.leaves(merged[k]), jax.tree.leaves(params[k])):
      assert np.array_equal(np.asarray(a), np.asarray(b))
