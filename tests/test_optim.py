"""Optimizer: groups, schedule, frozen params (no grad, no state), skip on non-finite, clipping."""

import math

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from ufm_jax.training import optim


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
  s = optim.cosine_schedule(1e-4, total_steps=100, warmup_steps=10)
  assert s(0) == 0.0 and float(s(jnp.int32(0))) == 0.0
  assert s(5) == pytest.approx(0.5e-4, rel=1e-12)
  assert s(10) == pytest.approx(1e-4, rel=1e-12)
  # cosine from step 10 to 100: lr = peak * 0.5 * (1 + cos(pi * (t-10)/90))
  for t in (30, 55, 90):
    expect = 1e-4 * 0.5 * (1 + math.cos(math.pi * (t - 10) / 90))
    assert s(t) == pytest.approx(expect, rel=1e-12)
    assert float(s(jnp.int32(t))) == pytest.approx(expect, rel=6e-8)   # float64 rounded once
  assert s(100) == pytest.approx(0.0, abs=1e-20) and s(1000) == s(100)


def test_schedule_min_lr_rate_and_fractional_warmup():
  # The official 560 recipe: 4.8 warmup epochs x 21 steps = 100.8 steps, 1% floor.
  s = optim.cosine_schedule(1e-4, total_steps=1008, warmup_steps=100.8, min_lr_rate=0.01)
  assert s(100) == pytest.approx(1e-4 * 100 / 100.8, rel=1e-12)
  assert s(101) < 1e-4   # the peak itself is never reached
  assert s(101) == pytest.approx(1e-4 * (0.01 + 0.99 * 0.5 * (1 + math.cos(
      math.pi * 0.2 / 907.2))), rel=1e-12)
  assert s(1008) == pytest.approx(1e-6, rel=1e-12)
  c = ml_collections.ConfigDict({"warmup_epochs": 4.8, "fractional_warmup": True})
  assert optim.warmup_steps(c, 1008, 21) == pytest.approx(100.8)
  c.fractional_warmup = False
  assert optim.warmup_steps(c, 1008, 21) == 101.0
  with pytest.raises(ValueError, match="steps per epoch"):
    optim.warmup_steps(c, 1008, None)
  assert optim.warmup_steps(ml_collections.ConfigDict({"warmup_frac": 0.1}), 1008, None) == 101.0


def test_zero_lr_groups_are_frozen_and_lr_keys_without_params_ignored():
  params = _params()
  c = _cfg(lr={"default": 1e-4, "encoder": 0.0, "unet_feature": 1e-3})
  tx, labels, sched = optim.make_optimizer(c, params, total_steps=10)
  assert labels["encoder"]["blocks_0"]["kernel"] == "frozen" and set(sched) == {"default"}
  # Without "default", a parameter in no group is an error naming it.
  c = _cfg()
  c.lr = ml_collections.ConfigDict({"encoder": 1e-4})
  with pytest.raises(ValueError, match="head1/conv/bias"):
    optim.make_optimizer(c, params, total_steps=10)
  c.lr = ml_collections.ConfigDict({"default": 1e-4})
  with pytest.raises(ValueError, match="no learning rate for the groups \\['encoder'\\]"):
    optim.make_optimizer(c, params, total_steps=10)


def test_official_groups_of_our_parameter_paths():
  paths = {"encoder/blocks/attn/qkv/kernel": "encoder", "info_sharing/norm/scale": "info_sharing",
           "head1_0_0/scratch/refinenet1/out_conv/kernel": "output_head",
           "uncertainty_head_0_1/conv1/bias": "uncertainty_head",
           "classification_head/mlp/fc1/kernel": "classification_head",
           "unet_feature/downs_0/conv_0/kernel": "unet_feature", "conv1/kernel": "unet_feature",
           "conv2/bias": "unet_feature", "classification_bias": "unet_feature"}
  tree = {}
  for p in paths:
    node = tree
    *parents, leaf = p.split("/")
    for k in parents:
      node = node.setdefault(k, {})
    node[leaf] = jnp.zeros(1)
  labels = optim.param_labels(tree, optim.PARAM_GROUPS)
  got = {optim.path_str(k): v for k, v in jax.tree_util.tree_flatten_with_path(labels)[0]}
  assert got == paths


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
  # Params and Adam's state are kept; the schedules advance (skip_advances_schedule, official).
  for a, b in zip(jax.tree.leaves((s1.params, optim.advance_schedules(s1.opt_state, -1))),
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


@pytest.mark.parametrize("advance", [True, False])
def test_a_skipped_step_advances_the_schedule_as_the_official_trainer(advance):
  """Step 1 skipped (non-finite loss): with skip_advances_schedule (official, train_pl.py:79-81
  then the scheduler's step) the update of step 2 uses the learning rate of step 2 and Adam's
  first bias-corrected step; without it, the rate of step 1 (the skip delays the schedule)."""
  params = {"w": jnp.zeros(3)}
  cfg = ml_collections.ConfigDict({"lr": {"default": 1e-2}, "warmup_frac": 0.5,
                                   "weight_decay": 0.0, "min_lr_rate": 0.0})
  tx, _, sched = optim.make_optimizer(cfg, params, total_steps=6)
  state = optim.TrainState.create(params, tx)
  grads = {"w": jnp.ones(3)}
  step = jax.jit(lambda s, g, l: optim.apply_gradients(s, g, l, tx, advance))
  state, ok = step(state, grads, jnp.float32(1.0))                  # step 0: lr 0
  assert bool(ok)
  state, ok = step(state, grads, jnp.float32(np.nan))               # step 1: skipped
  assert not bool(ok) and int(state.skipped) == 1
  before = np.asarray(state.params["w"])
  state, ok = step(state, grads, jnp.float32(1.0))                  # step 2
  lr = sched["default"](2 if advance else 1)
  # Adam's second applied update: m_hat = v_hat = 1 (constant gradient): the step is -lr.
  np.testing.assert_allclose(np.asarray(state.params["w"]) - before, -lr, rtol=1e-5)
  assert lr > 0 and sched["default"](1) != sched["default"](2)


def test_clip_apart_clips_each_part_by_its_own_norm():
  """Groups of grad_clip_apart are clipped by their own norm and left out of the others':
  head gradient (6, 8) (norm 10) and rest (0.3, 0.4) (norm 0.5) with max norm 1 give (0.6, 0.8)
  and the rest unchanged; one global clip would have scaled the rest by 1 / sqrt(100.25)."""
  params = {"head1": {"w": jnp.zeros(2)}, "uncertainty_head_0": {"w": jnp.zeros(2)}}
  labels = optim.param_labels(params, {"uncertainty_head": "^uncertainty_head_",
                                       "output_head": "^head1"})
  tx = optim.clip_apart(1.0, labels, ("uncertainty_head",))
  g = {"head1": {"w": jnp.array([0.3, 0.4])}, "uncertainty_head_0": {"w": jnp.array([6.0, 8.0])}}
  u, _ = tx.update(g, tx.init(params))
  np.testing.assert_allclose(u["uncertainty_head_0"]["w"], [0.6, 0.8], rtol=1e-6)
  np.testing.assert_allclose(u["head1"]["w"], [0.3, 0.4], rtol=1e-6)
  c = _cfg(lr={"default": 1.0, "uncertainty_head": 1.0},
           groups={"uncertainty_head": "^uncertainty_head_"},
           grad_clip_norm=1.0, grad_clip_apart=("uncertainty_head",))
  tx, _, _ = optim.make_optimizer(c, params, total_steps=10)
  assert len(optim.TrainState.create(params, tx).opt_state) == 2
  with pytest.raises(ValueError, match="grad_clip_apart.*'head'.*not groups"):
    optim.make_optimizer(_cfg(lr={"default": 1.0}, groups={}, grad_clip_norm=1.0,
                              grad_clip_apart=("head",)), params, total_steps=10)
