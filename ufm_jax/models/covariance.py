"""Flow covariance: the one home of its parametrisation and closed forms.

A model with UniCeption's `Covariance2DAdaptor` predicts, per source pixel, the 2x2 covariance of
the flow's end point in the target, stored channel-last as [..., 3] = (var_x, var_y, cov_xy) in
px^2 (x right, y down, like the flow):

    Sigma = [[var_x,  cov_xy],
             [cov_xy, var_y ]]

Parametrisation "exp_tanh" (uniception/models/prediction_heads/adaptors.py:1099-1139 at ee7fa0b):
the head's channels (c1, c2, s), with `low_confidence_init` adding 8 to c1 and c2 first (so a
fresh head starts at a variance of e^8 ~ 3000 px^2, a 55 px standard deviation, and its NLL is
small and flat), give

    var_x = e^c1,  var_y = e^c2,  rho = tanh(s),  cov_xy = rho e^((c1 + c2) / 2)
    log|Sigma| = c1 + c2 + log(1 - rho^2)
    Sigma^-1 = 1 / (1 - rho^2) [[e^-c1, -rho e^-((c1 + c2) / 2)], [., e^-c2]]

The model's outputs follow the official formulas (log det with its + 1e-8 inside the log), so that
they match the official ones; `params` = (c1, c2, s) after the offset are what the loss works on.
The training NLL (`gaussian_nll`) uses forms that stay finite where rho^2 rounds to 1: with the
whitened residual u = r_x e^(-c1/2), v = r_y e^(-c2/2),

    r^T Sigma^-1 r = (u^2 + v^2 - 2 rho u v) cosh(s)^2,   log(1 - rho^2) = -2 log cosh(s).

The numpy helpers below (inverse, Mahalanobis distance, eigenvalues, rescaling, 2x2 matrices) take
the (var_x, var_y, cov_xy) triplet, whichever parametrisation produced it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

PARAMETRIZATIONS = ("exp_tanh",)
# adaptors.py:1122-1123: `low_confidence_init` adds 8 to c1 and c2.
LOW_CONFIDENCE_OFFSET = 8.0
# adaptors.py:1130, 1132: added to 1 - tanh(s)^2 inside the official log and reciprocal.
OFFICIAL_EPS = 1e-8
LOG_2PI = math.log(2.0 * math.pi)
# The elliptical Laplace with covariance Sigma: p(r) = 3 / (2 pi |Sigma|^(1/2)) e^(-sqrt(3) d).
SQRT3 = math.sqrt(3.0)
LOG_2PI_OVER_3 = math.log(2.0 * math.pi / 3.0)
LIKELIHOODS = ("gaussian", "laplace")


@dataclasses.dataclass(frozen=True)
class CovarianceConfig:
  """The official Covariance2DAdaptor's kwargs (`parametrization`, `low_confidence_init`)."""
  parametrization: str = "exp_tanh"
  low_confidence_init: bool = False   # the official default

  def __post_init__(self):
    if self.parametrization not in PARAMETRIZATIONS:
      raise ValueError(f"flow covariance parametrization {self.parametrization!r} is not "
                       f"supported (expected one of {', '.join(PARAMETRIZATIONS)})")


def _xp(*arrays):
  """jax.numpy for jax arrays and tracers, numpy otherwise (no jax import for numpy callers)."""
  if any(type(a).__module__.startswith("jax") for a in arrays):
    import jax.numpy as jnp
    return jnp
  return np


def adaptor(x, cfg: CovarianceConfig) -> dict:
  """The head's 3 channels [..., 3] -> {"flow_covariance" [..., 3], "flow_covariance_inv" [..., 3]
  (the precision, as a triplet), "flow_covariance_log_det" [...], "flow_covariance_params"
  [..., 3] = (log var_x, log var_y, s)}, as the official adaptor computes them (float32 like its
  inputs; the inverse from the parameters, not from the triplet, whose determinant cancels when
  |rho| nears 1)."""
  xp = _xp(x)
  c1, c2, s = x[..., 0], x[..., 1], x[..., 2]
  if cfg.low_confidence_init:
    c1, c2 = c1 + LOW_CONFIDENCE_OFFSET, c2 + LOW_CONFIDENCE_OFFSET
  rho = xp.tanh(s)
  cov = xp.stack([xp.exp(c1), xp.exp(c2), rho * xp.exp((c1 + c2) / 2)], axis=-1)
  # 1 - tanh(s)^2 as sech(s)^2: in float32 the difference cancels where |rho| nears 1, and XLA's
  # tanh there is a few ulps off (a 1% error in log det at rho = 0.99999 against torch's).
  one_minus = xp.exp(-2 * _log_cosh(s, xp)) + OFFICIAL_EPS
  log_det = c1 + c2 + xp.log(one_minus)
  inv = xp.stack([xp.exp(-c1), xp.exp(-c2), -rho * xp.exp(-(c1 + c2) / 2)], axis=-1)
  return {"flow_covariance": cov, "flow_covariance_inv": inv / one_minus[..., None],
          "flow_covariance_log_det": log_det,
          "flow_covariance_params": xp.stack([c1, c2, s], axis=-1)}


def _log_cosh(s, xp):
  a = xp.abs(s)
  return a + xp.log1p(xp.exp(-2 * a)) - math.log(2.0)


def quadratic_and_log_det(params, r):
  """(r^T Sigma^-1 r, log|Sigma|) [...] from `params` (c1, c2, s) [..., 3] and residuals r
  [..., 2], in the forms that stay finite for any s (module docstring)."""
  xp = _xp(params, r)
  c1, c2, s = params[..., 0], params[..., 1], params[..., 2]
  u, v = r[..., 0] * xp.exp(-c1 / 2), r[..., 1] * xp.exp(-c2 / 2)
  log_cosh = _log_cosh(s, xp)
  quad = (xp.square(u) + xp.square(v) - 2 * xp.tanh(s) * u * v) * xp.exp(2 * log_cosh)
  return quad, c1 + c2 - 2 * log_cosh


def gaussian_nll(params, r, constant: bool = False):
  """0.5 r^T Sigma^-1 r + 0.5 log|Sigma| per pixel (+ log 2 pi with `constant`: the full negative
  log-likelihood of a 2D Gaussian, in nats)."""
  quad, log_det = quadratic_and_log_det(params, r)
  return 0.5 * quad + 0.5 * log_det + (LOG_2PI if constant else 0.0)


def laplace_nll_from(quad, log_det, constant: bool = False):
  """sqrt(3 r^T Sigma^-1 r) + 0.5 log|Sigma| (+ log(2 pi / 3) with `constant`): the negative
  log-likelihood of the 2D elliptical Laplace whose covariance is Sigma,

    p(r) = 3 / (2 pi |Sigma|^(1/2)) exp(-sqrt(3) d),   d^2 = r^T Sigma^-1 r,

  (d is Gamma(2, sqrt 3) distributed: E[d^2] = 2, the same Sigma as a Gaussian's). Its gradient
  in Sigma weighs a residual by d rather than d^2, so a few large errors pull a pixel's variance
  less. The square root's gradient at d = 0 is taken as 0 (a pixel with r = 0 exactly)."""
  xp = _xp(quad, log_det)
  pos = quad > 0
  d = xp.where(pos, xp.sqrt(xp.where(pos, quad, 1.0)), 0.0)
  return SQRT3 * d + 0.5 * log_det + (LOG_2PI_OVER_3 if constant else 0.0)


# --------------------------------------------------------------------------------------------
# On the (var_x, var_y, cov_xy) triplet


def determinant(cov):
  """|Sigma| [...] = var_x var_y - cov_xy^2 = var_x var_y (1 - rho^2), with 1 - rho^2 floored at
  OFFICIAL_EPS (1e-8, what the official adaptor adds to it). A float32 triplet resolves 1 - rho^2
  only to ~1e-7: where a model predicts |rho| that near 1, the difference rounds to zero or below,
  and the inverse, the Mahalanobis distance and the log-determinant would be infinite or NaN
  (one such pixel makes a whole bench's mean NLL NaN)."""
  xp = _xp(cov)
  vv = cov[..., 0] * cov[..., 1]
  return xp.maximum(vv - cov[..., 2] * cov[..., 2], OFFICIAL_EPS * vv)


def inverse(cov):
  """The precision Sigma^-1 as a triplet [..., 3] = (var_y, var_x, -cov_xy) / |Sigma|."""
  xp = _xp(cov)
  det = determinant(cov)
  return xp.stack([cov[..., 1], cov[..., 0], -cov[..., 2]], axis=-1) / det[..., None]


def mahalanobis_sq(cov, r):
  """r^T Sigma^-1 r [...] for residuals r [..., 2] (inf where a variance is 0)."""
  xp = _xp(cov, r)
  rx, ry = r[..., 0], r[..., 1]
  num = cov[..., 1] * rx * rx + cov[..., 0] * ry * ry - 2 * cov[..., 2] * rx * ry
  det = determinant(cov)
  return xp.where(det > 0, num / xp.where(det > 0, det, 1), xp.inf)


def eigenvalues(cov):
  """(larger, smaller) eigenvalues [...] of Sigma in px^2: the variances along the error
  ellipse's axes."""
  xp = _xp(cov)
  mean = (cov[..., 0] + cov[..., 1]) / 2
  half = xp.sqrt(xp.square((cov[..., 0] - cov[..., 1]) / 2) + xp.square(cov[..., 2]))
  return mean + half, xp.maximum(mean - half, 0)


def sigma_max(cov):
  """sqrt of the larger eigenvalue [...] in px: the standard deviation along the error
  ellipse's long axis (the summary the uncertainty panel and `match` use)."""
  return _xp(cov).sqrt(eigenvalues(cov)[0])


def rescale(cov, sx: float, sy: float):
  """The covariance of a flow scaled by (sx, sy): (var_x sx^2, var_y sy^2, cov_xy sx sy)."""
  xp = _xp(cov)
  return cov * xp.asarray([sx * sx, sy * sy, sx * sy], dtype=cov.dtype)


def matrices(cov) -> np.ndarray:
  """[..., 3] triplets -> [..., 2, 2] symmetric matrices (numpy)."""
  cov = np.asarray(cov)
  return np.stack([np.stack([cov[..., 0], cov[..., 2]], -1),
                   np.stack([cov[..., 2], cov[..., 1]], -1)], -2)
