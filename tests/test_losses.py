"""Losses against closed-form values (paper eq. 2-3, supplementary robust-loss figure)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax import losses


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
  # At x = c: ((1/1.5)+1)^(1/4) = (5/3)^(1/4).
  assert got[2] == pytest.approx(3 * ((5 / 3) ** 0.25 - 1), rel=1e-6)
  assert got[0] == 0.0


def test_gradient_peak_and_tail_match_supplementary_figure():
  grad = jax.vmap(jax.grad(losses.robust_charbonnier))
  # Setting d^2/dx^2 = 0: (1+u) = (3/2) u with u = x^2/(1.5c^2) -> u = 2 -> x = c*sqrt(3).
  peak = 0.24 * math.sqrt(3.0)
  assert peak == pytest.approx(0.416, abs=5e-4)
  xs = jnp.linspace(0.0, 3.0, 30001)
  g = np.asarray(grad(xs))
  assert float(xs[np.argmax(g)]) == pytest.approx(peak, abs=2e-4)
  # Value at the peak: (sqrt(3)/c) * 3^(-3/4).
  assert g.max() == pytest.approx(math.sqrt(3) / 0.24 * 3**-0.75, rel=1e-4)
  g500 = float(grad(jnp.array([500.0]))[0])
  assert g500 == pytest.approx(_drho(500.0), rel=1e-5)
  assert g500 == pytest.approx(0.124, abs=1e-3)


def test_flow_loss_masked_mean_and_epe_pooling():
  pred = np.zeros((2, 2, 3, 2), np.float32)
  gt = np.zeros_like(pred)
  gt[0, 0, 0] = (3.0, 4.0)   # EPE 5, valid
  gt[0, 0, 1] = (0.24, 0.0)  # EPE c, valid
  gt[1, 1, 2] = (100., 0.)   # invalid: must not count
  valid = np.zeros((2, 2, 3), bool)
  valid[0, 0, :2] = True
  valid[1, 0, 0] = True      # EPE 0, valid
  got = float(losses.flow_loss(jnp.asarray(pred), jnp.asarray(gt), jnp.asarray(valid)))
  assert got == pytest.approx((_rho(5.0) + _rho(0.24) + 0.0) / 3, rel=1e-6)
  # No valid pixel at all: 0, not NaN.
  assert float(losses.flow_loss(pred, gt, np.zeros_like(valid))) == 0.0


def test_flow_loss_gradient_finite_at_zero_error():
  g = jax.grad(lambda p: losses.flow_loss(p, jnp.zeros((1, 1, 2, 2)), jnp.ones((1, 1, 2), bool)))(
      jnp.zeros((1, 1, 2, 2)))
  assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g) == 0)


def test_bce_hand_computed_and_stable():
  logits = jnp.array([[[0.0, 2.0, -1.0, 1000.0, -1000.0]]])
  target = jnp.array([[[1, 1, 0, 0, 0]]], bool)
  valid = jnp.array([[[1, 1, 1, 0, 1]]], bool)
  # -log(0.5), -log(sigmoid(2)), -log(1 - sigmoid(-1)), (masked), -log(1 - sigmoid(-1000)) = 0
  expect = (math.log(2) + math.log1p(math.exp(-2)) + math.log1p(math.exp(-1)) + 0.0) / 4
  got = float(losses.covisibility_bce(logits, target, valid))
  assert got == pytest.approx(expect, rel=1e-6)
  # A confidently wrong huge logit gives a large finite loss and a finite gradient.
  big = jnp.array([[[1000.0]]])
  assert float(losses.covisibility_bce(big, jnp.zeros((1, 1, 1), bool), jnp.ones((1, 1, 1), bool))) \
      == pytest.approx(1000.0)
  g = jax.grad(lambda l: losses.covisibility_bce(l, jnp.zeros((1, 1, 1), bool),
                                                 jnp.ones((1, 1, 1), bool)))(big)
  assert float(g[0, 0, 0]) == pytest.approx(1.0)


def test_total_is_flow_plus_ten_bce():
  out = {"flow": jnp.zeros((1, 1, 2, 2)), "covisibility_logits": jnp.zeros((1, 1, 2))}
  batch = {"flow": jnp.array([[[[3.0, 4.0], [0.0, 0.0]]]]),
           "covisibility": jnp.ones((1, 1, 2), bool), "flow_valid": jnp.ones((1, 1, 2), bool),
           "covis_valid": jnp.ones((1, 1, 2), bool)}
  loss, aux = losses.ufm_loss(out, batch)
  assert float(aux["loss_flow"]) == pytest.approx(_rho(5.0) / 2, rel=1e-6)
  assert float(aux["loss_covis"]) == pytest.approx(math.log(2), rel=1e-6)
  assert float(loss) == pytest.approx(_rho(5.0) / 2 + 10 * math.log(2), rel=1e-6)
  assert float(aux["epe"]) == pytest.approx(2.5)


def test_flow_supervision_covisible_vs_all_pixels():
  out = {"flow": jnp.zeros((1, 1, 2, 2)), "covisibility_logits": jnp.zeros((1, 1, 2))}
  batch = {"flow": jnp.array([[[[3.0, 4.0], [0.24, 0.0]]]]),
           "covisibility": jnp.array([[[False, True]]]), "flow_valid": jnp.ones((1, 1, 2), bool),
           "covis_valid": jnp.ones((1, 1, 2), bool)}
  _, aux = losses.ufm_loss(out, batch)  # paper eq. 2: covisible pixels only
  assert float(aux["loss_flow"]) == pytest.approx(_rho(0.24), rel=1e-6)
  _, aux = losses.ufm_loss(out, batch, flow_pixels="all")  # the 980 bootstrap
  assert float(aux["loss_flow"]) == pytest.approx((_rho(5.0) + _rho(0.24)) / 2, rel=1e-6)
  with pytest.raises(ValueError, match="flow_pixels"):
    losses.ufm_loss(out, batch, flow_pixels="some")
