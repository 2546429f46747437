"""Gradient accumulation: a global batch split into microbatches that stay on every device.

The global batch is sharded by rows over the mesh's batch axes (each device holds a contiguous
block). A microbatch made of consecutive rows would live on 1/k of the devices, so microbatch j
takes instead the j-th of every k pair slots of each device's block: pairs j, j + k, j + 2k, ...
of the global batch. Splitting the sharded dimension into (outer, k, pair) keeps the outer part
sharded and the rest local, so the split moves no data between devices. A symmetrized pair
((a, b), (b, a): rows 2i, 2i + 1) stays within one microbatch.
"""

from __future__ import annotations

import jax


def pair_rows(apply_kwargs) -> int:
  """Rows that must stay together on one device and in one microbatch: a symmetrized pair's
  (a, b), (b, a) rows (2), or a plain row (1)."""
  return 2 if (apply_kwargs or {}).get("symmetrized") else 1


def check_divisible(batch_size: int, grad_accum: int, batch_shards: int, pair_rows: int = 2):
  """Raises a ValueError naming the sizes unless every device's rows split into `grad_accum`
  microbatches of whole pairs."""
  if grad_accum == 1:
    return
  unit = grad_accum * pair_rows * batch_shards
  if batch_size % unit:
    per_device = batch_size / batch_shards
    raise ValueError(
        f"grad_accum={grad_accum}: the batch of {batch_size} rows ({per_device:g} per device over "
        f"{batch_shards} batch shards) does not split into {grad_accum} microbatches of whole "
        f"{'pairs' if pair_rows == 2 else 'rows'} on every device; the batch must be a multiple "
        f"of {unit} (grad_accum x {pair_rows} rows x batch shards)")


def microbatches(batch: dict, grad_accum: int, mesh=None, pair_rows: int = 2) -> dict:
  """{key: [B, ...]} -> {key: [grad_accum, B / grad_accum, ...]}, microbatch j in row j of the
  leading axis (pair slots j mod grad_accum of each device's rows). `mesh`: the batch's, whose
  batch axes shard the microbatch rows (None: no constraint, one device)."""
  from ufm_jax.training import sharding
  sizes = {k: v.shape[0] for k, v in batch.items()}
  b = next(iter(sizes.values()))
  if any(s != b for s in sizes.values()):
    raise ValueError(f"batch entries differ in their leading (row) size: {sizes}")
  shards = 1 if mesh is None else sharding.batch_divisor(mesh)
  check_divisible(b, grad_accum, shards, pair_rows)
  spec = None
  if mesh is not None and shards > 1:
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(None, sharding.BATCH_AXES))

  def split(x):
    tail = x.shape[1:]
    x = x.reshape((b // (grad_accum * pair_rows), grad_accum, pair_rows) + tail)
    x = jax.numpy.moveaxis(x, 1, 0).reshape((grad_accum, b // grad_accum) + tail)
    return x if spec is None else jax.lax.with_sharding_constraint(x, spec)

  return {k: split(v) for k, v in batch.items()}


def constrain(tree, shardings):
  """with_sharding_constraint leaf by leaf (None: unchanged), so a loop-carried gradient sum
  keeps the params' sharding instead of whatever XLA would give a fresh array of zeros."""
  if shardings is None:
    return tree
  return jax.tree.map(jax.lax.with_sharding_constraint, tree, shardings)
