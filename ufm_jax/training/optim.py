"""AdamW with per-group learning rates, the official cosine schedule, frozen groups and
skip-on-non-finite.

Parameter groups are chosen by regexes on the "/"-joined parameter path (first match wins; the
rest is "default" when config.optim.lr has that key, else an error naming them, as the official
`configure_optimizers` asserts every parameter is in a group). `PARAM_GROUPS` maps our paths to
the official group names (`get_parameter_groups`, models/ufm.py:455-471, 664-682, 1213-1250 of
the train branch). A group whose learning rate is 0 is frozen, as the official code drops it from
the optimizer (train_pl.py:190-206): its parameters are labelled "frozen", get
`optax.set_to_zero()` and no optimizer state, and the train step takes no gradient for them
(`split_trainable`). Learning-rate keys of groups the model does not have are ignored (the
official refinement model has no uncertainty head, yet its scripts set that group's rate).

Config block (`config.optim`):
  lr: {"encoder": 5e-6, "info_sharing": 1e-4, ...}  peak learning rate per group (0: frozen)
  groups: {"encoder": r"^encoder/", ...}              group name -> regex on the param path
  frozen: r"..." or None                              params matching are frozen as well
  trainable: r"..." or None                           if set, everything NOT matching is frozen
  b1, b2, eps, weight_decay (on every parameter unless no_decay: a regex of exempt paths),
  grad_clip_norm (one global norm over all gradients; None/0 = off),
  grad_clip_apart: group names (e.g. ("uncertainty_head",)) whose gradients are clipped to
      grad_clip_norm by their own global norm and left out of the others' (`clip_apart`), so a
      head's loss cannot change the step size of the rest,
  warmup_epochs (official: epochs x steps per epoch, a float) or warmup_frac (of all steps),
  fractional_warmup, min_lr_rate: see `cosine_schedule`.
"""

from __future__ import annotations

import math
import re
from typing import Any, Callable

import flax
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import traverse_util

FROZEN = "frozen"

# Our parameter paths -> the official parameter groups (module attributes of
# UniFlowMatchConfidence / UniFlowMatchClassificationRefinement; the U-Net group also holds the
# two feature combiners and the classification bias, models/ufm.py:1234-1239).
PARAM_GROUPS = {
    "encoder": r"^encoder/",
    "info_sharing": r"^info_sharing/",
    "output_head": r"^head1_",
    "uncertainty_head": r"^uncertainty_head_",
    "classification_head": r"^classification_head/",
    "unet_feature": r"^(unet_feature/|conv1/|conv2/|classification_bias$)",
}


def path_str(path) -> str:
  return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k)))) for k in path)


def param_labels(params, groups: dict[str, str] | None = None, frozen: str | None = None,
                 trainable: str | Callable[[str], bool] | None = None):
  """Pytree of labels: a group name, "default" or "frozen" for every leaf."""
  groups = dict(groups or {})
  compiled = [(name, re.compile(rx)) for name, rx in groups.items()]
  frozen_rx = re.compile(frozen) if frozen else None
  if isinstance(trainable, str):
    trainable_rx = re.compile(trainable)
    trainable = lambda p: bool(trainable_rx.search(p))  # noqa: E731

  def label(path, _):
    p = path_str(path)
    if frozen_rx is not None and frozen_rx.search(p):
      return FROZEN
    if trainable is not None and not trainable(p):
      return FROZEN
    for name, rx in compiled:
      if rx.search(p):
        return name
    return "default"

  return jax.tree_util.tree_map_with_path(label, params)


class Schedule:
  """A learning-rate schedule as a table over steps 0..total_steps, computed in float64 on the
  host (`values`) and read on the device as float32: `schedule(count)` with a Python int gives
  the float64 value, with an array (optax's step count) the float32 table entry. Steps past the
  end keep the last value. float32 arithmetic of the cosine on the device would be off by up to
  3e-7 relative; the table is the float64 value rounded once (< 6e-8)."""

  def __init__(self, values: np.ndarray):
    self.values = np.asarray(values, np.float64)

  def __call__(self, count):
    last = len(self.values) - 1
    if isinstance(count, (int, np.integer)):
      return float(self.values[min(max(int(count), 0), last)])
    table = jnp.asarray(self.values.astype(np.float32))
    return table[jnp.clip(count, 0, last)]


def cosine_schedule(peak: float, total_steps: int, warmup_steps: float,
                    min_lr_rate: float = 0.0) -> Schedule:
  """transformers' get_cosine_with_min_lr_schedule_with_warmup (num_cycles 0.5) times `peak`:
  factor(k) = k / max(1, W) for k < W, else max(0, f (1 - min_lr_rate) + min_lr_rate) with
  f = 0.5 (1 + cos(pi * (k - W) / max(1, N - W))). The official recipes pass a fractional W
  (4.8 epochs x 21 steps = 100.8: the peak itself is never used) and min_lr_rate 0.01; step 0
  gets 0 whenever W > 0."""
  if total_steps <= 0:
    raise ValueError(f"total_steps must be positive, got {total_steps}")
  k = np.arange(total_steps + 1, dtype=np.float64)
  progress = (k - warmup_steps) / float(max(1, total_steps - warmup_steps))
  decay = np.maximum(0.0, 0.5 * (1.0 + np.cos(math.pi * 0.5 * 2.0 * progress))
                     * (1 - min_lr_rate) + min_lr_rate)
  factor = np.where(k < warmup_steps, k / float(max(1, warmup_steps)), decay)
  return Schedule(peak * factor)


def warmup_steps(ocfg, total_steps: int, steps_per_epoch: float | None) -> float:
  """Warmup length in (possibly fractional) steps: `warmup_epochs` x steps per epoch (rounded
  to whole steps when `fractional_warmup` is False), else `warmup_frac` of all steps (rounded)."""
  epochs = ocfg.get("warmup_epochs")
  if epochs is None:
    frac = ocfg.get("warmup_frac", 0.1)
    if frac is None:
      raise ValueError("config.optim: set warmup_epochs or warmup_frac")
    return float(int(round(frac * total_steps)))
  if not steps_per_epoch:
    raise ValueError("config.optim.warmup_epochs needs the steps per epoch (num_epochs and a "
                     "pipeline that knows its pairs per epoch); set optim.warmup_frac instead")
  w = float(epochs) * steps_per_epoch
  return w if ocfg.get("fractional_warmup", True) else float(round(w))


def make_optimizer(ocfg, params, total_steps: int, trainable_fn=None,
                   steps_per_epoch: float | None = None):
  """Returns (tx, labels, schedules): an optax transformation over the *full* param tree.

  `trainable_fn(path_str) -> bool` overrides `ocfg.trainable` (used for the refine stage filter).
  `steps_per_epoch` turns `warmup_epochs` into steps (the official `len(train_dataloader) //
  accumulate_grad_batches`). Schedules exist for the groups that train (lr > 0).
  """
  lr = {k: float(v) for k, v in dict(ocfg.lr).items()}
  groups = dict(ocfg.get("groups", {}) or {})
  labels = param_labels(params, groups, ocfg.get("frozen"), trainable_fn or ocfg.get("trainable"))
  flat = traverse_util.flatten_dict(flax.core.unfreeze(labels), sep="/")
  if "default" in flat.values() and "default" not in lr:
    orphans = sorted(p for p, l in flat.items() if l == "default")
    raise ValueError(f"{len(orphans)} parameters are in no group of config.optim.groups "
                     f"({sorted(groups)}) and config.optim.lr has no 'default': "
                     f"{', '.join(orphans[:5])}{' ...' if len(orphans) > 5 else ''}")
  used = set(flat.values()) - {FROZEN}
  missing = sorted(used - set(lr))
  if missing:
    raise ValueError(f"config.optim.lr has no learning rate for the groups {missing} "
                     f"(it has {sorted(lr)})")
  frozen_groups = {g for g in used if lr[g] == 0}
  if frozen_groups:
    labels = jax.tree.map(lambda l: FROZEN if l in frozen_groups else l, labels)
  w = warmup_steps(ocfg, total_steps, steps_per_epoch)
  min_rate = ocfg.get("min_lr_rate", 0.0)
  schedules = {g: cosine_schedule(lr[g], total_steps, w, min_rate)
               for g in sorted(used - frozen_groups)}
  wd = ocfg.get("weight_decay", 0.05)
  no_decay = ocfg.get("no_decay")
  wd_mask = None
  if no_decay:
    rx = re.compile(no_decay)
    wd_mask = lambda p: jax.tree_util.tree_map_with_path(  # noqa: E731
        lambda path, _: not rx.search(path_str(path)), p)
  transforms = {
      g: optax.adamw(schedules[g], b1=ocfg.get("b1", 0.9), b2=ocfg.get("b2", 0.95),
                     eps=ocfg.get("eps", 1e-8), weight_decay=wd, mask=wd_mask)
      for g in schedules}
  transforms[FROZEN] = optax.set_to_zero()
  tx = optax.multi_transform(transforms, labels)
  clip = ocfg.get("grad_clip_norm")
  apart = tuple(ocfg.get("grad_clip_apart") or ())
  if apart and not clip:
    raise ValueError(f"config.optim.grad_clip_apart={apart} needs a grad_clip_norm")
  unknown = sorted(set(apart) - set(groups))
  if unknown:
    raise ValueError(f"config.optim.grad_clip_apart: {unknown} are not groups of "
                     f"config.optim.groups ({sorted(groups)})")
  if clip and apart:
    tx = optax.chain(clip_apart(clip, labels, apart), tx)
  elif clip:
    tx = optax.chain(optax.clip_by_global_norm(clip), tx)
  return tx, labels, schedules


def clip_apart(max_norm: float, labels, apart) -> optax.GradientTransformation:
  """optax.clip_by_global_norm applied separately to the gradients labelled with a group of
  `apart` and to all the others: each part is scaled by min(1, max_norm / its own norm)."""
  inside = jax.tree.map(lambda l: l in apart, labels)

  def update(updates, state, params=None):
    del params
    parts = [jax.tree.map(lambda g, m, want=want: g if m == want else jnp.zeros_like(g),
                          updates, inside) for want in (True, False)]
    scale = [jnp.minimum(1.0, max_norm / jnp.maximum(optax.global_norm(p), 1e-30))
             for p in parts]
    out = jax.tree.map(lambda g, m: g * jnp.where(m, scale[0], scale[1]).astype(g.dtype),
                       updates, inside)
    return out, state

  return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def split_trainable(params, labels):
  """(trainable, frozen) flat dicts keyed by path tuples; merge back with `merge_params`."""
  flat = traverse_util.flatten_dict(flax.core.unfreeze(params))
  flat_labels = traverse_util.flatten_dict(flax.core.unfreeze(labels))
  trainable = {k: v for k, v in flat.items() if flat_labels[k] != FROZEN}
  frozen = {k: v for k, v in flat.items() if flat_labels[k] == FROZEN}
  return trainable, frozen


def merge_params(trainable, frozen):
  return traverse_util.unflatten_dict({**trainable, **frozen})


def count_params(params, labels=None) -> dict[str, int]:
  """Number of parameters per label (or in total)."""
  if labels is None:
    return {"total": sum(int(x.size) for x in jax.tree.leaves(params))}
  out: dict[str, int] = {}
  for x, l in zip(jax.tree.leaves(params), jax.tree.leaves(labels)):
    out[l] = out.get(l, 0) + int(x.size)
  return out


@flax.struct.dataclass
class TrainState:
  """What a training run checkpoints. `batch_stats`: the BatchNorm running statistics of a model
  that has them (the refinement recipe's U-Net), outside the optimizer (no gradient, no weight
  decay, no parameter group); None, and absent from the pytree and its checkpoints, otherwise
  (`create` returns a `TrainStateWithStats` only when there are statistics, so the checkpoints of
  models without BatchNorm keep the layout they always had)."""
  step: jnp.ndarray
  params: Any
  opt_state: Any
  skipped: jnp.ndarray  # number of updates skipped for a non-finite loss or gradient
  batch_stats = None    # not a field here: see TrainStateWithStats

  @classmethod
  def create(cls, params, tx, batch_stats=None):
    kw = dict(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params),
              skipped=jnp.zeros((), jnp.int32))
    if batch_stats is None:
      return TrainState(**kw)
    return TrainStateWithStats(**kw, batch_stats=batch_stats)

  def variables(self):
    """The model's variables as the loaders return them: {"params"}, and "batch_stats" for a
    model with BatchNorm."""
    if self.batch_stats is None:
      return {"params": self.params}
    return {"params": self.params, "batch_stats": self.batch_stats}


@flax.struct.dataclass
class TrainStateWithStats(TrainState):
  """TrainState of a model with BatchNorm: the running statistics are a field (checkpointed)."""
  batch_stats: Any


def apply_gradients(state: TrainState, grads, loss, tx,
                    skip_advances_schedule: bool = True) -> tuple[TrainState, jnp.ndarray]:
  """One optimizer update through `optax.apply_if_finite`: when loss or any gradient is
  non-finite the params and Adam's moments and step count are kept as they were, `step`
  advances (the data stay aligned) and `skipped` (its total_notfinite) is incremented.

  skip_advances_schedule (config.optim.skip_advances_schedule): True (official) moves every
  group's learning-rate schedule on by the skipped step, as the official trainer steps its
  scheduler after an update whose zero loss carried no gradient (train_pl.py:79-81; torch's
  AdamW leaves parameters without a gradient and their step count alone); False: the schedules
  count applied updates only, so each skip delays the rest of the schedule by one step.

  The wrapper's state is rebuilt around `state.opt_state` on each call, so the TrainState and its
  checkpoints keep the plain optimizer's layout. It never gives up and applies a non-finite
  update: stopping after too many skips in a row is the train loop's job (loop_control.SaveAndStop,
  config.max_nonfinite_steps). Returns (new_state, ok).
  """
  # apply_if_finite looks at the gradients only: a non-finite loss counts as non-finite gradients.
  grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(loss), g, jnp.nan), grads)
  guarded = optax.apply_if_finite(tx, max_consecutive_errors=jnp.iinfo(jnp.int32).max)
  wrapped = optax.ApplyIfFiniteState(
      notfinite_count=jnp.zeros([], jnp.int32), last_finite=jnp.array(True),
      total_notfinite=state.skipped, inner_state=state.opt_state)
  updates, wrapped = guarded.update(grads, wrapped, state.params)
  opt_state, ok = wrapped.inner_state, wrapped.last_finite
  if skip_advances_schedule:
    opt_state = advance_schedules(opt_state, jnp.where(ok, 0, 1))
  return state.replace(step=state.step + 1, params=optax.apply_updates(state.params, updates),
                       opt_state=opt_state, skipped=wrapped.total_notfinite), ok


def advance_schedules(opt_state, by):
  """opt_state with the step count of every learning-rate schedule (optax's
  ScaleByScheduleState) moved on by `by`; Adam's own count (its bias correction) unchanged."""
  is_schedule = lambda x: isinstance(x, optax.ScaleByScheduleState)  # noqa: E731
  return jax.tree.map(
      lambda x: x._replace(count=x.count + jnp.asarray(by, x.count.dtype)) if is_schedule(x)
      else x, opt_state, is_leaf=is_schedule)


def current_lrs(schedules, step) -> dict[str, float]:
  """Learning rate per group at `step` (the step whose update is being applied)."""
  return {g: s(int(step)) for g, s in schedules.items()}
