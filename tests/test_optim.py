"""Optimizer: groups, schedule, frozen params (no grad, no state), skip on non-finite, clipping."""

import math

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from ufm_jax import optim


def _params():
  return {
      "encoder": {"blocks_0": {"kernel": jnp.ones((3, 4)), "bias": jnp.ones((4,))}},
      "info_sharing": {"proj": {"kernel": jnp.ones((4, 5))}},
      "head1": {"conv": {"kernel": jnp.ones((1, 1, 5, 2)), "bias": jnp.zeros((2,))}},
  }


def _cfg(**kw):
  c = ml_collections.ConfigDict({
      "lr": {"default": 1e-4, "encoder": 5e-6}, "groups": {"encoder": r"^encoder/"},
      "b1": 0.9, "b2": 0.95, "weight_decay": 0.05, "warmup_frac": 0.1, "frozen": None,
      "trainable": None, "grad_clip_norm": None})
  c.update(kw)
  return c


def test_labels_groups_and_frozen():
  labels = optim.param_labels(_params(), {"encoder": "^encoder/"}, frozen="^head1/conv/bias$")
  assert labels["encoder"]["blocks_0"]["kernel"] == "encoder"
  assert labels["info_sharing"]["proj"]["kernel"] == "default"
  assert labels["head1"]["conv"]["kernel"] == "default"
  assert labels["head1"]["conv"]["bias"] == "frozen"
  labels = optim.param_labels(_params(), {}, trainable=lambda p: p.startswith("head1"))
  assert labels["encoder"]["blocks_0"]["bias"] == "frozen"
  assert labels["head1"]["conv"]["bias"] == "default"


def test_schedule_warmup_and_cosine_closed_form():
  s = optim.lr_schedule(1e-4, total_steps=100, warmup_frac=0.1)
  assert float(s(0)) == 0.0
  assert float(s(5)) == pytest.approx(0.5e-4, rel=1e-6)
  assert float(s(10)) == pytest.approx(1e-4, rel=1e-6)
  # cosine from step 10 to 100: lr = peak * 0.5 * (1 + cos(pi * (t-10)/90))
  for t in (30, 55, 90):
    assert float(s(t)) == pytest.approx(1e-4 * 0.5 * (1 + math.cos(math.pi * (t - 10) / 90)),
                                        rel=1e-5)
  assert float(s(100)) == pytest.approx(0.0, abs=1e-12)


def test_first_adamw_step_per_group_lr_and_decoupled_decay():
  params = _params()
  tx, labels, sched = optim.make_optimizer(_cfg(warmup_frac=0.0), params, total_steps=10)
  state = optim.TrainState.create(params, tx)
  grads = jax.tree.map(lambda p: 0.3 * jnp.ones_like(p), params)
  new, ok = optim.apply_gradients(state, grads, jnp.float32(1.0), tx)
  assert bool(ok)
  # Step 1 of Adam with bias correction: update = -lr * (g/|g| + wd * p) = -lr * (1 + 0.05 p).
  enc = np.asarray(new.params["encoder"]["blocks_0"]["kernel"])
  np.testing.assert_allclose(enc, 1 - 5e-6 * (1 + 0.05), rtol=1e-6)
  rest = np.asarray(new.params["info_sharing"]["proj"]["kernel"])
  np.testing.assert_allclose(rest, 1 - 1e-4 * (1 + 0.05), rtol=1e-6)
  bias = np.asarray(new.params["head1"]["conv"]["bias"])  # p = 0: no decay term
  np.testing.assert_allclose(bias, -1e-4, rtol=1e-4)
  assert int(new.step) == 1 and int(new.skipped) == 0


def test_frozen_params_have_no_state_and_do_not_move():
  params = _params()
  tx, labels, _ = optim.make_optimizer(_cfg(frozen="^encoder/"), params, total_steps=10)
  state = optim.TrainState.create(params, tx)
  opt_leaves = jax.tree.leaves(state.opt_state)
  n_state = sum(x.size for x in opt_leaves if x.ndim > 0)
  n_trainable = sum(x.size for x, l in zip(jax.tree.leaves(params), jax.tree.leaves(labels))
                    if l != "frozen")
  assert n_state == 2 * n_trainable  # mu and nu only for the trainable leaves
  trainable, frozen = optim.split_trainable(params, labels)
  assert set(k[0] for k in frozen) == {"encoder"}
  assert all(k[0] != "encoder" for k in trainable)

  def loss_fn(tr):
    p = optim.merge_params(tr, frozen)
    return sum(jnp.sum(x**2) for x in jax.tree.leaves(p))

  g_tr = jax.grad(loss_fn)(trainable)
  grads = optim.merge_params(g_tr, jax.tree.map(jnp.zeros_like, frozen))
  for _ in range(3):
    state, _ = optim.apply_gradients(state, grads, jnp.float32(1.0), tx)
  np.testing.assert_array_equal(state.params["encoder"]["blocks_0"]["kernel"], 1.0)
  assert not np.allclose(state.params["info_sharing"]["proj"]["kernel"], 1.0)


def test_non_finite_skips_update_and_counts():
  params = _params()
  tx, _, _ = optim.make_optimizer(_cfg(), params, total_steps=10)
  state = optim.TrainState.create(params, tx)
  grads = jax.tree.map(jnp.ones_like, params)
  bad = jax.tree.map(lambda g: g, grads)
  bad["head1"]["conv"]["bias"] = jnp.array([jnp.nan, 1.0])
  step = jax.jit(lambda s, g, l: optim.apply_gradients(s, g, l, tx))
  s1, ok = step(state, bad, jnp.float32(1.0))
  assert not bool(ok) and int(s1.skipped) == 1 and int(s1.step) == 1
  for a, b in zip(jax.tree.leaves((s1.params, s1.opt_state)),
                  jax.tree.leaves((state.params, state.opt_state))):
    np.testing.assert_array_equal(a, b)
  s2, ok = step(s1, grads, jnp.float32(np.inf))
  assert not bool(ok) and int(s2.skipped) == 2
  s3, ok = step(s2, grads, jnp.float32(1.0))
  assert bool(ok) and int(s3.skipped) == 2
  assert np.all(np.isfinite(np.asarray(s3.params["head1"]["conv"]["bias"])))


def test_global_norm_clipping():
  params = {"w": jnp.zeros((4,))}
  c = _cfg(lr={"default": 1.0}, groups={}, weight_decay=0.0, warmup_frac=0.0, grad_clip_norm=1.0)
  tx, _, _ = optim.make_optimizer(c, params, total_steps=1000)
  # Clipping happens before Adam; check via the clip transform's effect on a plain SGD chain too.
  clip_only = optim.optax.clip_by_global_norm(1.0)
  g = {"w": jnp.array([3.0, 4.0, 0.0, 0.0])}
  u, _ = clip_only.update(g, clip_only.init(params))
  np.testing.assert_allclose(u["w"], [0.6, 0.8, 0, 0], rtol=1e-6)
  state = optim.TrainState.create(params, tx)
  assert len(state.opt_state) == 2  # (clip state, multi_transform state)
