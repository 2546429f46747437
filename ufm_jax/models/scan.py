"""Scanned transformer blocks (`UFMConfig.scan_blocks`): one stacked parameter tree per block
stack, run by `jax.lax.scan` so XLA compiles one block body instead of 24 + 12 unrolled copies.

Layout: with scan on, `encoder/blocks_{i}/...` becomes `encoder/blocks/...` and
`info_sharing/self_attention_blocks_{i}/...` becomes `info_sharing/self_attention_blocks/...`,
every leaf with a leading [depth] axis. The official key map (`ufm_jax.official`) stays per-layer;
`stack_blocks` / `unstack_blocks` convert between the two layouts, so any per-layer tree (official
snapshot, converted checkpoint, DINOv2 weights) loads into a scan model and back.

Intermediate taps stay exact: the stack runs as one scan per contiguous segment ending at a tap,
and the tap is that segment's final carry. When the "intermediates" collection is mutable (the
parity tests), each segment also returns its per-block outputs as scan ys and they are sown as
`block{i}_out`, as the unrolled model does; training never pays for them.

FSDP: with a `layer_gather` hook (`ufm_jax.training.sharding.layer_gather`) the stacked params stay sharded
and each block's weights are all-gathered inside the scan body, and its gradient reduce-scattered
there, so a device holds one or two gathered layers at a time instead of the whole model, with
remat or without it.
"""

import functools
import re
from typing import Callable, Dict, Optional, Sequence, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

# (top-level module, per-layer name prefix) of every scanned stack; the stacked tree is named
# like the prefix without the index.
STACKS = (("encoder", "blocks"), ("info_sharing", "self_attention_blocks"))
# "/"-joined param paths (or optimizer-state paths, which end in them) inside a stacked tree.
STACKED_PATH = re.compile(r"(^|/)(" + "|".join(f"{t}/{p}" for t, p in STACKS) + r")/")

# (path of a stacked tree, its params) -> a function gathering one layer's params, or None.
LayerGather = Optional[Callable[[str, object], Callable]]


def segments(stops: Sequence[int]) -> Tuple[Tuple[int, int], ...]:
  """[lo, hi) block ranges ending at each of the sorted, distinct `stops` (exclusive ends)."""
  out, lo = [], 0
  for hi in sorted(set(stops)):
    if hi > lo:
      out.append((lo, hi))
      lo = hi
  return tuple(out)


def stacked_params(module: nn.Module, name: str, block: nn.Module, depth: int, dim: int):
  """The [depth]-stacked parameters of `depth` copies of the unbound `block` (one flax param
  holding a tree), each copy drawn with its own key, as `depth` separate blocks would be."""
  def init(key):
    x = jnp.zeros((1, 1, dim), jnp.float32)
    return jax.vmap(lambda k: block.init(k, x)["params"])(jax.random.split(key, depth))
  return module.param(name, init)


def run(block: nn.Module, stack, x: jax.Array, lo: int, hi: int, remat: bool,
        constrain: Callable[[jax.Array], jax.Array], collect: bool,
        gather: LayerGather = None, path: str = ""):
  """Blocks lo..hi-1 of `stack` on x; returns (x, per-block outputs [hi-lo, ...] or None).

  `constrain` (the activation-sharding hook) is applied to every block's output, as at every
  block boundary of the unrolled stack. With remat the body is checkpointed per block
  (prevent_cse=False: the scan already keeps XLA from merging the recomputation away).
  `gather` (FSDP's `layer_gather` hook, `path` the stacked tree's param path) gathers each
  block's weights inside the body; remat then gathers them again for the backward pass instead
  of keeping them. Without remat the body is checkpointed too, but it saves every value computed
  from the activations (`_computed_from_activations`): only what comes from the weights alone
  (the gather, the casts to the compute dtype) is recomputed, so the backward pass gathers each
  layer again instead of keeping every layer's gathered weights.
  """
  part = jax.tree.map(lambda a: a[lo:hi], stack)
  gather_layer = gather(path, stack) if gather is not None else None

  def body(h, p):
    if gather_layer is not None:
      p = gather_layer(p)
    h = constrain(block.apply({"params": p}, h))
    return h, (h if collect else None)

  if remat:
    body = jax.checkpoint(body, prevent_cse=False)
  elif gather_layer is not None:
    body = jax.checkpoint(body, prevent_cse=False,
                          policy=functools.partial(_computed_from_activations, jnp.ndim(x)))
  return jax.lax.scan(body, x, part)


def _computed_from_activations(rank: int, prim, *avals, **params) -> bool:
  """Remat policy: save the outputs of an operation with an input of the activations' rank (a
  block's activations are [batch, tokens, channels] and more; its weights have fewer dimensions),
  recompute the others: the layer's weights as gathered and cast."""
  del prim, params
  return any(getattr(a, "ndim", 0) >= rank for a in avals)


# ----------------------------------------------------------------------------- param layout


def _depths(config) -> Dict[str, int]:
  return {"encoder": config.encoder.depth, "info_sharing": config.info_sharing.depth}


def stack_blocks(params, config):
  """Per-layer block params (`blocks_{i}`) -> the stacked tree of a `scan_blocks` model.

  Idempotent (an already stacked stack is left as is), and stacks only when all `depth` blocks of
  the config are present: a partial tree keeps its per-layer keys, so a merge reports them as
  unused instead of silently filling a stack. Other keys (and blocks >= depth) pass through.
  """
  params = dict(params)
  depth = _depths(config)
  for top, prefix in STACKS:
    sub = params.get(top)
    if sub is None or prefix in sub:
      continue
    names = [f"{prefix}_{i}" for i in range(depth[top])]
    if not all(n in sub for n in names):
      continue
    sub = dict(sub)
    layers = [sub.pop(n) for n in names]
    sub[prefix] = jax.tree.map(_stack, *layers)
    params[top] = sub
  return params


def _stack(*a):
  # Host trees (loaders, merges) stay numpy; device trees stay on device.
  return np.stack(a) if all(isinstance(t, np.ndarray) for t in a) else jnp.stack(a)


def unstack_blocks(params, config):
  """Inverse of `stack_blocks`: the stacked tree -> `blocks_{i}` per-layer params (idempotent)."""
  params = dict(params)
  depth = _depths(config)
  for top, prefix in STACKS:
    sub = params.get(top)
    if sub is None or prefix not in sub:
      continue
    sub = dict(sub)
    stack = sub.pop(prefix)
    n = {int(np.shape(a)[0]) for a in jax.tree.leaves(stack)}
    if n != {depth[top]}:
      raise ValueError(f"{top}/{prefix}: stacked leading sizes {sorted(n)} != the config's "
                       f"{top} depth {depth[top]}")
    for i in range(depth[top]):
      sub[f"{prefix}_{i}"] = jax.tree.map(lambda a: a[i], stack)
    params[top] = sub
  return params


def to_layout(params, config):
  """`params` in the layout of `config`'s model (stacked iff `config.scan_blocks`)."""
  return stack_blocks(params, config) if config.scan_blocks else unstack_blocks(params, config)

