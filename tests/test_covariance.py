"""The flow covariance's closed forms (ufm_jax.models.covariance), the NLL loss term, the calibration
metrics on constructed cases with answers derived by hand, and the synthetic cov config training
a few steps with its NLL finite and reaching the covariance head."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from ufm_jax.evaluators import metrics
from ufm_jax.training import config_lib, losses, trainer
from ufm_jax.data import synthetic
from ufm_jax.models import covariance


def _exp_tanh_inputs():
  # var_x = 1, var_y = 4, rho = 0.5: cov_xy = 0.5 * sqrt(1 * 4) = 1, |Sigma| = 4 - 1 = 3
  return np.array([[0.0, math.log(4.0), math.atanh(0.5)]])


@pytest.mark.parametrize("low", [False, True])
def test_exp_tanh_by_hand(low):
  x = _exp_tanh_inputs() - (8.0 if low else 0.0) * np.array([1, 1, 0])
  out = covariance.adaptor(x, covariance.CovarianceConfig(low_confidence_init=low))
  np.testing.assert_allclose(out["flow_covariance"], [[1.0, 4.0, 1.0]], rtol=1e-12)
  np.testing.assert_allclose(out["flow_covariance_log_det"], [math.log(3.0)], rtol=1e-7)
  np.testing.assert_allclose(out["flow_covariance_inv"], [[4 / 3, 1 / 3, -1 / 3]], rtol=1e-7)
  np.testing.assert_allclose(covariance.inverse(out["flow_covariance"]), [[4 / 3, 1 / 3, -1 / 3]],
                             rtol=1e-12)
  np.testing.assert_allclose(out["flow_covariance_params"], _exp_tanh_inputs(), atol=1e-12)


def test_unknown_parametrization_is_refused():
  with pytest.raises(ValueError, match="'cholesky' is not supported"):
    covariance.CovarianceConfig(parametrization="cholesky")


def test_closed_forms_against_the_matrix():
  rng = np.random.default_rng(0)
  params = rng.normal(size=(50, 3)) * [2, 2, 1.5]
  r = rng.normal(size=(50, 2)) * 3
  cov = covariance.adaptor(params, covariance.CovarianceConfig())["flow_covariance"]
  m = covariance.matrices(cov)
  want_quad = np.einsum("ni,nij,nj->n", r, np.linalg.inv(m), r)
  quad, log_det = covariance.quadratic_and_log_det(params, r)
  np.testing.assert_allclose(quad, want_quad, rtol=1e-9)
  np.testing.assert_allclose(log_det, np.linalg.slogdet(m)[1], rtol=1e-9)
  np.testing.assert_allclose(covariance.mahalanobis_sq(cov, r), want_quad, rtol=1e-8)
  # the full 2D Gaussian NLL: -log N(r; 0, Sigma)
  want_nll = 0.5 * want_quad + 0.5 * np.linalg.slogdet(m)[1] + math.log(2 * math.pi)
  np.testing.assert_allclose(covariance.gaussian_nll(params, r, constant=True), want_nll,
                             rtol=1e-9)
  big, small = covariance.eigenvalues(cov)
  np.testing.assert_allclose(np.stack([small, big], -1), np.linalg.eigvalsh(m), rtol=1e-9)
  # diag(9, 4) rotated by 30 degrees: sigma_max = 3 px
  c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
  rot = np.array([[c, -s], [s, c]]) @ np.diag([9.0, 4.0]) @ np.array([[c, s], [-s, c]])
  np.testing.assert_allclose(covariance.sigma_max(np.array([rot[0, 0], rot[1, 1], rot[0, 1]])),
                             3.0, rtol=1e-12)
  scaled = covariance.rescale(np.array([1.0, 4.0, 1.0]), 2.0, 0.5)
  np.testing.assert_allclose(scaled, [4.0, 1.0, 1.0])


def test_float32_forms_stay_finite_where_rho_rounds_to_one():
  """s = 12: tanh(s) is 1 in float32, so 1 - rho^2 is 0 there; the loss's forms use cosh."""
  params = jnp.array([[0.0, 0.0, 12.0]], jnp.float32)
  r = jnp.array([[1.0, -1.0]], jnp.float32)
  quad, log_det = covariance.quadratic_and_log_det(params, r)
  cosh2 = math.cosh(12.0) ** 2
  np.testing.assert_allclose(float(quad[0]), (2 + 2 * math.tanh(12.0)) * cosh2, rtol=1e-4)
  np.testing.assert_allclose(float(log_det[0]), -math.log(cosh2), rtol=1e-5)
  g = jax.grad(lambda p: covariance.gaussian_nll(p, r).sum())(params)
  assert np.isfinite(np.asarray(g)).all()


# --------------------------------------------------------------------------- the loss term


def _outputs_and_batch(flow_value, params_value, h=4, w=5):
  flow = jnp.full((1, h, w, 2), flow_value, jnp.float32)
  out = {"flow": flow, "flow_covariance_params": jnp.broadcast_to(
      jnp.asarray(params_value, jnp.float32), (1, h, w, 3))}
  covis = np.ones((1, h, w), bool)
  covis[0, 0] = False                      # a row the flow term does not supervise
  batch = {"flow": jnp.zeros((1, h, w, 2), jnp.float32), "covisibility": jnp.asarray(covis),
           "covis_valid": jnp.ones((1, h, w), bool), "flow_valid": jnp.ones((1, h, w), bool)}
  return out, batch


def _recipe(**nll):
  return losses.recipe_from_config({
      "terms": ("robust_epe", "flow_nll"), "robust_epe": {"type": "epe"},
      "flow_nll": {"type": "flow_nll", "pixels": "robust_epe", **nll}})


def test_nll_term_by_hand_on_the_supervised_pixels():
  # r = (1, 1), Sigma = diag(e^0, e^(ln 4)) = diag(1, 4): 0.5 (1 + 1/4) + 0.5 ln 4
  out, batch = _outputs_and_batch(1.0, [0.0, math.log(4.0), 0.0])
  loss, aux = _recipe(eps=None)(out, batch)
  want = 0.5 * 1.25 + 0.5 * math.log(4.0)
  np.testing.assert_allclose(float(aux["loss_flow_nll"]), want, rtol=1e-6)
  np.testing.assert_allclose(float(aux["flow_nll/mahalanobis_sq"]), 1.25, rtol=1e-6)
  np.testing.assert_allclose(float(loss), float(aux["loss_robust_epe"]) + want, rtol=1e-6)
  # the mask is the flow term's: NaN flow on the unsupervised row changes nothing
  out2 = dict(out, flow_covariance_params=out["flow_covariance_params"].at[0, 0].set(jnp.nan))
  np.testing.assert_allclose(float(_recipe(eps=None)(out2, batch)[1]["loss_flow_nll"]), want,
                             rtol=1e-6)


@pytest.mark.parametrize("detach", [True, False])
def test_detach_flow_decides_whether_the_nll_reaches_the_flow(detach):
  out, batch = _outputs_and_batch(1.0, [0.0, 0.0, 0.3])
  recipe = losses.recipe_from_config({
      "terms": ("robust_epe", "flow_nll"), "robust_epe": {"type": "epe", "multiplier": 0.0,
                                                         "multiplier_applied": True},
      "flow_nll": {"type": "flow_nll", "detach_flow": detach}})
  g = jax.grad(lambda o: recipe(o, batch)[0])(out)
  assert np.abs(np.asarray(g["flow_covariance_params"])).max() > 0
  flow_grad = np.abs(np.asarray(g["flow"])).max()
  assert (flow_grad == 0) if detach else (flow_grad > 0)


def test_laplace_density_integrates_to_one_with_covariance_sigma():
  """exp(-laplace_nll_from(d^2, log|Sigma|, constant=True)) on a fine grid (|r| < 60 px, where the
  tail left out is below 1e-12): total mass 1 and second moment Sigma = (1, 4, 1)."""
  cov = np.array([1.0, 4.0, 1.0])
  x = np.linspace(-60, 60, 2401)
  rx, ry = np.meshgrid(x, x, indexing="ij")
  r = np.stack([rx, ry], -1)
  d2 = covariance.mahalanobis_sq(np.broadcast_to(cov, r.shape[:2] + (3,)), r)
  p = np.exp(-covariance.laplace_nll_from(d2, math.log(3.0), constant=True))
  cell = (x[1] - x[0]) ** 2
  np.testing.assert_allclose(p.sum() * cell, 1.0, atol=1e-4)
  second = [(p * rx * rx).sum() * cell, (p * ry * ry).sum() * cell, (p * rx * ry).sum() * cell]
  np.testing.assert_allclose(second, cov, rtol=2e-3)


def test_laplace_nll_term_by_hand_and_finite_where_the_residual_is_zero():
  # r = (1, 1), Sigma = diag(1, 4): d = sqrt(1.25); sqrt(3) d + 0.5 ln 4
  out, batch = _outputs_and_batch(1.0, [0.0, math.log(4.0), 0.0])
  _, aux = _recipe(eps=None, likelihood="laplace")(out, batch)
  np.testing.assert_allclose(float(aux["loss_flow_nll"]),
                             math.sqrt(3 * 1.25) + 0.5 * math.log(4.0), rtol=1e-6)
  exact, batch = _outputs_and_batch(0.0, [0.5, 0.5, 0.2])    # r = 0 on every pixel
  recipe = _recipe(likelihood="laplace")
  g = jax.grad(lambda p: recipe(dict(exact, flow_covariance_params=p), batch)[0])(
      exact["flow_covariance_params"])
  assert np.isfinite(np.asarray(g)).all()
  with pytest.raises(ValueError, match="likelihood='student'"):
    _recipe(likelihood="student")


def test_nll_term_errors_name_what_is_missing():
  out, batch = _outputs_and_batch(1.0, [0.0, 0.0, 0.0])
  with pytest.raises(ValueError, match="pixels='epe_all' names no flow term"):
    _recipe(pixels="epe_all")(out, batch)
  with pytest.raises(ValueError, match="predicts no flow covariance"):
    _recipe()({"flow": out["flow"]}, batch)


# --------------------------------------------------------------------------- calibration metrics


def test_calibration_of_exact_gaussians():
  """Residuals drawn from the predicted Gaussian: coverage 100 (1 - e^(-k^2/2)) = 39.35, 86.47,
  98.89 %; mean NLL = E[0.5 d^2] + 0.5 log|Sigma| + log 2 pi = 1 + 0.5 log 3 + log 2 pi."""
  rng = np.random.default_rng(1)
  n = 400_000
  sigma = np.array([[1.0, 1.0], [1.0, 4.0]])          # (var_x, var_y, cov_xy) = (1, 4, 1)
  r = rng.multivariate_normal([0, 0], sigma, size=n).reshape(400, 1000, 2)
  gt = rng.normal(size=(400, 1000, 2)) * 5
  cov = np.broadcast_to(np.array([1.0, 4.0, 1.0]), (400, 1000, 3))
  acc, sp = metrics.Pooled(), metrics.Sparsification()
  metrics.add_calibration(acc, sp, gt + r, gt, cov, np.ones((400, 1000), bool))
  res = acc.result()
  for k, want in ((1, 39.347), (2, 86.466), (3, 98.889)):
    assert abs(res[f"coverage_{k}sigma"] - want) < 0.3, (k, res)
  assert abs(res["nll"] - (1 + 0.5 * math.log(3) + math.log(2 * math.pi))) < 0.01, res
  assert res["nll_laplace"] > res["nll"] + 0.05, res   # a Gaussian's residuals: it fits worse


def test_calibration_of_exact_laplaces():
  """Residuals drawn from the elliptical Laplace with covariance Sigma = (1, 4, 1): d is
  Gamma(2, rate sqrt 3), so coverage 100 (1 - (1 + sqrt(3) k) e^(-sqrt(3) k)) = 51.66, 86.03,
  96.57 %; mean nll_laplace = E[sqrt(3) d] + 0.5 log 3 + log(2 pi / 3) = 2 + ..., and the
  Gaussian's `nll` of the same residuals is larger (the Laplace fits them better)."""
  rng = np.random.default_rng(2)
  n = 400_000
  d = rng.gamma(2.0, 1 / math.sqrt(3), size=n)
  theta = rng.uniform(0, 2 * math.pi, size=n)
  w = np.stack([d * np.cos(theta), d * np.sin(theta)], -1)
  chol = np.linalg.cholesky(np.array([[1.0, 1.0], [1.0, 4.0]]))
  r = (w @ chol.T).reshape(400, 1000, 2)
  gt = np.zeros((400, 1000, 2))
  cov = np.broadcast_to(np.array([1.0, 4.0, 1.0]), (400, 1000, 3))
  acc, sp = metrics.Pooled(), metrics.Sparsification()
  metrics.add_calibration(acc, sp, gt + r, gt, cov, np.ones((400, 1000), bool))
  res = acc.result()
  for k, want in ((1, 51.66), (2, 86.03), (3, 96.57)):
    assert abs(res[f"coverage_{k}sigma"] - want) < 0.3, (k, res)
  want_laplace = 2 + 0.5 * math.log(3) + math.log(2 * math.pi / 3)
  assert abs(res["nll_laplace"] - want_laplace) < 0.01, res
  assert res["nll"] > res["nll_laplace"] + 0.05, res


def test_calibration_stays_finite_where_rho_rounds_to_one_in_float32():
  """A float32 triplet from s = 12 (var 1, 4): cov_xy^2 rounds to var_x var_y or above it, so the
  plain determinant is 0 or negative. Its floor (1 - rho^2 >= 1e-8, the official epsilon) keeps
  the bench's NLL finite, and a residual along the ellipse's long axis stays inside 1 sigma."""
  cov = covariance.adaptor(np.array([[0.0, math.log(4.0), 12.0]], np.float32),
                           covariance.CovarianceConfig())["flow_covariance"].astype(np.float32)
  assert cov[0, 0] * cov[0, 1] - cov[0, 2] ** 2 <= 0
  det = covariance.determinant(cov.astype(np.float64))
  np.testing.assert_allclose(det, 1e-8 * 4.0, rtol=1e-6)
  flow_gt = np.zeros((1, 2, 2))
  flow = np.array([[[0.0, 0.0], [0.5, 1.0]]])          # r = 0 and r = (0.5, 1), on the long axis
  acc, sp = metrics.Pooled(), metrics.Sparsification()
  metrics.add_calibration(acc, sp, flow, flow_gt, np.broadcast_to(cov, (1, 2, 3)),
                          np.ones((1, 2), bool))
  res = acc.result()
  assert np.isfinite(res["nll"]) and np.isfinite(res["nll_laplace"]), res
  assert res["coverage_1sigma"] == 100.0, res


def test_sparsification_by_hand():
  """EPE (0, 0, 0, 4). On the grid f = 0, 0.01, ..., 0.99, a curve with values v0..v3 on the
  quarters has trapezoid area 0.25 (v0 + v1 + v2 + v3) - 0.005 (v0 + v3). Oracle (1, 0, 0, 0):
  0.245. Random (flat at the mean 1): 0.99, so ause_random = 0.745. Uncertainty in the worst
  order (the error-free pixels first, 4 last): (1, 4/3, 2, 4): 2.058333, ause = 1.813333. In the
  oracle's order: 0. One image: per image and pooled agree."""
  epe = np.array([0.0, 0.0, 0.0, 4.0])
  for unc, want in ((np.array([1.0, 2.0, 3.0, 0.0]), 1.813333333), (epe + 1, 0.0)):
    sp = metrics.Sparsification()
    sp.add(epe, unc)
    res = sp.result()
    for pooling in ("", "_pooled"):
      np.testing.assert_allclose(res[f"ause{pooling}"], want, atol=1e-9)
      np.testing.assert_allclose(res[f"ause{pooling}_random"], 0.745, atol=1e-9)


def test_per_image_and_pooled_sparsification_of_two_images_by_hand():
  """Ilg et al.'s per-image AUSE against the pooled one, on 2 images of 4 pixels.

  On the grid f = i / 100, i = 0..99, the implementation removes floor(f n) pixels. A curve that
  is v_k where k pixels are removed, on n_k grid points, has trapezoid area
  0.01 (sum_k n_k v_k - (v_first + v_last) / 2) (each block of n_k points gives n_k - 1 steps of
  v_k, each junction a step of the two values' mean).

  n = 4: k = 0, 1, 2, 3 on 25 points each (f in [0, 0.25), [0.25, 0.5), ...).
    Image A: EPE (1, 2, 3, 4), uncertainty (4, 1, 2, 3): removes EPE 1, 4, 3 in turn.
      curve (2.5, 3, 2.5, 2), oracle (removes 4, 3, 2) (2.5, 2, 1.5, 1), difference (0, 1, 1, 1):
      0.01 (25 * 3 - (0 + 1) / 2) = 0.745. Random: flat 2.5, difference (0, 0.5, 1, 1.5):
      0.01 (25 * 3 - 1.5 / 2) = 0.7425.
    Image B: EPE (0, 0, 0, 8), uncertainty (1.5, 2.5, 3.5, 9): the oracle's order, 0. Random: flat
      2, oracle (2, 0, 0, 0), difference (0, 2, 2, 2): 0.01 (25 * 6 - 2 / 2) = 1.49.
    ause = (0.745 + 0) / 2 = 0.3725, ause_random = (0.7425 + 1.49) / 2 = 1.11625.
  Pooled, n = 8: k = floor(8 i / 100) on 13, 12, 13, 12, 13, 12, 13, 12 points. By uncertainty
  (9, 4, 3.5, 3, 2.5, 2, 1.5, 1) the EPE removed is 8, 1, 0, 4, 0, 3, 0 (sum 18):
    curve  18/8, 10/7, 9/6, 9/5, 5/4, 5/3, 2/2, 2/1
    oracle 18/8, 10/7, 6/6, 3/5, 1/4, 0, 0, 0 (removes 8, 4, 3, 2, 1, 0, 0)
    difference (0, 0, 0.5, 1.2, 1, 5/3, 1, 2): 0.01 (90.9 - 1) = 0.899;
    random, flat 18/8 = 2.25: difference (0, 2.25 - 10/7, 1.25, 1.65, 2, 2.25, 2.25, 2.25):
    0.01 (12 (2.25 - 10/7) + 13 * 1.25 + 12 * 1.65 + 13 * 2 + 12 * 2.25 + 13 * 2.25 + 12 * 2.25
    - 2.25 / 2)."""
  sp = metrics.Sparsification()
  sp.add(np.array([1.0, 2.0, 3.0, 4.0]), np.array([4.0, 1.0, 2.0, 3.0]))
  sp.add(np.array([0.0, 0.0, 0.0, 8.0]), np.array([1.5, 2.5, 3.5, 9.0]))
  res = sp.result()
  np.testing.assert_allclose(res["ause"], 0.3725, atol=1e-12)
  np.testing.assert_allclose(res["ause_random"], 1.11625, atol=1e-12)
  np.testing.assert_allclose(res["ause_pooled"], 0.899, atol=1e-12)
  pooled_random = 0.01 * (12 * (2.25 - 10 / 7) + 13 * 1.25 + 12 * 1.65 + 13 * 2 + 12 * 2.25
                          + 13 * 2.25 + 12 * 2.25 - 2.25 / 2)
  np.testing.assert_allclose(res["ause_pooled_random"], pooled_random, atol=1e-12)


def test_pooled_and_per_image_sparsification():
  """Two images of uniform error (1 px and 3 px, 100 pixels each), the uncertainty ranking the
  images: per image there is nothing to rank (every area 0); pooled, the order is the oracle's
  (ause_pooled 0), and a random order, flat at the mean 2, is not: f = i / 100 removes
  k = floor(200 f) pixels (2i, or 2i - 1 where the float64 f * 200 rounds below 2i, e.g. i = 29),
  the oracle's 3 px ones first, so oracle = (3 (100 - k) + 100) / (200 - k) for k <= 100 and 1
  after. The pooled histograms agree with an exact sort of all pixels."""
  sp = metrics.Sparsification()
  sp.add(np.ones((10, 10)), np.full((10, 10), 1.0))
  sp.add(np.full((10, 10), 3.0), np.full((10, 10), 9.0))
  res = sp.result()
  assert res["ause"] == 0 and res["ause_random"] == 0
  k = np.floor(np.arange(100) / 100 * 200)
  oracle = np.where(k <= 100, (3 * (100 - k) + 100) / (200 - k), 1.0)
  want = sum((4 - oracle[j] - oracle[j + 1]) / 2 * 0.01 for j in range(99))
  assert abs(res["ause_pooled"]) < 1e-12
  np.testing.assert_allclose(res["ause_pooled_random"], want, atol=1e-12)
  rng = np.random.default_rng(0)
  sp, es, us = metrics.Sparsification(), [], []
  for i in range(10):
    e = np.abs(rng.normal(size=(30, 40))) * (1 + i)
    u = e * np.exp(rng.normal(size=e.shape))
    sp.add(e, u)
    es.append(e.ravel())
    us.append(u.ravel())
  e, u = np.concatenate(es), np.concatenate(us)
  f = metrics.Sparsification.FRACTIONS
  oracle = metrics.Sparsification.curve(e, e)
  res = sp.result()
  np.testing.assert_allclose(res["ause_pooled"], np.trapezoid(
      metrics.Sparsification.curve(e, u) - oracle, f), rtol=1e-3)
  np.testing.assert_allclose(res["ause_pooled_random"], np.trapezoid(e.mean() - oracle, f),
                             rtol=1e-3)


# --------------------------------------------------------------------------- the recipe switch


@pytest.mark.slow
def test_synthetic_cov_config_trains_and_its_nll_reaches_the_head():
  """configs/synthetic.py:cov=True at 28 px: the model has the covariance before the covisibility
  in its uncertainty head (sorted, low_confidence_init); three Adam steps of the config's loss
  keep flow_nll finite, and the NLL alone has a gradient on the head's covariance channels and
  none on the flow head (detach_flow) or the covisibility channel."""
  config = config_lib.load_config("configs/synthetic.py:cov=True,size=28,eval=False")
  model = trainer.build_model(config)
  cfg = model.config
  assert cfg.uncertainty_head_adaptors == ("flow_cov", "non_occluded_mask")
  assert cfg.flow_covariance.low_confidence_init and cfg.covisibility_head.output_dim == 4
  scfg = synthetic.SyntheticConfig(size=(28, 28), pair_type="shift", max_shift=4)
  rows = [s for seed in (1, 2) for s in synthetic.generate_pair(seed, scfg)]   # (a, b), (b, a)
  keys = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")
  batch = {k: jnp.asarray(np.stack([r[k] for r in rows])) for k in keys}
  recipe = losses.recipe_from_config(config.loss)
  params = trainer.init_params(model, (28, 28), jax.random.PRNGKey(0))

  def loss_fn(p):
    out = model.apply({"params": p}, batch["image0"], batch["image1"], **config.apply_kwargs)
    total, aux = recipe(out, batch)
    return total, aux

  @jax.jit
  def step(p):   # one compile: the total's value and gradient, and the NLL's gradient alone
    (loss, aux), g = jax.value_and_grad(loss_fn, has_aux=True)(p)
    g_nll = jax.grad(lambda q: loss_fn(q)[1]["loss_flow_nll"])(p)
    return loss, aux, g, g_nll

  tx = optax.adam(1e-3)
  opt = tx.init(params)
  for _ in range(3):
    loss, aux, g, g_nll = step(params)
    assert np.isfinite(float(loss)) and np.isfinite(float(aux["loss_flow_nll"])), aux
    updates, opt = tx.update(g, opt)
    params = optax.apply_updates(params, updates)
  last = np.asarray(g_nll["uncertainty_head_0_1"]["conv2_2"]["kernel"])   # [1, 1, in, 4]
  assert np.abs(last[..., :3]).max() > 0 and np.abs(last[..., 3]).max() == 0
  assert all(np.abs(np.asarray(x)).max() == 0 for x in jax.tree.leaves(g_nll["head1_0_1"]))


@pytest.mark.parametrize("recipe,pixels", [("ufm560", "robust_epe"), ("ufm980", "epe_all")])
def test_full_size_recipes_with_cov_build(recipe, pixels):
  """configs/ufm560.py:cov=True and configs/ufm980.py:cov=True build their full-size model
  (traced by jax.eval_shape at 420x560: no compute) with the covariance in the uncertainty head,
  the NLL term on the recipe's flow pixels, and the uncertainty head trained (the 980 recipe
  freezes it without cov)."""
  config = config_lib.load_config(f"configs/{recipe}.py:cov=True")
  model = trainer.build_model(config)
  assert model.config.uncertainty_head_adaptors == ("flow_cov", "non_occluded_mask")
  assert model.config.flow_covariance.low_confidence_init
  assert config.loss.terms[-1] == "flow_nll" and config.loss.flow_nll.pixels == pixels
  recipe_fn = losses.recipe_from_config(config.loss)   # every term builds
  assert recipe_fn is not None
  x = jax.ShapeDtypeStruct((1, 420, 560, 3), jnp.uint8)
  variables = jax.eval_shape(lambda a: trainer.init_variables(model, (420, 560), a),
                             jax.random.PRNGKey(0))
  out = jax.eval_shape(lambda v, a, b: model.apply(v, a, b), variables, x, x)
  assert out["flow_covariance"].shape == (1, 420, 560, 3)
  assert out["flow_covariance_params"].shape == (1, 420, 560, 3)
  assert out["covisibility"].shape == (1, 420, 560)
  assert config.optim.lr.uncertainty_head > 0   # the covariance trains


# --------------------------------------------------------------------------- model_init


def test_model_init_adds_a_covariance_head_to_a_model_without_one(tmp_path):
  """A released model (no covariance) initialises a cov=True model: every tensor loads but the
  uncertainty head's last convolution, whose covisibility channel (now channel 3) takes the
  source's channel 0 and whose covariance channels stay as initialised; two covariances that
  disagree (low_confidence_init) are refused by name."""
  from flax import traverse_util

  from ufm_jax import testing
  from ufm_jax.training import model_init
  from ufm_jax.models import ufm
  from ufm_jax.official import config as official_config
  from ufm_jax.official import keymap
  base_cfg = testing.official_small_config()
  base = ufm.model_from_config(base_cfg)
  params = testing.perturbed_params(base, 4)
  state = keymap.state_dict_from_params(params, official_config.ufm_buffers(base_cfg))
  testing.write_snapshot(tmp_path / "snap", official_config.official_config_dict(base_cfg), state)
  cfg = ufm.with_flow_covariance(base_cfg)
  template = {"params": testing.perturbed_params(ufm.model_from_config(cfg), 5)}
  out, rep = model_init.load_init_variables(f"snapshot:{tmp_path / 'snap'}", template, cfg)
  assert not rep.left_at_init and not rep.unused
  assert sorted(r.split(" ")[0] for r in rep.resized) == ["uncertainty_head_0_1/conv2_2/bias",
                                                          "uncertainty_head_0_1/conv2_2/kernel"]
  assert "flow_cov left at init" in rep.resized[0]
  got = np.asarray(out["params"]["uncertainty_head_0_1"]["conv2_2"]["kernel"])
  fresh = template["params"]["uncertainty_head_0_1"]["conv2_2"]["kernel"]
  src = params["uncertainty_head_0_1"]["conv2_2"]["kernel"]
  np.testing.assert_array_equal(got[..., 3], src[..., 0])
  np.testing.assert_array_equal(got[..., :3], fresh[..., :3])
  flat = traverse_util.flatten_dict(out["params"], sep="/")
  np.testing.assert_array_equal(flat["head1_0_1/conv2_2/kernel"],
                                params["head1_0_1"]["conv2_2"]["kernel"])
  # a covariance on both sides must be the same parametrisation
  testing.write_snapshot(tmp_path / "cov", official_config.official_config_dict(cfg),
                         keymap.state_dict_from_params(template["params"],
                                                       official_config.ufm_buffers(cfg)))
  other = ufm.with_flow_covariance(base_cfg, low_confidence_init=False)
  with pytest.raises(ValueError, match="flow_covariance.low_confidence_init: source True"):
    model_init.load_init_variables(f"snapshot:{tmp_path / 'cov'}", template, other)
