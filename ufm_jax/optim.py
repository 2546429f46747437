"""AdamW with per-group learning rates, cosine schedules, trainable filters and skip-on-non-finite.

Parameter groups are chosen by regexes on the "/"-joined parameter path (first match wins, the rest
is "default"); frozen parameters are labelled "frozen", get `optax.set_to_zero()` and therefore no
optimizer state, and the train step takes no gradient for them (`split_trainable`).

Config block (`config.optim`):
  lr: {"default": 1e-4, "encoder": 5e-6, ...}   peak learning rate per group
  groups: {"encoder": r"^encoder/"}              group name -> regex on the param path
  frozen: r"..." or None                        params matching are frozen (e.g. the refine base)
  trainable: r"..." or None                     if set, everything NOT matching is frozen
  b1, b2, weight_decay, eps, warmup_frac, end_lr_frac, grad_clip_norm (None/0 = off)
"""

from __future__ import annotations

import re
from typing import Any, Callable

import flax
import flax.struct
import jax
import jax.numpy as jnp
import optax
from flax import traverse_util

FROZEN = "frozen"


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


def lr_schedule(peak: float, total_steps: int, warmup_frac: float = 0.1, end_frac: float = 0.0):
  """Linear warmup from 0 over warmup_frac*total_steps, then cosine to end_frac*peak at total."""
  warmup = int(round(warmup_frac * total_steps))
  if total_steps <= 0:
    raise ValueError(f"total_steps must be positive, got {total_steps}")
  return optax.warmup_cosine_decay_schedule(
      init_value=0.0, peak_value=peak, warmup_steps=warmup,
      decay_steps=max(total_steps, warmup + 1), end_value=peak * end_frac)


def make_optimizer(ocfg, params, total_steps: int, trainable_fn=None):
  """Returns (tx, labels, schedules): an optax transformation over the *full* param tree.

  `trainable_fn(path_str) -> bool` overrides `ocfg.trainable` (used for the refine stage filter).
  """
  lr = dict(ocfg.lr)
  groups = dict(ocfg.get("groups", {}) or {})
  unknown = set(groups) - set(lr)
  if unknown or "default" not in lr:
    raise ValueError(f"config.optim.lr needs 'default' and one entry per group {sorted(groups)}; "
                     f"got lr keys {sorted(lr)}")
  labels = param_labels(params, groups, ocfg.get("frozen"), trainable_fn or ocfg.get("trainable"))
  used = set(jax.tree.leaves(labels))
  schedules = {g: lr_schedule(lr[g], total_steps, ocfg.get("warmup_frac", 0.1),
                              ocfg.get("end_lr_frac", 0.0)) for g in lr}
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
      for g in lr if g in used}
  transforms[FROZEN] = optax.set_to_zero()
  tx = optax.multi_transform(transforms, labels)
  clip = ocfg.get("grad_clip_norm")
  if clip:
    tx = optax.chain(optax.clip_by_global_norm(clip), tx)
  return tx, labels, schedules


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
  step: jnp.ndarray
  params: Any
  opt_state: Any
  skipped: jnp.ndarray  # number of updates skipped for a non-finite loss or gradient

  @classmethod
  def create(cls, params, tx):
    return cls(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params),
               skipped=jnp.zeros((), jnp.int32))


def apply_gradients(state: TrainState, grads, loss, tx) -> tuple[TrainState, jnp.ndarray]:
  """One optimizer update through `optax.apply_if_finite`: when loss or any gradient is
  non-finite the params and optimizer state are kept as they were (step still advances, so the
  schedule and data stay aligned) and `skipped` (its total_notfinite) is incremented.

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
  return state.replace(step=state.step + 1, params=optax.apply_updates(state.params, updates),
                       opt_state=wrapped.inner_state,
                       skipped=wrapped.total_notfinite), wrapped.last_finite


def current_lrs(schedules, step) -> dict[str, float]:
  """Learning rate per group at `step` (the step whose update is being applied)."""
  return {g: float(s(step)) for g, s in schedules.items()}
