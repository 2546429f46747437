"""The refinement losses against values derived here from their definition (the official parity
is tests/test_official_losses.py): window sampling, bounds, rows, pixel cap, the in-place ground
truth cleanup, and a few steps of the refine stage with the base frozen by lr 0."""

import math

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from ufm_jax.training import losses, optim
from ufm_jax.training import refine_training as rt


def _bf16(x):
  return np.asarray(jnp.asarray(x, jnp.float32).astype(jnp.bfloat16).astype(jnp.float32))


def _bilinear(f, x, y):
  """f [H, W, C] sampled at (x, y) (pixel index coordinates), zero outside."""
  h, w, _ = f.shape
  x0, y0 = math.floor(x), math.floor(y)
  out = np.zeros(f.shape[-1])
  for yy, wy in ((y0, 1 - (y - y0)), (y0 + 1, y - y0)):
    for xx, wx in ((x0, 1 - (x - x0)), (x0 + 1, x - x0)):
      if 0 <= xx < w and 0 <= yy < h:
        out = out + wx * wy * f[yy, xx].astype(np.float64)
  return out


def _expected_ce(f0, f1, bias, flow, gt, px, temperature, p):
  """Cross-entropy at pixel px = (x, y) from the definition: window of P x P integer offsets
  around x + flow, target features bilinear (zero padding) on bfloat16 values, 4-point GT."""
  x, y = px
  src = f0[y, x].astype(np.float64)
  f1b = _bf16(f1)
  r = p // 2
  scores = np.array([[_bilinear(f1b, x + flow[0] + dx, y + flow[1] + dy) @ src / temperature
                      for dx in range(-r, r + 1)] for dy in range(-r, r + 1)]).reshape(-1) + bias
  logp = scores - np.log(np.exp(scores - scores.max()).sum()) - scores.max()
  gx, gy = gt[0] - flow[0] + r, gt[1] - flow[1] + r   # window coordinates of the GT
  target = np.zeros((p, p))
  x0, y0 = int(math.floor(gx)), int(math.floor(gy))
  for yy, wy in ((y0, 1 - (gy - y0)), (y0 + 1, gy - y0)):
    for xx, wx in ((x0, 1 - (gx - x0)), (x0 + 1, gx - x0)):
      if wx * wy:
        target[yy, xx] = wx * wy
  return -(target.reshape(-1) * logp).sum()


def _case(seed=0, h=5, w=7, c=4, p=3):
  rng = np.random.default_rng(seed)
  f0 = rng.normal(size=(1, h, w, c)).astype(np.float32)
  f1 = rng.normal(size=(1, h, w, c)).astype(np.float32)
  bias = (0.1 * rng.normal(size=p * p)).astype(np.float32)
  return f0, f1, bias


def _run(term, f0, f1, bias, flow, gt, covis, rows=None, rng=None, shared_gt=None):
  outputs = {"feature_map_0": jnp.asarray(f0), "feature_map_1": jnp.asarray(f1),
             "attention_bias": jnp.asarray(bias)}
  batch = {"flow": jnp.asarray(gt), "covisibility": jnp.asarray(covis)}
  shared = {"gt": jnp.asarray(gt if shared_gt is None else shared_gt), "pred": jnp.asarray(flow)}
  ctx = {"temperature": 2.0, "suitable_rows": rows, "rng": rng or jax.random.PRNGKey(0)}
  return term(outputs, batch, shared, ctx)


def test_cross_entropy_matches_the_definition_at_one_pixel():
  f0, f1, bias = _case()
  h, w = 5, 7
  flow = np.zeros((1, h, w, 2), np.float32)
  flow[0, 2, 3] = (0.3, 0.6)             # window centre at (3.3, 2.6): every tap inside
  gt = flow.copy()
  gt[0, 2, 3] = (0.3 + 0.45, 0.6 - 0.2)
  covis = np.zeros((1, h, w), bool)
  covis[0, 2, 3] = True
  term = rt.RefinementCE(multiplier=10.0, datasets=None)
  loss, logs, _ = _run(term, f0, f1, bias, flow, gt, covis)
  ce = _expected_ce(f0[0], f1[0], bias, flow[0, 2, 3], gt[0, 2, 3], (3, 2), 2.0, 3)
  assert float(logs["refinement_cross_entropy@non_occluded_mask"]) == pytest.approx(
      ce / (1 + 1e-4), rel=2e-5)
  assert float(loss) == pytest.approx(10 * ce / (1 + 1e-4), rel=2e-5)
  assert float(logs["ratio_in_refinement_range"]) == pytest.approx(1 / (1 + 1e-4))
  # float32 taps (no bfloat16 cast): the same loss up to the cast.
  loss32, _, _ = _run(rt.RefinementCE(datasets=None, gather_dtype="float32"), f0, f1, bias, flow,
                      gt, covis)
  assert float(loss32) == pytest.approx(float(loss), rel=1e-2) and float(loss32) != float(loss)


def test_taps_truncate_towards_zero_at_the_left_border():
  """A window centre at x = -0.4: the taps of the left column sit at (-1.4, -0.4) -> .long()
  gives (-1, 0): column 0 is read where zero padding (floor) would be."""
  f0, f1, bias = _case(1)
  h, w = 5, 7
  flow = np.zeros((1, h, w, 2), np.float32)
  flow[0, 2, 0] = (-0.4, 0.25)
  gt = flow.copy()
  gt[0, 2, 0, 0] += 0.5
  covis = np.zeros((1, h, w), bool)
  covis[0, 2, 0] = True
  floor, _, _ = _run(rt.RefinementCE(datasets=None, taps="floor"), f0, f1, bias, flow, gt, covis)
  trunc, _, _ = _run(rt.RefinementCE(datasets=None), f0, f1, bias, flow, gt, covis)
  ce = _expected_ce(f0[0], f1[0], bias, flow[0, 2, 0], gt[0, 2, 0], (0, 2), 2.0, 3)
  assert float(floor) == pytest.approx(10 * ce / (1 + 1e-4), rel=2e-5)
  assert abs(float(trunc) - float(floor)) > 1e-3


@pytest.mark.slow
def test_window_bounds_rows_and_nan_ground_truth():
  f0, f1, bias = _case(2, h=2, w=8)
  flow = np.zeros((1, 2, 8, 2), np.float32)
  gt = np.zeros_like(flow)
  # P = 3: r in [-1 + 1e-4, 1 - 1e-4) on both axes (float32 compare).
  rs = [-1.0, np.float32(-1 + 1e-4), 0.0, np.float32(1 - 1e-4), np.float32(0.9998), 1.0]
  for i, r in enumerate(rs):
    gt[0, 0, i, 0] = r
  gt[0, 1, 0] = (np.nan, 0.0)                  # NaN GT: not supervised
  gt[0, 1, 1] = (0.5, 0.5)
  covis = np.ones((1, 2, 8), bool)
  covis[0, 0, 6:] = False
  _, logs, after = _run(rt.RefinementCE(datasets=None), f0, f1, bias, flow, gt, covis)
  # In the window: r = -1+1e-4, 0, 0.9998 in row 0 and (0.5, 0.5) plus 6 zero residuals in row 1.
  n_ref = 6 + 7     # covisible, finite GT
  assert float(logs["ratio_in_refinement_range"]) * (1e-4 + n_ref) == pytest.approx(3 + 7)
  assert np.asarray(after["gt"])[0, 1, 0, 0] == 0.0   # NaN zeroed for the terms after it
  # A row whose dataset is not suitable for refinement supervises nothing.
  b = np.concatenate([gt, gt])
  _, logs2, _ = _run(rt.RefinementCE(datasets=None), np.concatenate([f0, f0]),
                     np.concatenate([f1, f1]), bias, np.concatenate([flow, flow]), b,
                     np.concatenate([covis, covis]), rows=jnp.array([False, True]))
  assert float(logs2["ratio_in_refinement_range"]) * (1e-4 + 2 * n_ref) == pytest.approx(10)


def test_pixel_cap_keeps_about_the_cap():
  mask = jnp.ones((4, 50, 50), bool)            # 10000 pixels
  kept = rt.cap_pixels(mask, 1000, jax.random.PRNGKey(3))
  n = int(kept.sum())
  assert abs(n - 1000) < 4 * math.sqrt(1000 * 0.9)   # Bernoulli(0.1) per pixel
  assert bool(jnp.all(rt.cap_pixels(mask, 20000, jax.random.PRNGKey(3)) == mask))
  assert rt.buffer_size(10000, 1000) == 1000 + 8 * 31 + 8 and rt.buffer_size(100, 1000) == 100
  assert rt.buffer_size(100, None) == 100


@pytest.mark.slow
def test_recipe_rows_from_dataset_ids_and_the_shared_cleanup():
  f0, f1, bias = _case(4, h=2, w=4)
  flow = np.zeros((1, 2, 4, 2), np.float32)
  gt = np.zeros_like(flow)
  gt[0, 0, 0] = (np.nan, np.nan)
  covis = np.ones((1, 2, 4), bool)
  cfg = ml_collections.ConfigDict({
      "terms": ("epe", "refinement_cross_entropy"),
      "epe": {"type": "epe", "multiplier": 0.0},
      "refinement_cross_entropy": {"type": "refinement_ce", "datasets": ("blendedmvs",)},
      "shared_cleanup": True})
  outputs = {"flow": jnp.asarray(flow), "feature_map_0": jnp.asarray(f0),
             "feature_map_1": jnp.asarray(f1), "attention_bias": jnp.asarray(bias)}
  batch = {"flow": jnp.asarray(gt), "covisibility": jnp.asarray(covis),
           "dataset_id": jnp.array([1])}
  names = ("megadepth", "blendedmvs")
  key = "refinement_cross_entropy/ratio_in_refinement_range"
  _, aux = losses.recipe_from_config(cfg, temperature=2.0, dataset_names=names)(outputs, batch)
  # The EPE term zeroed the NaN GT in place: the refinement sees 8 finite pixels, all in range.
  assert float(aux[key]) == pytest.approx(8 / (8 + 1e-4))
  cfg.shared_cleanup = False
  _, aux = losses.recipe_from_config(cfg, temperature=2.0, dataset_names=names)(outputs, batch)
  assert float(aux[key]) == pytest.approx(7 / (7 + 1e-4))
  batch["dataset_id"] = jnp.array([0])      # megadepth: not suitable
  _, aux = losses.recipe_from_config(cfg, temperature=2.0, dataset_names=names)(outputs, batch)
  assert float(aux[key]) == 0.0


def test_eval_loss_window_and_gradients():
  p = 3
  rng = np.random.default_rng(5)
  logits = rng.normal(size=(1, 1, 4, p * p)).astype(np.float32)
  logp = np.asarray(jax.nn.log_softmax(jnp.asarray(logits))).reshape(1, 1, 4, p, p)
  flow = np.zeros((1, 1, 4, 2), np.float32)
  gt = np.array([[[[0.25, -0.5], [1.0, 0.0], [-1.0, 0.0], [0.0, 0.999]]]], np.float32)
  covis = np.ones((1, 1, 4), bool)
  term = rt.RefinementCEEval()

  def f(lp, fl):
    out = {"log_softmax": lp}
    batch = {"flow": jnp.asarray(gt), "covisibility": jnp.asarray(covis)}
    return term(out, batch, {"gt": batch["flow"], "pred": fl}, {})

  loss, logs, _ = f(jnp.asarray(logp), jnp.asarray(flow))
  # Window [0.5, 2.5) on r + 1.5: r = 1.0 is out (2.5), r = -1.0 in (0.5), 0.999 in.
  l0 = logp[0, 0]
  ce = [-(0.75 * 0.5 * l0[0][0, 1] + 0.75 * 0.5 * l0[0][1, 1] + 0.25 * 0.5 * l0[0][0, 2]
          + 0.25 * 0.5 * l0[0][1, 2]),
        -l0[2][1, 0],
        -(0.001 * l0[3][1, 1] + 0.999 * l0[3][2, 1])]
  assert float(logs["ratio_in_refinement_range"]) == pytest.approx(3 / (4 + 1e-4))
  assert float(loss) == pytest.approx(10 * sum(ce) / (3 + 1e-4), rel=1e-4)
  g_lp, g_flow = jax.grad(lambda a, b: f(a, b)[0], argnums=(0, 1))(jnp.asarray(logp),
                                                                    jnp.asarray(flow))
  np.testing.assert_allclose(np.asarray(g_lp)[0, 0, 2], np.eye(1, 9, 3).reshape(3, 3)
                             * -10 / (3 + 1e-4), atol=1e-6)
  np.testing.assert_array_equal(np.asarray(g_lp)[0, 0, 1], 0.0)
  assert np.abs(np.asarray(g_flow)[0, 0, 0]).max() > 0   # target weights depend on the flow


@pytest.mark.slow
def test_refine_stage_trains_only_the_refiner():
  """Tiny UFM-Refine, the refine-560 learning rates (base groups at 0): a few steps of the
  refinement loss on a fixed GT offset lower it, and the base parameters stay bitwise."""
  from ufm_jax.training import trainer
  from ufm_jax.models import variants
  model = variants.build_model("tiny_refine", param_init="official")
  params = trainer.random_params(model, 0)
  ocfg = ml_collections.ConfigDict({
      "lr": {"encoder": 0.0, "info_sharing": 0.0, "output_head": 0.0, "uncertainty_head": 0.0,
             "classification_head": 3e-3, "unet_feature": 3e-3},
      "groups": dict(optim.PARAM_GROUPS), "warmup_frac": 0.0, "grad_clip_norm": 1.0})
  tx, labels, _ = optim.make_optimizer(ocfg, params, total_steps=100)
  assert {l for l in jax.tree.leaves(labels)} == {"frozen", "classification_head", "unet_feature"}
  term = rt.RefinementCE(datasets=None)
  rng = np.random.default_rng(0)
  src = rng.integers(0, 256, (1, 28, 42, 3), dtype=np.uint8)
  tgt = np.roll(src, 2, axis=2)
  covis = jnp.ones((1, 28, 42), bool)
  offset = jnp.array([0.5, -1.25])

  def loss_fn(tr, fr):
    out = model.apply({"params": optim.merge_params(tr, jax.lax.stop_gradient(fr))}, src, tgt)
    reg = jax.lax.stop_gradient(out["flow_before_refinement"])
    batch = {"flow": reg + offset, "covisibility": covis}
    return term(out, batch, {"gt": batch["flow"], "pred": reg},
                {"temperature": model.config.temperature, "rng": jax.random.PRNGKey(0)})[0]

  state = optim.TrainState.create(params, tx)

  @jax.jit
  def step(state):
    tr, fr = optim.split_trainable(state.params, labels)
    loss, g = jax.value_and_grad(loss_fn)(tr, fr)
    grads = optim.merge_params(g, jax.tree.map(jnp.zeros_like, fr))
    return optim.apply_gradients(state, grads, loss, tx)[0], loss

  history = []
  for _ in range(6):
    state, loss = step(state)
    history.append(float(loss))
  assert history[-1] < history[0] - 0.05, history
  for k in ("encoder", "info_sharing", "head1_0_0", "uncertainty_head_0_1"):
    for a, b in zip(jax.tree.leaves(state.params[k]), jax.tree.leaves(params[k])):
      assert np.array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
def test_eight_groups_are_the_mean_of_eight_group_losses_each_capped_on_its_own():
  """The recipes' loss.groups=8 (one per GPU of the paper's run): the total is the mean of the
  losses of 8 consecutive 2-row blocks, each block with its own means and its own pixel cap
  (here 10 pixels of up to 40), as 8 DDP workers would; not the cap once over all 16 rows."""
  rng = np.random.default_rng(7)
  b, h, w, c, p = 16, 4, 5, 4, 3
  flow = rng.normal(size=(b, h, w, 2)).astype(np.float32)
  gt = flow + rng.uniform(-0.5, 0.5, size=flow.shape).astype(np.float32)   # all in the window
  covis = rng.random((b, h, w)) < np.repeat(np.linspace(0.2, 1.0, 8), 2)[:, None, None]
  outputs = {"flow": jnp.asarray(flow),
             "feature_map_0": jnp.asarray(rng.normal(size=(b, h, w, c)), jnp.float32),
             "feature_map_1": jnp.asarray(rng.normal(size=(b, h, w, c)), jnp.float32),
             "attention_bias": jnp.asarray(0.1 * rng.normal(size=p * p), jnp.float32)}
  batch = {"flow": jnp.asarray(gt), "covisibility": jnp.asarray(covis),
           "covis_valid": jnp.ones((b, h, w), bool)}

  def recipe(groups):
    return losses.recipe_from_config(ml_collections.ConfigDict({
        "terms": ("robust_epe", "refinement_cross_entropy"),
        "robust_epe": {"type": "robust", "range": "covisible", "alpha": 0.5, "c": 0.24},
        "refinement_cross_entropy": {"type": "refinement_ce", "datasets": None,
                                     "max_pixels": 10},
        "groups": groups}), temperature=2.0)

  key = jax.random.PRNGKey(5)
  total, aux = recipe(8)(outputs, batch, rng=key)
  keys = jax.random.split(key, 8)
  per_group = [recipe(1)({k: v[2 * g:2 * g + 2] if v.ndim == 4 else v for k, v in outputs.items()},
                         {k: v[2 * g:2 * g + 2] for k, v in batch.items()}, rng=keys[g])
               for g in range(8)]
  np.testing.assert_allclose(float(total), np.mean([float(t) for t, _ in per_group]), rtol=1e-5)
  ratio = "refinement_cross_entropy/ratio_in_refinement_range"
  ratios = np.array([float(a[ratio]) for _, a in per_group])
  np.testing.assert_allclose(float(aux[ratio]), ratios.mean(), rtol=1e-5)
  counts = covis.reshape(8, -1).sum(1)
  # each group: all its covisible pixels up to ~10, its own draw
  assert (counts <= 10).sum() == 2
  np.testing.assert_allclose(ratios[counts <= 10], 1.0, rtol=1e-3)
  capped = ratios[counts > 20] * counts[counts > 20]
  assert capped.size and np.all(capped < 25) and np.all(capped >= 1)
  # pooled: one cap of 10 over every row's pixels (the kept share is far smaller)
  _, pooled_aux = recipe(1)(outputs, batch, rng=key)
  assert float(pooled_aux[ratio]) < 20 / counts.sum() < 0.5 * float(aux[ratio])
  with pytest.raises(ValueError, match=r"groups=8 .*batch of 12 rows.*multiple of 8"):
    recipe(8)({k: v[:12] if v.ndim == 4 else v for k, v in outputs.items()},
              {k: v[:12] for k, v in batch.items()})
  with pytest.raises(ValueError, match=r"batch of 48 rows in 4 microbatches.*multiple of 64"):
    losses.check_groups(48, 8, grad_accum=4, pair_rows=2)
  losses.check_groups(96, 8, grad_accum=1, pair_rows=2)
