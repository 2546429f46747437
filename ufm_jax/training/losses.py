"""The training losses of UFM as the official training code computes them.

Official: `uniflowmatch/loss/{epe,cross_entropy,refinement_cross_entropy_efficient}.py` and
`training/train_pl.py:58-85` on the `train` branch of etola/UFM (d8c421e). A recipe is a list of
terms summed in config order (the official YAML order, `configs/loss/*.yaml`):

  type "robust"         RobustRegressionLoss: Barron's robust loss of the flow error (paper eq. 2)
  type "epe"            FlowEPELoss: the end-point error itself
  type "bce"            CrossEntropyLoss: covisibility BCE on logits (paper eq. 3)
  type "refinement_ce"  RefinementCrossEntropyLossEfficient (ufm_jax.training.refine_training)
  type "refinement_ce_eval"  RefinementCrossEntropyLoss, the refine recipes' test loss
  type "teacher_robust", "teacher_bce"  distillation: the same two losses against a teacher's
                        outputs instead of labels (ufm_jax.training.distill_loss, configs/distill.py)
  type "flow_nll"       FlowCovarianceNLL: the flow's negative log-likelihood under the predicted
                        covariance (ours: the official code has the head but no loss for it)

Every official quirk is a field of its term with the official behaviour as default; the field's
comment says what the alternative changes. docs/recipe.md lists them with their file:line.

Batch (NHWC, `ufm_jax.data.pipeline`): flow [B,H,W,2] (may hold NaN or huge values where the
dataset stores invalid flow that way), covisibility [B,H,W] (official `non_occluded_mask`),
covis_valid (official `occlusion_supervision_mask`), flow_valid (no official counterpart; used only
where said), dataset_id. Outputs: flow [B,H,W,2], covisibility_logits [B,H,W]; refinement models
also flow_before_refinement, feature_map_0/1 [B,H,W,C], attention_bias [P*P]. The regression
terms read `flow_before_refinement` when present: in training mode the official refinement model
returns the regressed flow as `flow.flow_output` (models/ufm.py:1000-1022).

Official batches are symmetrized ((a, b), (b, a) rows) and every loss averages over all rows
together (`batch[0]` holds both directions after `make_batch_symmetric`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.training import distill_loss, refine_training
from ufm_jax.training.loss_common import (MAX_GT, check_choice, invalid_gt_mask, masked_mean,
                                 pixel_grid, robust_of_squared)
from ufm_jax.models import covariance

# Thresholds (px) of the official outlier-ratio logs (loss/epe.py:190, 309).
OUTLIER_THRESHOLDS = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0)


def end_point_error(d, eps: float = 0.0):
  """|d| over the last axis. eps = 0: the plain norm with torch's zero gradient at an exactly zero
  residual (a naive jnp norm gives NaN there); eps > 0: sqrt(|d|^2 + eps^2), smooth everywhere."""
  sq = jnp.sum(jnp.square(d), axis=-1)
  if eps:
    return jnp.sqrt(sq + eps * eps)
  return jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)


def robust_charbonnier(x, alpha: float = 0.5, c: float = 0.24):
  """Barron's general robust loss of an error x, as a function of x^2 (smooth at 0):
  |a-2|/a * (((x/c)^2/|a-2| + 1)^(a/2) - 1); alpha not in {0, 2}."""
  return robust_of_squared(jnp.square(x / c), alpha)


def _ones_like_mask(x):
  return jnp.ones(x.shape[:-1], bool)


@dataclasses.dataclass(frozen=True)
class FlowRegression:
  """RobustRegressionLoss (kind "robust", loss/epe.py:215-329) and FlowEPELoss (kind "epe",
  loss/epe.py:10-212): the masked mean of a per-pixel flow error.

  Mask: range "covisible" = `covisibility` (official supervision_range 'occlusion'); "all" = the
  GT target (integer pixel index + flow) inside [-margin W, (1+margin) W) x [-margin H,
  (1+margin) H) (official 'all' with fov_threshold = margin, loss/epe.py:75-105), and only where
  the batch has ground truth (flow_valid: the official datasets encode missing flow as 4000 px,
  which that range test excludes). The official test reads no mask (every pixel counts as valid,
  epe.py:63-69), so a row whose official label is zero flow with all masks False (FlyingChairs'
  second view) is supervised towards zero flow everywhere: its reader marks that flow valid
  (source option `backward_zero_flow`, ufm_jax/data/sources/flyingchairs.py).
  """
  kind: str = "robust"              # "robust" | "epe"
  range: str = "covisible"          # "covisible" | "all"
  margin: float = 0.25              # range "all": tolerance as a fraction of W and H
  alpha: float = 0.5                # robust: Barron alpha (paper / RoMa)
  c: float = 0.24                   # robust: scale (px)
  multiplier: float = 1.0
  # Quirk (epe.py:209, 329: the loss is returned without `multiplier`): False adds the plain
  # mean to the total whatever the multiplier (the refine-560 `epe` term, multiplier 0, adds its
  # full value); True multiplies it in.
  multiplier_applied: bool = False
  # Quirk (epe.py:271-282): "zero" sets NaN GT components and components beyond max_gt to 0 and
  # keeps the pixel in the mean (a residual against 0; in range "all" a NaN target passes the
  # margin test); "drop" removes such pixels, and pixels with flow_valid False, from the mask.
  invalid_gt: str = "zero"
  max_gt: float = MAX_GT
  # Quirk (epe.py:186, 293): the mean divides by sum(mask) + eps; None divides by max(sum, 1).
  eps: Optional[float] = 1e-4
  # Quirk (kind "epe", epe.py:177): 0 = the plain norm, gradient 0 at an exactly zero residual
  # (torch's linalg.norm backward); > 0: sqrt(|r|^2 + epe_eps^2).
  epe_eps: float = 0.0

  def __post_init__(self):
    check_choice("kind", self.kind, ("robust", "epe"))
    check_choice("range", self.range, ("covisible", "all"))
    check_choice("invalid_gt", self.invalid_gt, ("zero", "drop"))

  def mask(self, batch, gt):
    """(supervision mask, the official NaN/max_gt-filtered mask used by the logs)."""
    flow_valid = batch.get("flow_valid")
    flow_valid = _ones_like_mask(gt) if flow_valid is None else flow_valid.astype(bool)
    nan = jnp.isnan(gt).any(-1)
    if self.range == "covisible":
      base = batch["covisibility"].astype(bool)
    else:
      h, w = gt.shape[1:3]
      xs, ys = pixel_grid(h, w)
      tx, ty = xs + gt[..., 0], ys + gt[..., 1]
      m = self.margin
      outside = (tx < -m * w) | (ty < -m * h) | (tx >= (1 + m) * w) | (ty >= (1 + m) * h)
      base = ~outside & (flow_valid | nan)
    filtered = base & ~invalid_gt_mask(gt, self.max_gt)
    mask = base if self.invalid_gt == "zero" else filtered & flow_valid
    return mask, filtered

  def __call__(self, outputs, batch, shared, ctx):
    gt, pred = shared["gt"], shared["pred"]
    mask, filtered = self.mask(batch, gt)
    gt = jnp.where(jnp.isnan(gt), 0.0, gt)
    gt = jnp.where(jnp.abs(gt) > self.max_gt, 0.0, gt)
    pred = jnp.where(jnp.isnan(pred), 0.0, pred)
    d = pred - gt
    if self.kind == "robust":
      per_pixel = robust_of_squared(jnp.sum(jnp.square(d / self.c), -1), self.alpha)
    else:
      per_pixel = end_point_error(d, self.epe_eps)
    value = masked_mean(per_pixel, mask, self.eps)
    loss = value * self.multiplier if self.multiplier_applied else value
    logs = self._logs(value, jax.lax.stop_gradient(d), mask, filtered)
    ctx.setdefault("masks", {})[ctx.get("term")] = mask   # the pixels it supervises (flow_nll)
    return loss, logs, dict(shared, gt=gt, pred=pred)

  def _logs(self, value, d, mask, filtered):
    """The official log dict (epe.py:188-209, 295-327), keyed as there."""
    where = "non_occluded_mask" if self.range == "covisible" else "all"
    epe = end_point_error(d)
    n = jnp.sum(filtered.astype(jnp.float32))
    mean_epe = masked_mean(epe, mask, self.eps)
    px = jnp.sum(jnp.where(filtered, epe, 0.0)) / n          # NaN when nothing is supervised
    if self.kind == "robust":
      logs = {f"robust_epe@{where}": value, f"flow_epe[flow_output]@{where}": mean_epe,
              f"px_robust_epe@{where}": px}
      prefix = "flow_output_pixel_outlier"
    else:
      logs = {f"flow_epe@{where}": value, f"px_flow_epe@{where}": px}
      prefix = "pixel_outlier"
    for i, t in enumerate(OUTLIER_THRESHOLDS):
      count = jnp.sum((filtered & (epe > t)).astype(jnp.float32))
      logs[f"{prefix}/lv{i + 1}"] = jnp.where(n > 0, count / jnp.maximum(n, 1.0), count)
    return logs


@dataclasses.dataclass(frozen=True)
class CovisibilityBCE:
  """CrossEntropyLoss with target 'occlusion' (loss/cross_entropy.py:76-103): binary
  cross-entropy of `covisibility_logits` against `covisibility`, summed over `covis_valid`."""
  multiplier: float = 10.0
  # Quirk (cross_entropy.py:98): divides by sum(valid) + eps; None divides by max(sum, 1).
  eps: Optional[float] = 1e-6

  def __call__(self, outputs, batch, shared, ctx):
    x = outputs["covisibility_logits"].astype(jnp.float32)
    t = batch["covisibility"].astype(jnp.float32)
    per_pixel = -(t * jax.nn.log_sigmoid(x) + (1.0 - t) * jax.nn.log_sigmoid(-x))
    ce = masked_mean(per_pixel, batch["covis_valid"], self.eps)
    return self.multiplier * ce, {"occlusion_ce": ce}, shared


@dataclasses.dataclass(frozen=True)
class FlowCovarianceNLL:
  """Negative log-likelihood of the flow under the predicted covariance (`flow_covariance_params`,
  ufm_jax.models.covariance), per pixel with r = flow - gt:

    gaussian  0.5 r^T Sigma^-1 r + 0.5 log|Sigma|   (the 2D Gaussian's, less its constant log 2 pi)
    laplace   sqrt(3 r^T Sigma^-1 r) + 0.5 log|Sigma|   (the elliptical Laplace with covariance
              Sigma, less log(2 pi / 3); `likelihood`, covariance.laplace_nll_from)

  in the closed forms of ufm_jax.models.covariance (finite for any correlation), averaged over the pixels
  the flow term named by `pixels` supervises (its mask, with its invalid-GT rule: that term must
  come first in `terms`), times `multiplier`. The official code has no such term (its validation
  config names a FlowEPECovarianceLoss that exists on no branch).

  `detach_flow` decides where the gradient goes: True stops it at r, so the NLL trains only the
  covariance and the flow is trained by the flow term alone; False lets it reach the flow (and the
  trunk), an extra regression loss weighted by the predicted precision. The recipes use True:
  at the trained synthetic run that pull would be ~2% of the flow term's gradient on the flow
  head and the trunk (benchmarks/nll_flow_gradient.py), the flow term's own direction
  reweighted towards the pixels the model is already sure of; trained with False the synthetic
  run's held-out EPE is 1.478 px against 1.052 with True and 1.253 without the head
  (docs/uncertainty.md). True keeps the flow trained by the recipe's flow term alone.

  `likelihood`: the recipes use "gaussian". Trained with "laplace" on the synthetic layers task,
  whose errors do have a Laplace's tail, the head calibrated no better (coverage as close to its
  family's, AUSE 0.71 of random against 0.48: docs/uncertainty.md).
  """
  pixels: str = "robust_epe"
  multiplier: float = 1.0
  detach_flow: bool = True
  likelihood: str = "gaussian"
  eps: Optional[float] = 1e-4      # masked-mean denominator, as the flow terms'
  max_gt: float = MAX_GT

  def __post_init__(self):
    check_choice("likelihood", self.likelihood, covariance.LIKELIHOODS)

  def __call__(self, outputs, batch, shared, ctx):
    if "flow_covariance_params" not in outputs:
      raise ValueError("loss term flow_nll: the model predicts no flow covariance (add a "
                       "flow_cov adaptor: model.flow_covariance, ufm.with_flow_covariance)")
    masks = ctx.get("masks", {})
    if self.pixels not in masks:
      raise ValueError(f"loss term flow_nll: pixels={self.pixels!r} names no flow term before it "
                       f"(flow terms so far: {sorted(k for k in masks if k)})")
    gt, pred = shared["gt"], shared["pred"]
    gt = jnp.where(jnp.isnan(gt) | (jnp.abs(gt) > self.max_gt), 0.0, gt)
    r = jnp.where(jnp.isnan(pred), 0.0, pred) - gt
    if self.detach_flow:
      r = jax.lax.stop_gradient(r)
    params = outputs["flow_covariance_params"].astype(jnp.float32)
    quad, log_det = covariance.quadratic_and_log_det(params, r)
    mask = masks[self.pixels]
    # where(), not the product alone: a pixel outside the mask contributes nothing, NaN included
    per_pixel = (0.5 * quad + 0.5 * log_det if self.likelihood == "gaussian"
                 else covariance.laplace_nll_from(quad, log_det))
    value = masked_mean(jnp.where(mask, per_pixel, 0.0), mask, self.eps)
    q = jax.lax.stop_gradient(jnp.where(mask, quad, 0.0))
    m = mask.astype(jnp.float32)
    n = jnp.maximum(jnp.sum(m), 1.0)
    logs = {"nll": value,
            # a calibrated Gaussian: E[r^T Sigma^-1 r] = 2, P(within 2 sigma) = 1 - e^-2 = 0.865
            "mahalanobis_sq": jnp.sum(q * m) / n,
            "coverage_2sigma": jnp.sum((q <= 4.0) * m) / n,
            "sigma_geomean": jnp.exp(jnp.sum(jax.lax.stop_gradient(
                jnp.where(mask, log_det, 0.0))) / n / 4)}
    return self.multiplier * value, logs, shared


def term_types() -> dict:
  """Config `type` -> term class."""
  return {"robust": FlowRegression, "epe": FlowRegression, "bce": CovisibilityBCE,
          "flow_nll": FlowCovarianceNLL,
          "refinement_ce": refine_training.RefinementCE,
          "refinement_ce_eval": refine_training.RefinementCEEval,
          "teacher_robust": distill_loss.TeacherFlow,
          "teacher_bce": distill_loss.TeacherCovisibility}


def make_term(spec: Mapping[str, Any], name: str = "?"):
  """A term from its config block {"type": ..., field: value, ...}; unknown fields raise."""
  spec = dict(spec)
  kind = spec.pop("type", None)
  types = term_types()
  if kind not in types:
    raise ValueError(f"loss term {name!r}: type {kind!r}; expected one of {sorted(types)}")
  cls = types[kind]
  if cls is FlowRegression:
    spec["kind"] = kind
  fields = {f.name for f in dataclasses.fields(cls)}
  unknown = sorted(set(spec) - fields)
  if unknown:
    raise ValueError(f"loss term {name!r} ({kind}): unknown keys {unknown}; known: "
                     f"{sorted(fields - {'kind'})}")
  return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec.items()})


def from_official(class_name: str, kwargs: Mapping[str, Any]) -> dict:
  """The term config equivalent to an official loss YAML entry (`class`, `kwargs`)."""
  kw = dict(kwargs)
  kw.pop("minimum_mask_threshold", None)   # stored but never used (epe.py:179-181)
  mult = float(kw.pop("multiplier", 1.0))

  def supervision_range():
    r = kw.pop("supervision_range", "occlusion")
    if r not in ("occlusion", "all"):
      raise ValueError(f"{class_name}: supervision_range {r!r} has no equivalent here")
    return "covisible" if r == "occlusion" else "all"

  if class_name in ("RobustRegressionLoss", "FlowEPELoss"):
    out = {"type": "robust" if class_name == "RobustRegressionLoss" else "epe",
           "multiplier": mult, "range": supervision_range(),
           "margin": float(kw.pop("fov_threshold", 0.0))}
    if class_name == "RobustRegressionLoss":
      out["alpha"] = float(kw.pop("alpha", 0.5))
      out["c"] = float(kw.pop("c", 0.03))
      if kw.pop("target", "flow_output") != "flow_output":
        raise ValueError("RobustRegressionLoss: only target 'flow_output' is supported")
  elif class_name == "CrossEntropyLoss":
    if kw.pop("target", "occlusion") != "occlusion" or \
       kw.pop("target_supervision_mask", None) != "occlusion_supervision_mask":
      raise ValueError("CrossEntropyLoss: only target 'occlusion' with target_supervision_mask "
                       "'occlusion_supervision_mask' is supported")
    out = {"type": "bce", "multiplier": mult}
  elif class_name in ("RefinementCrossEntropyLossEfficient", "RefinementCrossEntropyLoss"):
    if supervision_range() != "covisible" or \
       kw.pop("supervision_strategy", "4_point_average") != "4_point_average":
      raise ValueError(f"{class_name}: only supervision_range 'occlusion' with "
                       "supervision_strategy '4_point_average' is supported")
    out = {"type": "refinement_ce" if class_name.endswith("Efficient") else "refinement_ce_eval",
           "multiplier": mult}
  else:
    raise ValueError(f"official loss class {class_name!r} has no equivalent here")
  if kw:
    raise ValueError(f"{class_name}: unsupported kwargs {sorted(kw)}")
  return out


# "The training takes 4 days on 8 H100 GPUs" (paper, Training Details): the recipes' loss
# groups, one per GPU of that run (Recipe.groups).
PAPER_GPUS = 8


def check_groups(batch_rows: int, groups: int, grad_accum: int = 1, pair_rows: int = 1):
  """ValueError naming the numbers unless the rows one loss sees (the batch, or each of
  grad_accum microbatches) split into `groups` equal blocks of whole pairs (pair_rows 2:
  symmetrized (a, b), (b, a) rows)."""
  if groups < 1:
    raise ValueError(f"config.loss.groups={groups}: the loss groups must be 1 or more")
  if groups == 1:
    return
  unit = groups * grad_accum * pair_rows
  if batch_rows % unit:
    what = f"batch of {batch_rows} rows"
    if grad_accum > 1:
      what += f" in {grad_accum} microbatches"
    raise ValueError(
        f"config.loss.groups={groups} (one loss per group of rows, as one per GPU of the paper's "
        f"{PAPER_GPUS}-GPU run) does not divide the {what} into groups of whole "
        f"{'pairs' if pair_rows == 2 else 'rows'}: the global batch must be a multiple of "
        f"{unit} (groups x grad_accum x {pair_rows}), or set --config.loss.groups")


@dataclasses.dataclass(frozen=True)
class Recipe:
  """Terms summed in order; `__call__(outputs, batch, rng=, suitable_rows=)` -> (loss, aux).

  aux: "loss_<term>" (what the term adds to the total) and "<term>/<official log key>".
  """
  terms: Tuple[Tuple[str, Any], ...]
  # Quirk (epe.py:274-282, refinement_cross_entropy_efficient.py:184): the official terms zero NaN
  # (and > max_gt) GT and NaN predictions *in place*, in the tensors every later term reads, so
  # e.g. the refinement loss after a regression term supervises NaN-GT pixels towards 0. False:
  # each term sees the batch and outputs as given.
  shared_cleanup: bool = True
  temperature: Optional[float] = None    # the refinement model's (RefinementCE reads it)
  # Rows in official batches that may supervise the refinement: dataset names -> per-row flags.
  dataset_names: Optional[Tuple[str, ...]] = None
  # The official runs are DDP: each of N GPUs takes the loss over its own rows (its own means
  # and pixel cap) and the gradients are averaged, i.e. the total is the mean of N per-group
  # losses over consecutive row blocks. The recipes set the paper's N = 8 (PAPER_GPUS) whatever
  # our device count; 1 pools the whole batch.
  groups: int = 1

  def __call__(self, outputs, batch, rng=None, suitable_rows=None):
    if rng is None:
      rng = jax.random.PRNGKey(0)
    if suitable_rows is None:
      suitable_rows = self.suitable_rows(batch)
    if self.groups == 1:
      return self._pooled(outputs, batch, rng, suitable_rows)
    b = batch["flow"].shape[0]
    check_groups(b, self.groups)

    def split(tree):   # [B, ...] leaves -> [G, B/G, ...]; others (attention_bias) shared
      return jax.tree.map(lambda x: x.reshape((self.groups, b // self.groups) + x.shape[1:])
                          if getattr(x, "ndim", 0) and x.shape[0] == b else x, tree)

    def axes(tree):
      return jax.tree.map(lambda x: 0 if getattr(x, "ndim", 0) and x.shape[0] == b else None,
                          tree)

    total, aux = jax.vmap(self._pooled, in_axes=(axes(outputs), axes(batch), 0,
                                                 None if suitable_rows is None else 0))(
        split(outputs), split(batch), jax.random.split(rng, self.groups), split(suitable_rows))
    return jnp.mean(total), jax.tree.map(jnp.mean, aux)

  def _pooled(self, outputs, batch, rng, suitable_rows):
    pred = outputs.get("flow_before_refinement", outputs.get("flow"))
    # A distillation batch may carry no labels at all (ufm_jax.training.distill_loss reads the teacher's).
    gt = batch.get("flow")
    shared = {"gt": None if gt is None else gt.astype(jnp.float32),
              "pred": None if pred is None else pred.astype(jnp.float32)}
    ctx = {"temperature": self.temperature, "suitable_rows": suitable_rows, "masks": {}}
    total = jnp.zeros((), jnp.float32)
    aux = {}
    for i, (name, term) in enumerate(self.terms):
      ctx["rng"] = jax.random.fold_in(rng, i)
      ctx["term"] = name
      loss, logs, after = term(outputs, batch, shared, ctx)
      if self.shared_cleanup:
        shared = after
      total = total + loss
      aux[f"loss_{name}"] = loss
      aux.update({f"{name}/{k}": v for k, v in logs.items()})
    return total, aux

  def suitable_rows(self, batch):
    """Per-row `suitable_for_refinement` from batch["dataset_id"] (None: every row)."""
    datasets = [t.datasets for _, t in self.terms if getattr(t, "datasets", None) is not None]
    if not datasets or self.dataset_names is None or "dataset_id" not in batch:
      return None
    table = np.array([n in datasets[0] for n in self.dataset_names], bool)
    return jnp.asarray(table)[batch["dataset_id"]]


def recipe_from_config(cfg: Mapping[str, Any], temperature: Optional[float] = None,
                       dataset_names: Optional[Sequence[str]] = None) -> Recipe:
  """`config.loss` -> Recipe: {"terms": (names in order), name: {type, fields}, shared_cleanup,
  groups}."""
  cfg = dict(cfg.to_dict() if hasattr(cfg, "to_dict") else cfg)
  names = tuple(cfg.pop("terms", ()))
  if not names:
    raise ValueError("config.loss.terms is empty: name the loss terms in the order they sum")
  missing = [n for n in names if n not in cfg]
  if missing:
    raise ValueError(f"config.loss.terms names {missing} without a config.loss.<name> block")
  terms = tuple((n, make_term(cfg.pop(n), n)) for n in names)
  shared_cleanup = bool(cfg.pop("shared_cleanup", True))
  groups = int(cfg.pop("groups", 1))
  if cfg:
    raise ValueError(f"config.loss: unknown keys {sorted(cfg)} (blocks not named in terms?)")
  return Recipe(terms, shared_cleanup, temperature,
                None if dataset_names is None else tuple(dataset_names), groups)
