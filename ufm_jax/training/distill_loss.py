"""The distillation loss terms: UFM's two training losses with the teacher's outputs as targets.

The teacher runs inside the train step (ufm_jax.training.distill) and its outputs, warped into the
student's crop, reach the loss as batch keys:

  teacher_flow            [B,H,W,2] float32  the teacher's flow in the student's crop (px)
  teacher_covisibility    [B,H,W] float32    its covisibility probability (0 where the match
                                             leaves the crop); absent for a teacher without an
                                             uncertainty head
  teacher_in_view         [B,H,W] bool       the crop pixel lies inside the teacher's view
  teacher_in_crop         [B,H,W] bool       the teacher's match lies inside the target crop
  teacher_flow_covariance [B,H,W,3] float32  (var_x, var_y, cov_xy) in crop px^2, from a
                                             teacher with a flow covariance head

Both terms are registered in `ufm_jax.training.losses.term_types` ("teacher_robust", "teacher_bce") and
sum with any other term of a recipe (configs/distill.py mixes in the label terms when a source's
labels are wanted). Neither reads a label key.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp

from ufm_jax.training.loss_common import check_choice, masked_mean, robust_of_squared


def _sum(x):
  return jnp.sum(x.astype(jnp.float32))


@dataclasses.dataclass(frozen=True)
class TeacherFlow:
  """The official robust EPE (paper eq. 2, loss/epe.py:215-329; alpha and c as the official
  defaults) of the student's flow against the teacher's, on the teacher's covisible pixels:
  `teacher_in_view & teacher_in_crop & teacher_covisibility > covisible_threshold` (the
  official 'covisible' range with the teacher's covisibility as the label; a teacher without
  covisibility supervises every pixel whose match stays in the crop).

  covariance: "auto" weights each pixel by s^2 / (s^2 + sigma^2), sigma^2 = (var_x + var_y) / 2
    of the teacher's flow covariance in crop px^2 and s = `covariance_scale` px, where the batch
    has `teacher_flow_covariance`: pixels the teacher is sure of count fully, a pixel with a
    sigma of 3 s a tenth. The mean divides by the summed weights, so the loss keeps its scale.
    "off": every supervised pixel counts once. Without a covariance in the batch both are the
    plain masked mean.
  """
  alpha: float = 0.5
  c: float = 0.24
  multiplier: float = 1.0
  covisible_threshold: float = 0.5
  covariance: str = "auto"
  covariance_scale: float = 1.0
  eps: Optional[float] = 1e-4

  def __post_init__(self):
    check_choice("covariance", self.covariance, ("auto", "off"))
    if self.covariance_scale <= 0:
      raise ValueError(f"loss option covariance_scale={self.covariance_scale}: must be > 0 px")

  def mask(self, batch):
    """The pixels the term supervises (bool [B,H,W])."""
    mask = batch["teacher_in_view"] & batch["teacher_in_crop"]
    if "teacher_covisibility" in batch:
      mask = mask & (batch["teacher_covisibility"] > self.covisible_threshold)
    return mask

  def weights(self, batch):
    """Per-pixel weights from the teacher's covariance, or None (every pixel counts once)."""
    cov = batch.get("teacher_flow_covariance")
    if cov is None or self.covariance == "off":
      return None
    var = 0.5 * (cov[..., 0] + cov[..., 1]).astype(jnp.float32)
    s2 = self.covariance_scale ** 2
    return s2 / (s2 + jnp.maximum(var, 0.0))

  def __call__(self, outputs, batch, shared, ctx):
    if "teacher_flow" not in batch:
      raise ValueError("loss term teacher_robust: the batch has no teacher_flow (a distillation "
                       "config runs the teacher in the step: set config.teacher)")
    pred = shared["pred"]
    target = batch["teacher_flow"].astype(jnp.float32)
    d = jnp.where(jnp.isnan(pred), 0.0, pred) - target
    per_pixel = robust_of_squared(jnp.sum(jnp.square(d / self.c), -1), self.alpha)
    mask = self.mask(batch)
    w = self.weights(batch)
    if w is None:
      value = masked_mean(per_pixel, mask, self.eps)
    else:
      weight = jnp.where(mask, w, 0.0)
      value = jnp.sum(per_pixel * weight) / (jnp.sum(weight) + (self.eps or 0.0))
    d = jax.lax.stop_gradient(d)
    epe = jnp.sqrt(jnp.sum(jnp.square(d), -1))
    n = _sum(mask)
    logs = {"robust_epe@teacher": value,
            "epe@teacher": jnp.sum(jnp.where(mask, epe, 0.0)) / jnp.maximum(n, 1.0),
            "supervised_fraction": n / mask.size}
    if w is not None:
      logs["covariance_weight"] = jnp.sum(jnp.where(mask, w, 0.0)) / jnp.maximum(n, 1.0)
    return self.multiplier * value, logs, shared


@dataclasses.dataclass(frozen=True)
class TeacherCovisibility:
  """Covisibility BCE (paper eq. 3, loss/cross_entropy.py:76-103) of the student's logits
  against the teacher's covisibility probability as a soft target, times `multiplier` (10, the
  official weight), over the crop pixels inside the teacher's view.

  out_of_crop: where the teacher's match leaves the student's target crop. "not_covisible"
    (default): supervised with target 0, what the cropped pair shows. "unsupervised": dropped,
    as the official flow pathway drops such pixels from its labels' covis_valid
    (`input.augment.supervise_out_of_view=False`).
  """
  multiplier: float = 10.0
  out_of_crop: str = "not_covisible"
  eps: Optional[float] = 1e-6

  def __post_init__(self):
    check_choice("out_of_crop", self.out_of_crop, ("not_covisible", "unsupervised"))

  def __call__(self, outputs, batch, shared, ctx):
    if "teacher_covisibility" not in batch:
      raise ValueError("loss term teacher_bce: the teacher has no covisibility (no uncertainty "
                       "head); leave teacher_bce out of config.loss.terms")
    if "covisibility_logits" not in outputs:
      raise ValueError("loss term teacher_bce: the student has no uncertainty head")
    x = outputs["covisibility_logits"].astype(jnp.float32)
    t = batch["teacher_covisibility"].astype(jnp.float32)
    valid = batch["teacher_in_view"]
    if self.out_of_crop == "unsupervised":
      valid = valid & batch["teacher_in_crop"]
    per_pixel = -(t * jax.nn.log_sigmoid(x) + (1.0 - t) * jax.nn.log_sigmoid(-x))
    ce = masked_mean(per_pixel, valid, self.eps)
    # The part of the BCE the student can still remove: the teacher's own entropy is its floor.
    t = jnp.clip(t, 1e-7, 1 - 1e-7)
    entropy = masked_mean(-(t * jnp.log(t) + (1 - t) * jnp.log1p(-t)), valid, self.eps)
    agree = masked_mean(((x > 0) == (batch["teacher_covisibility"] > 0.5)).astype(jnp.float32),
                        valid, self.eps)
    return self.multiplier * ce, {"bce@teacher": ce, "kl@teacher": ce - entropy,
                                  "agreement": agree}, shared
