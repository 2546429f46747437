"""Loss terms and recipes against values derived here from their definitions (the official
parity is tests/test_official_losses.py): masks, quirks and their switches, config handling."""

import math
import pathlib

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from ufm_jax.training import losses


def _rho(x, a=0.5, c=0.24):
  # Written out for alpha=0.5: |a-2| = 1.5, |a-2|/a = 3.
  return 3.0 * ((x * x / (c * c) / 1.5 + 1.0) ** 0.25 - 1.0)


def _drho(x, c=0.24):
  # d/dx 3((x^2/(1.5c^2)+1)^(1/4) - 1) = (x/c^2) (x^2/(1.5c^2)+1)^(-3/4)
  return x / c**2 * (x * x / (1.5 * c * c) + 1.0) ** -0.75


def test_robust_values_closed_form():
  xs = np.array([0.0, 0.1, 0.24, 1.0, 3.0, 500.0])
  got = np.asarray(losses.robust_charbonnier(jnp.asarray(xs)))
  np.testing.assert_allclose(got, [_rho(x) for x in xs], rtol=1e-5, atol=1e-7)
  assert got[2] == pytest.approx(3 * ((5 / 3) ** 0.25 - 1), rel=1e-6)
  assert got[0] == 0.0


def test_gradient_peak_and_tail_match_supplementary_figure():
  grad = jax.vmap(jax.grad(losses.robust_charbonnier))
  peak = 0.24 * math.sqrt(3.0)   # d^2/dx^2 = 0 at x = c sqrt(3)
  xs = jnp.linspace(0.0, 3.0, 30001)
  g = np.asarray(grad(xs))
  assert float(xs[np.argmax(g)]) == pytest.approx(peak, abs=2e-4)
  assert g.max() == pytest.approx(math.sqrt(3) / 0.24 * 3**-0.75, rel=1e-4)
  g500 = float(grad(jnp.array([500.0]))[0])
  assert g500 == pytest.approx(_drho(500.0), rel=1e-5)


def _term(**kw):
  return losses.FlowRegression(**kw)


def _run(term, pred, gt, covis, **batch):
  b = {"flow": jnp.asarray(gt, jnp.float32), "covisibility": jnp.asarray(covis), **batch}
  shared = {"gt": b["flow"], "pred": jnp.asarray(pred, jnp.float32)}
  return term({}, b, shared, {})


def test_robust_masked_mean_with_the_official_denominator():
  pred = np.zeros((1, 1, 4, 2), np.float32)
  gt = np.array([[[[3, 4], [0.24, 0], [100, 0], [0, 0]]]], np.float32)
  covis = np.array([[[True, True, False, True]]])
  loss, logs, _ = _run(_term(), pred, gt, covis)
  expect = (_rho(5.0) + _rho(0.24) + 0.0) / (3 + 1e-4)
  assert float(loss) == pytest.approx(expect, rel=1e-6)
  assert float(logs["flow_epe[flow_output]@non_occluded_mask"]) == pytest.approx(
      (5 + 0.24) / (3 + 1e-4), rel=1e-6)
  assert float(logs["px_robust_epe@non_occluded_mask"]) == pytest.approx((5 + 0.24) / 3, rel=1e-6)
  # Outlier ratios over the 3 supervised pixels: > 0.25 px (lv1): 1 of 3 (EPE 5).
  assert float(logs["flow_output_pixel_outlier/lv1"]) == pytest.approx(1 / 3)
  # eps=None: plain mean; nothing supervised: 0, the px mean NaN (as the official logs).
  loss, _, _ = _run(_term(eps=None), pred, gt, covis)
  assert float(loss) == pytest.approx((_rho(5.0) + _rho(0.24)) / 3, rel=1e-6)
  loss, logs, _ = _run(_term(), pred, gt, np.zeros_like(covis))
  assert float(loss) == 0.0 and math.isnan(float(logs["px_robust_epe@non_occluded_mask"]))


def test_invalid_ground_truth_zero_versus_drop():
  pred = np.full((1, 1, 4, 2), 1.0, np.float32)
  gt = np.array([[[[np.nan, 2.0], [3000.0, 1.0], [1500.0, 1500.0], [1.0, 1.0]]]], np.float32)
  covis = np.ones((1, 1, 4), bool)
  # "zero" (official): NaN -> 0 and components > 2048 -> 0, every pixel stays in the mean;
  # |u| + |v| >= 2048 with both components <= 2048 keeps its GT.
  loss, logs, after = _run(_term(), pred, gt, covis)
  residuals = [math.hypot(1, 1), math.hypot(1, 0), math.hypot(1499, 1499), 0.0]
  assert float(loss) == pytest.approx(sum(_rho(r) for r in residuals) / (4 + 1e-4), rel=1e-6)
  np.testing.assert_array_equal(np.asarray(after["gt"])[0, 0],
                                [[0, 2], [0, 1], [1500, 1500], [1, 1]])
  # Only the last pixel is valid ground truth for the logs.
  assert float(logs["px_robust_epe@non_occluded_mask"]) == 0.0
  # "drop": the three invalid pixels leave the mask (and flow_valid False drops one more).
  loss, _, _ = _run(_term(invalid_gt="drop"), pred, gt, covis)
  assert float(loss) == 0.0
  pred2 = np.zeros_like(pred)
  loss, _, _ = _run(_term(invalid_gt="drop"), pred2, gt, covis,
                    flow_valid=jnp.array([[[True, True, True, False]]]))
  assert float(loss) == 0.0
  # A NaN prediction is set to 0 (no gradient there).
  pred3 = np.array([[[[np.nan, 0.0], [0, 0], [0, 0], [1, 1]]]], np.float32)
  g = jax.grad(lambda p: _run(_term(), p, gt, covis)[0])(jnp.asarray(pred3))
  assert np.all(np.isfinite(np.asarray(g))) and np.asarray(g)[0, 0, 0, 0] == 0.0


def test_all_pixels_range_is_the_target_within_the_margin():
  h, w = 4, 8
  gt = np.zeros((1, h, w, 2), np.float32)
  # Targets x + u at exactly -0.25 W (in), one ulp below (out), 1.25 W (out), just below (in).
  gt[0, 0, 0, 0] = -0.25 * w
  gt[0, 0, 1, 0] = np.nextafter(np.float32(-0.25 * w), np.float32(-100)) - 1
  gt[0, 0, 2, 0] = 1.25 * w - 2
  gt[0, 0, 3, 0] = np.nextafter(np.float32(1.25 * w), np.float32(0)) - 3
  gt[0, 1, 0, 1] = np.nan                       # NaN target: passes, residual against 0
  gt[0, 1, 1, 1] = -0.25 * h - 1 - 0.5          # y target below -0.25 H: out
  pred = gt.copy()
  pred[np.isnan(pred)] = 0
  pred += 1.0                                   # every residual (1, 1)
  term = _term(range="all", margin=0.25)
  mask, _ = term.mask({"covisibility": jnp.zeros((1, h, w), bool)}, jnp.asarray(gt))
  mask = np.asarray(mask)[0]
  assert mask[0, 0] and not mask[0, 1] and not mask[0, 2] and mask[0, 3]
  assert mask[1, 0] and not mask[1, 1]
  assert mask.sum() == h * w - 3
  # flow_valid False (no ground truth: the official sets encode it as 4000 px) leaves the range.
  fv = np.ones((1, h, w), bool)
  fv[0, 3, 3] = False
  mask2, _ = term.mask({"flow_valid": jnp.asarray(fv)}, jnp.asarray(gt))
  assert int(np.asarray(mask2).sum()) == h * w - 4
  loss, _, _ = _run(term, pred, gt, np.zeros((1, h, w), bool))
  n = h * w - 3
  expect = ((n - 1) * _rho(math.sqrt(2)) + _rho(math.hypot(1, 1))) / (n + 1e-4)
  assert float(loss) == pytest.approx(expect, rel=1e-5)


def test_epe_term_zero_gradient_at_zero_error_and_ignored_multiplier():
  gt = np.zeros((1, 1, 2, 2), np.float32)
  pred = gt.copy()
  pred[0, 0, 1] = (3.0, 4.0)
  covis = np.ones((1, 1, 2), bool)
  term = _term(kind="epe", multiplier=0.0)
  loss, logs, _ = _run(term, pred, gt, covis)
  assert float(loss) == pytest.approx(5.0 / (2 + 1e-4), rel=1e-6)   # multiplier 0 ignored
  assert float(logs["flow_epe@non_occluded_mask"]) == float(loss)
  g = np.asarray(jax.grad(lambda p: _run(term, p, gt, covis)[0])(jnp.asarray(pred)))
  np.testing.assert_array_equal(g[0, 0, 0], 0.0)
  np.testing.assert_allclose(g[0, 0, 1], np.array([0.6, 0.8]) / (2 + 1e-4), rtol=1e-6)
  loss, _, _ = _run(_term(kind="epe", multiplier=0.0, multiplier_applied=True), pred, gt, covis)
  assert float(loss) == 0.0
  smooth = _term(kind="epe", epe_eps=1e-3)
  g = np.asarray(jax.grad(lambda p: _run(smooth, p, gt, covis)[0])(jnp.asarray(gt)))
  assert np.all(np.isfinite(g))


def test_bce_hand_computed_stable_and_eps():
  logits = jnp.array([[[0.0, 2.0, -1.0, 1000.0, -1000.0]]])
  target = jnp.array([[[1, 1, 0, 0, 0]]], bool)
  valid = jnp.array([[[1, 1, 1, 0, 1]]], bool)
  term = losses.CovisibilityBCE()
  batch = {"covisibility": target, "covis_valid": valid}
  loss, logs, _ = term({"covisibility_logits": logits}, batch, {}, {})
  per = math.log(2) + math.log1p(math.exp(-2)) + math.log1p(math.exp(-1)) + 0.0
  assert float(logs["occlusion_ce"]) == pytest.approx(per / (4 + 1e-6), rel=1e-6)
  assert float(loss) == pytest.approx(10 * per / (4 + 1e-6), rel=1e-6)
  big = {"covisibility_logits": jnp.array([[[1000.0]]])}
  one = {"covisibility": jnp.zeros((1, 1, 1), bool), "covis_valid": jnp.ones((1, 1, 1), bool)}
  assert float(term(big, one, {}, {})[0]) == pytest.approx(10 * 1000 / (1 + 1e-6), rel=1e-6)
  g = jax.grad(lambda l: term({"covisibility_logits": l}, one, {}, {})[0])(
      big["covisibility_logits"])
  assert float(g[0, 0, 0]) == pytest.approx(10 / (1 + 1e-6), rel=1e-6)


def _config(**over):
  c = ml_collections.ConfigDict({
      "terms": ("robust_epe", "covisibility_ce"),
      "robust_epe": {"type": "robust", "alpha": 0.5, "c": 0.24},
      "covisibility_ce": {"type": "bce", "multiplier": 10.0}, "shared_cleanup": True})
  c.update(over)
  return c


def test_recipe_sums_terms_in_order_with_their_logs():
  recipe = losses.recipe_from_config(_config())
  out = {"flow": jnp.zeros((1, 1, 2, 2)), "covisibility_logits": jnp.zeros((1, 1, 2))}
  batch = {"flow": jnp.array([[[[3.0, 4.0], [0.0, 0.0]]]]),
           "covisibility": jnp.ones((1, 1, 2), bool), "covis_valid": jnp.ones((1, 1, 2), bool)}
  loss, aux = recipe(out, batch)
  flow = _rho(5.0) / (2 + 1e-4)
  bce = 10 * math.log(2) * 2 / (2 + 1e-6)
  assert float(aux["loss_robust_epe"]) == pytest.approx(flow, rel=1e-6)
  assert float(aux["loss_covisibility_ce"]) == pytest.approx(bce, rel=1e-6)
  assert float(loss) == pytest.approx(flow + bce, rel=1e-6)
  assert "robust_epe/px_robust_epe@non_occluded_mask" in aux
  assert "covisibility_ce/occlusion_ce" in aux
  # The refinement model's regressed flow is what the regression terms read (official training
  # mode returns it as flow.flow_output).
  out2 = dict(out, flow=jnp.ones((1, 1, 2, 2)), flow_before_refinement=out["flow"])
  assert float(recipe(out2, batch)[0]) == pytest.approx(flow + bce, rel=1e-6)


def test_recipe_config_errors_name_the_key():
  with pytest.raises(ValueError, match="unknown keys \\['alpah'\\]"):
    losses.recipe_from_config(_config(robust_epe={"type": "robust", "alpah": 0.5}))
  with pytest.raises(ValueError, match="type 'huber'"):
    losses.recipe_from_config(_config(robust_epe={"type": "huber"}))
  with pytest.raises(ValueError, match="without a config.loss.<name> block"):
    losses.recipe_from_config(_config(terms=("robust_epe", "epe")))
  with pytest.raises(ValueError, match="invalid_gt"):
    losses.recipe_from_config(_config(robust_epe={"type": "robust", "invalid_gt": "nan"}))


def test_official_yaml_entries_map_to_terms():
  assert losses.from_official("RobustRegressionLoss", {
      "multiplier": 1.0, "supervision_range": "all", "minimum_mask_threshold": 0.1,
      "fov_threshold": 0.25, "alpha": 0.5, "c": 0.24}) == {
          "type": "robust", "multiplier": 1.0, "range": "all", "margin": 0.25, "alpha": 0.5,
          "c": 0.24}
  assert losses.from_official("FlowEPELoss", {"multiplier": 0.0})["type"] == "epe"
  assert losses.from_official("CrossEntropyLoss", {
      "multiplier": 10, "target": "occlusion",
      "target_supervision_mask": "occlusion_supervision_mask"}) == {"type": "bce",
                                                                    "multiplier": 10.0}
  with pytest.raises(ValueError, match="fov_mask"):
    losses.from_official("FlowEPELoss", {"supervision_range": "fov_mask"})


def test_groups_average_per_group_losses_like_ddp():
  """loss.groups = N: the mean of N losses over consecutive row blocks (each with its own
  denominator), as N DDP workers average their gradients."""
  rng = np.random.default_rng(0)
  out = {"flow": jnp.asarray(rng.normal(size=(4, 3, 5, 2)), jnp.float32),
         "covisibility_logits": jnp.asarray(rng.normal(size=(4, 3, 5)), jnp.float32)}
  covis = rng.random((4, 3, 5)) < 0.5
  covis[:2] = rng.random((2, 3, 5)) < 0.9      # the groups differ in their pixel counts
  batch = {"flow": jnp.asarray(rng.normal(size=(4, 3, 5, 2)), jnp.float32),
           "covisibility": jnp.asarray(covis), "covis_valid": jnp.ones((4, 3, 5), bool)}
  pooled = losses.recipe_from_config(_config())
  grouped = losses.recipe_from_config(_config(groups=2))
  halves = [pooled({k: v[s] for k, v in out.items()}, {k: v[s] for k, v in batch.items()})[0]
            for s in (slice(0, 2), slice(2, 4))]
  total, aux = grouped(out, batch)
  assert float(total) == pytest.approx((float(halves[0]) + float(halves[1])) / 2, rel=1e-6)
  assert float(total) != pytest.approx(float(pooled(out, batch)[0]), rel=1e-4)
  assert aux["loss_robust_epe"].shape == ()
  with pytest.raises(ValueError, match="does not divide"):
    losses.recipe_from_config(_config(groups=3))(out, batch)


@pytest.mark.parametrize("recipe,rows", [("ufm560", 12), ("ufm980", 4), ("ufm560_refine", 6),
                                         ("ufm980_refine", 4)])
def test_recipes_take_one_loss_per_gpu_of_the_papers_8(recipe, rows):
  """"4 days on 8 H100 GPUs" (paper, Training Details): 8 loss groups of the official per-GPU
  rows (48 / 16 / 24 / 16 unique pairs per step over 8 GPUs, symmetrized), whatever the mesh."""
  from ufm_jax.training import config_lib
  config = config_lib.load_config(
      str(pathlib.Path(__file__).resolve().parents[1] / "configs" / f"{recipe}.py"))
  assert config.loss.groups == 8
  assert config.input.batch_size // config.loss.groups == rows
  losses.check_groups(config.input.batch_size, config.loss.groups, 1, 2)
  with pytest.raises(ValueError, match=rf"groups=8 .*batch of {config.input.batch_size + 2} "
                                       r"rows.*multiple of 16"):
    losses.check_groups(config.input.batch_size + 2, config.loss.groups, 1, 2)
