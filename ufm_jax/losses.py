"""Training losses of UFM (paper eq. 2-3): robust flow regression + covisibility BCE.

The refinement-stage cross-entropy lives with the refiner (`ufm_jax.refine_training`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

# The paper follows RoMa: alpha=0.5, c=0.24 (supplementary "Visualization on the Robust Charbonnier
# Loss"). dL/dx peaks at x = c*sqrt(3) ~ 0.416 px and is still ~0.124 at 500 px.
ALPHA = 0.5
SCALE = 0.24
COVIS_WEIGHT = 10.0


def robust_charbonnier(x, alpha: float = ALPHA, c: float = SCALE):
  """Barron's general robust loss, rho(x) = |a-2|/a * (((x/c)^2/|a-2| + 1)^(a/2) - 1).

  Valid for alpha not in {0, 2}; UFM only uses alpha=0.5. Applied to the (non-negative) end-point
  error, so it is a function of the squared error and smooth at 0.
  """
  if alpha in (0.0, 2.0):
    raise ValueError(f"robust_charbonnier: alpha={alpha} needs the limit form; UFM uses 0.5")
  b = abs(alpha - 2.0)
  return b / alpha * ((jnp.square(x / c) / b + 1.0) ** (alpha / 2.0) - 1.0)


def masked_mean(values, mask):
  mask = mask.astype(values.dtype)
  # max(.,1): a batch without any valid pixel contributes 0 rather than NaN.
  return jnp.sum(values * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def end_point_error(flow_pred, flow_gt):
  """Per-pixel EPE [..., H, W] with a gradient that stays finite at zero error."""
  sq = jnp.sum(jnp.square(flow_pred - flow_gt), axis=-1)
  # sqrt'(0) is inf; the robust loss is a function of sq anyway, but the EPE itself is logged.
  safe = jnp.where(sq > 0, sq, 1.0)
  return jnp.where(sq > 0, jnp.sqrt(safe), 0.0)


def flow_loss(flow_pred, flow_gt, flow_valid, alpha: float = ALPHA, c: float = SCALE):
  """L_EPE: robust Charbonnier of the EPE averaged over `flow_valid` pixels (all images pooled)."""
  epe = end_point_error(flow_pred.astype(jnp.float32), flow_gt.astype(jnp.float32))
  return masked_mean(robust_charbonnier(epe, alpha, c), flow_valid)


def covisibility_bce(logits, covisibility, covis_valid):
  """Binary cross-entropy on logits averaged over `covis_valid` pixels.

  Uses log-sigmoid (softplus) forms, so large |logits| neither overflow nor produce log(0).
  """
  logits = logits.astype(jnp.float32)
  target = covisibility.astype(jnp.float32)
  per_pixel = -(target * jax.nn.log_sigmoid(logits) + (1.0 - target) * jax.nn.log_sigmoid(-logits))
  return masked_mean(per_pixel, covis_valid)


def flow_supervision_mask(batch, flow_pixels: str = "covisible"):
  """Pixels whose flow is supervised: "covisible" (paper eq. 2, UFM-560: flow_valid & covisible)
  or "all" (the 980 bootstrap: every pixel with ground-truth flow, as optical-flow benchmarks)."""
  if flow_pixels == "covisible":
    return batch["flow_valid"].astype(bool) & batch["covisibility"].astype(bool)
  if flow_pixels == "all":
    return batch["flow_valid"].astype(bool)
  raise ValueError(f"flow_pixels must be 'covisible' or 'all', got {flow_pixels!r}")


def ufm_loss(outputs, batch, covis_weight: float = COVIS_WEIGHT, alpha: float = ALPHA,
             c: float = SCALE, flow_pixels: str = "covisible"):
  """Total loss L = L_EPE + covis_weight * L_BCE, plus the terms and a few diagnostics.

  `outputs`: model dict with "flow" [B,H,W,2] and "covisibility_logits" [B,H,W].
  `batch`: dict with "flow", "covisibility", "flow_valid", "covis_valid".
  `flow_pixels`: see `flow_supervision_mask`.
  Returns (loss, aux) with aux = {loss_flow, loss_covis, epe, covis_acc}.
  """
  flow_mask = flow_supervision_mask(batch, flow_pixels)
  l_flow = flow_loss(outputs["flow"], batch["flow"], flow_mask, alpha, c)
  l_covis = covisibility_bce(outputs["covisibility_logits"], batch["covisibility"],
                             batch["covis_valid"])
  loss = l_flow + covis_weight * l_covis
  epe = end_point_error(jax.lax.stop_gradient(outputs["flow"]).astype(jnp.float32),
                        batch["flow"].astype(jnp.float32))
  pred_covis = outputs["covisibility_logits"] > 0
  acc = (pred_covis == batch["covisibility"].astype(bool)).astype(jnp.float32)
  aux = {
      "loss_flow": l_flow,
      "loss_covis": l_covis,
      "epe": masked_mean(epe, flow_mask),
      "covis_acc": masked_mean(acc, batch["covis_valid"]),
  }
  return loss, aux
