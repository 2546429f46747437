"""What every training loss term shares (ufm_jax.training.losses, ufm_jax.training.refine_training,
ufm_jax.training.distill_loss): the invalid-ground-truth rule, the masked mean with the official
denominators, the pixel grid, the robust loss, and option checking. Its own module so that the
refinement and distillation terms and the recipe that composes all terms import it without
importing each other."""

from __future__ import annotations

from typing import Optional

import jax.numpy as jnp

# |GT component| above which the official code treats flow as an invalid marker (KITTI/HD1K
# store 4000): loss/epe.py:174, 282.
MAX_GT = 2048.0


def masked_mean(values, mask, eps: Optional[float]):
  """sum(values * mask) / (sum(mask) + eps); eps None: / max(sum(mask), 1)."""
  m = mask.astype(values.dtype)
  n = jnp.sum(m)
  return jnp.sum(values * m) / (n + eps if eps is not None else jnp.maximum(n, 1.0))


def pixel_grid(h: int, w: int):
  """(x [1,1,W], y [1,H,1]) float32 integer pixel indices (the official meshgrids)."""
  return (jnp.arange(w, dtype=jnp.float32)[None, None, :],
          jnp.arange(h, dtype=jnp.float32)[None, :, None])


def invalid_gt_mask(gt, max_gt: float = MAX_GT):
  """Pixels whose GT the official code filters out of its logs and refinement: any NaN
  component or |u| + |v| >= max_gt (a NaN sum compares False, so NaN is caught twice)."""
  return jnp.isnan(gt).any(-1) | ~(jnp.sum(jnp.abs(gt), -1) < max_gt)


def robust_of_squared(e, alpha: float):
  """Barron's general robust loss as a function of the squared scaled error e = (x / c)^2:
  |a-2|/a * ((e/|a-2| + 1)^(a/2) - 1); alpha not in {0, 2} (paper eq. 2, loss/epe.py:215-329)."""
  if alpha in (0.0, 2.0):
    raise ValueError(f"robust loss: alpha={alpha} needs the limit form; UFM uses 0.5")
  b = abs(alpha - 2.0)
  return b / alpha * ((e / b + 1.0) ** (alpha / 2.0) - 1.0)


def check_choice(name, value, choices):
  if value not in choices:
    raise ValueError(f"loss option {name}={value!r}; expected one of {choices}")
