"""Training the refiner (paper, supplementary "Training the Refinement").

The base model is frozen; only the refinement stage trains. The P x P attention of each pixel is a
distribution over offsets around the regressed flow; it is supervised with cross-entropy against a
soft target that spreads the ground-truth location bilinearly over its 4 adjacent offsets, on
covisible pixels whose ground truth falls inside the window.
"""

import jax
import jax.numpy as jnp
import optax

# Top-level param collections of UFM-Refine that train in this stage (names as in PyTorch).
TRAINABLE = ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias")


def refinement_target(flow_regressed, flow_gt, radius):
  """Soft classification target and the in-window mask.

  Args:
    flow_regressed: [..., 2] flow the window is centred on (the base model's output).
    flow_gt: [..., 2] ground-truth flow.
    radius: R (window offsets -R..R on each axis, P = 2R+1).
  Returns:
    target [..., P, P] with [..., a, b] <-> offset (dx, dy) = (b - R, a - R): for the GT offset
    (dx, dy) = flow_gt - flow_regressed at window position (gx, gy) = (dx + R, dy + R), the four taps
    (y0|y0+1, x0|x0+1) around it get (1-alpha)(1-beta), alpha(1-beta), (1-alpha)beta, alpha*beta with
    alpha = gx - x0, beta = gy - y0; zero everywhere when outside.
    inside [...] bool: 0 <= gx <= 2R and 0 <= gy <= 2R (the GT lies in the closed window).
  """
  p = 2 * radius + 1
  g = flow_gt - flow_regressed + radius                                     # [..., 2] (gx, gy)
  inside = jnp.all((g >= 0) & (g <= 2 * radius), axis=-1)
  # x0 in 0..2R-1 so both neighbours exist; a GT on the last tap gets alpha = 1 there.
  lo = jnp.clip(jnp.floor(g), 0, 2 * radius - 1)
  frac = jnp.clip(g - lo, 0.0, 1.0)
  taps = jnp.arange(p, dtype=g.dtype)

  def axis_weights(lo_, f):   # [..., P]: (1-f) at lo, f at lo+1
    return (jnp.where(taps == lo_[..., None], 1 - f[..., None], 0.0)
            + jnp.where(taps == lo_[..., None] + 1, f[..., None], 0.0))

  wx = axis_weights(lo[..., 0], frac[..., 0])
  wy = axis_weights(lo[..., 1], frac[..., 1])
  target = wy[..., :, None] * wx[..., None, :]
  return jnp.where(inside[..., None, None], target, 0.0), inside


def refinement_loss(log_softmax, flow_regressed, flow_gt, covisible, valid=None):
  """Cross-entropy of the attention distribution against the soft target.

  Args:
    log_softmax: [B, H, W, P, P] the model's "log_softmax" output.
    flow_regressed: [B, H, W, 2] the model's "flow_before_refinement" (gradient stopped here).
    flow_gt: [B, H, W, 2]; covisible: [B, H, W] bool ground-truth covisibility;
    valid: optional [B, H, W] bool (e.g. flow_valid & covis_valid of the sample).
  Returns:
    (loss, aux): loss = mean over supervised pixels (covisible, valid, GT inside the window) of
    -sum target * log_softmax; 0 when no pixel is supervised. aux has "refine_pixels" (count) and
    "refine_inside_frac" (fraction of covisible valid pixels whose GT is in the window).
  """
  radius = log_softmax.shape[-1] // 2
  target, inside = refinement_target(jax.lax.stop_gradient(flow_regressed).astype(jnp.float32),
                                     flow_gt.astype(jnp.float32), radius)
  eligible = covisible.astype(bool)
  if valid is not None:
    eligible = eligible & valid.astype(bool)
  mask = eligible & inside
  ce = -jnp.sum(target * log_softmax.astype(jnp.float32), axis=(-1, -2))
  n = jnp.sum(mask)
  loss = jnp.sum(jnp.where(mask, ce, 0.0)) / jnp.maximum(n, 1)
  aux = {"refine_pixels": n,
         "refine_inside_frac": n / jnp.maximum(jnp.sum(eligible), 1)}
  return loss, aux


def _require_refiner(params):
  if not any(k in params for k in TRAINABLE):
    raise ValueError(f"no refinement parameters ({', '.join(TRAINABLE)}) in the tree; top-level "
                     f"keys are {sorted(params)}")


def trainable_mask(params):
  """Pytree of bools like `params`: True for the refinement stage (U-Net, classification head,
  combiner convs, classification bias), False for the frozen base model."""
  _require_refiner(params)
  return {k: jax.tree_util.tree_map(lambda _: k in TRAINABLE, v) for k, v in params.items()}


def split_params(params):
  """(trainable, frozen) top-level sub-dicts; differentiate w.r.t. the first only, so the base
  gets no gradient at all (not even a computed-then-dropped one)."""
  _require_refiner(params)
  trainable = {k: v for k, v in params.items() if k in TRAINABLE}
  frozen = {k: v for k, v in params.items() if k not in TRAINABLE}
  return trainable, frozen


def merge_params(trainable, frozen):
  return {**frozen, **trainable}


def masked_optimizer(tx, params):
  """`tx` on the refinement stage only; frozen params get zero updates and hold no optimizer state."""
  labels = jax.tree_util.tree_map(lambda t: "train" if t else "freeze", trainable_mask(params))
  return optax.multi_transform({"train": tx, "freeze": optax.set_to_zero()}, labels)
