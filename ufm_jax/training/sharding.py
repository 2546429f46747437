"""Device mesh, parameter sharding rules -> NamedShardings, and global batch assembly.

Everything about how arrays are laid out on devices lives here; `train.py` only calls it.

Config:
  config.mesh = "data:-1,fsdp:1"   axis names and sizes (or a list of (name, size) pairs); one size
                                   of -1 takes the remaining devices
  config.sharding_rules = [(regex, rule), ...]  on the "/"-joined param path, first match wins:
      "fsdp"       shard the largest dimension divisible by the fsdp axis size over `fsdp`
      "replicate"  keep a full copy on every device
      a tuple      explicit PartitionSpec entries, e.g. (None, "fsdp")
  config.sharding_min_size = N    tensors with fewer entries stay replicated under "fsdp"
  The batch is always sharded on its leading dimension over ("data", "fsdp"), and so is every
  activation at the model's block boundaries (`activation_constraint`): FSDP gathers the weights
  of a layer, never the batch.

FSDP gathers: the scanned blocks' stacked params (models/scan.py) are gathered one layer at a time
inside the scan (`layer_gather`), and their gradients reduce-scattered there; every other param is
gathered whole at the start of the step (`gathered`) and its gradient reduce-scattered too. The
layer axis of a stack is never sharded.
"""

from __future__ import annotations

import collections
import json
import math
import os
import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from ufm_jax.training import optim
from ufm_jax.models import scan

BATCH_AXES = ("data", "fsdp")


def maybe_initialize_distributed():
  """`jax.distributed.initialize()` when launched as one of several processes.

  Explicit localhost/multi-node launch: JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID.
  Managed clusters (TPU pods, SLURM, ...) are detected by JAX itself when UFM_MULTIHOST=1
  (launch/slurm/train.sbatch sets it).
  Returns True when distributed mode was initialised.
  """
  if os.environ.get("JAX_NUM_PROCESSES"):
    n = int(os.environ["JAX_NUM_PROCESSES"])
    if n > 1:
      jax.distributed.initialize(
          coordinator_address=os.environ["JAX_COORDINATOR_ADDRESS"], num_processes=n,
          process_id=int(os.environ["JAX_PROCESS_ID"]))
      return True
    return False
  if os.environ.get("UFM_MULTIHOST") == "1":
    jax.distributed.initialize(local_device_ids=_slurm_host_gpus())
    return True
  return False


def _slurm_host_gpus():
  """Under Slurm with one task per host, the ids of all the GPUs Slurm gave the host: JAX's
  Slurm detection otherwise assumes a task per GPU and hands each task the GPU of its local rank
  (GPU 0 only, with one task per host). None elsewhere (JAX decides)."""
  per_node = os.environ.get("SLURM_STEP_TASKS_PER_NODE", "")
  gpus = os.environ.get("SLURM_GPUS_ON_NODE", "")
  if per_node.split("(")[0] != "1" or not gpus.isdigit():
    return None
  return list(range(int(gpus)))


def parse_mesh(mesh_config) -> list[tuple[str, int]]:
  if isinstance(mesh_config, str):
    try:
      return [(a.split(":")[0].strip(), int(a.split(":")[1])) for a in mesh_config.split(",")]
    except (IndexError, ValueError) as e:
      raise ValueError(f"config.mesh={mesh_config!r}: want 'axis:size,axis:size'") from e
  return [(str(n), int(s)) for n, s in mesh_config]


def make_mesh(mesh_config, devices=None) -> Mesh:
  """Mesh from "data:-1,fsdp:2" or [(axis, size), ...]; -1 means "all remaining devices"."""
  mesh_config = parse_mesh(mesh_config)
  devices = list(jax.devices() if devices is None else devices)
  names = [str(n) for n, _ in mesh_config]
  for required in BATCH_AXES:
    if required not in names:
      raise ValueError(f"config.mesh must name the axes {BATCH_AXES}; got {names}")
  sizes = [int(s) for _, s in mesh_config]
  if sizes.count(-1) > 1:
    raise ValueError(f"config.mesh: at most one axis may be -1; got {list(mesh_config)}")
  known = int(np.prod([s for s in sizes if s != -1]))
  if -1 in sizes:
    if len(devices) % known:
      raise ValueError(f"config.mesh {list(mesh_config)} does not divide {len(devices)} devices")
    sizes[sizes.index(-1)] = len(devices) // known
  if -1 not in sizes and int(np.prod(sizes)) < len(devices) and jax.process_count() == 1:
    devices = devices[:int(np.prod(sizes))]  # an explicit smaller mesh uses the first devices
  if int(np.prod(sizes)) != len(devices):
    raise ValueError(f"config.mesh {list(mesh_config)} needs {int(np.prod(sizes))} devices, "
                     f"have {len(devices)}")
  try:
    arr = jax.experimental.mesh_utils.create_device_mesh(sizes, devices)
  except Exception:  # noqa: BLE001 - CPU/fake devices have no topology to optimise for
    arr = np.asarray(devices).reshape(sizes)
  return Mesh(arr, names)


def _fsdp_spec(shape, axis_size: int, axis: str = "fsdp", min_size: int = 0,
               first: int = 0) -> P:
  """Shard the largest dimension (from `first` on) divisible by axis_size; replicate if none (or
  tiny arrays)."""
  if axis_size == 1 or int(np.prod(shape, dtype=np.int64)) < min_size:
    return P()
  order = sorted(range(first, len(shape)), key=lambda i: -shape[i])
  for i in order:
    if shape[i] % axis_size == 0 and shape[i] >= axis_size:
      spec = [None] * len(shape)
      spec[i] = axis
      return P(*spec)
  return P()


def spec_for(path: str, shape, rules, mesh: Mesh, min_size: int = 0) -> P:
  for rx, rule in rules:
    if re.search(rx, path):
      if rule == "fsdp":
        # A scanned stack's leading axis is its layers: each scan step gathers one of them.
        first = 1 if scan.STACKED_PATH.search(path) else 0
        return _fsdp_spec(shape, mesh.shape["fsdp"], min_size=min_size, first=first)
      if rule == "replicate":
        return P()
      rule = tuple(rule)
      if len(rule) != len(shape):
        raise ValueError(f"sharding rule {rx!r} -> {rule} has {len(rule)} entries but param "
                         f"{path} has shape {tuple(shape)}")
      return P(*rule)
  return P()


def tree_shardings(tree, mesh: Mesh, rules, min_size: int = 0) -> Any:
  """NamedSharding for every leaf of `tree` (arrays or ShapeDtypeStructs) by the config rules;
  "fsdp" leaves with fewer than `min_size` entries are replicated.

  Leaves that are scalars (step counters) are replicated, and so are BatchNorm running statistics
  (under a "batch_stats" key): small, and updated from statistics every device computes whole.
  """
  rules = [tuple(r) for r in (rules or [])]

  def one(path, x):
    shape = getattr(x, "shape", ())
    if len(shape) == 0 or any(getattr(k, "name", getattr(k, "key", None)) == "batch_stats"
                              for k in path):
      return NamedSharding(mesh, P())
    return NamedSharding(mesh, spec_for(optim.path_str(path), shape, rules, mesh, min_size))

  return jax.tree_util.tree_map_with_path(one, tree)


def batch_sharding(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, P(BATCH_AXES))


FSDP_GATHERS = ("layer", "step")


def fsdp_gathers(mesh: Mesh, config):
  """(gather_params, layer_gather) by `config.fsdp_gather`: "layer" (default) gathers the
  scanned blocks a layer at a time inside the scan and every other param at the start of the
  step; "step" gathers every param at the start of the step (the whole model on each device for
  the step's duration). Both None on a one-device mesh."""
  mode = config.fsdp_gather
  if mode not in FSDP_GATHERS:
    raise ValueError(f"config.fsdp_gather={mode!r}; expected one of {FSDP_GATHERS}")
  rules, min_size = config.sharding_rules, config.sharding_min_size
  if mode == "step":
    return gathered(mesh, rules, min_size), None
  return (gathered(mesh, rules, min_size, except_stacks=True),
          layer_gather(mesh, rules, min_size))


# XLA:TPU reduces a gradient over a large FSDP group as an all-reduce of the whole gradient
# followed by a slice, not as a reduce-scatter: a 64-way reduce-scatter over a v5e-64's 8 x 8
# chips compiled to an all-reduce (libtpu 0.0.42.1), where 8 chips get a reduce-scatter. Constrained
# to a shard over fewer devices first, it reduce-scatters twice. Groups from this size on are
# reduced in two stages (`_two_stage`).
TWO_STAGE_MIN_DEVICES = 64


def _two_stage(mesh):
  """(a view of `mesh` with its fsdp axis split into fsdp_outer x fsdp_inner, fsdp_outer taking
  the largest divisor of the size up to its square root), or None below TWO_STAGE_MIN_DEVICES.
  A block of an fsdp_outer shard is a block of the fsdp shard, so the second stage reduces
  within the first stage's shards: no data crosses between them."""
  n = mesh.shape["fsdp"]
  outer = max((d for d in range(1, math.isqrt(n) + 1) if n % d == 0), default=1)
  if n < TWO_STAGE_MIN_DEVICES or outer == 1:
    return None
  names, sizes = list(mesh.axis_names), [mesh.shape[a] for a in mesh.axis_names]
  i = names.index("fsdp")
  names[i:i + 1], sizes[i:i + 1] = ["fsdp_outer", "fsdp_inner"], [outer, n // outer]
  if isinstance(mesh, Mesh):
    return Mesh(mesh.devices.reshape(sizes), tuple(names))
  return jax.sharding.AbstractMesh(tuple(sizes), tuple(names))


def _outer_stage(sharding: NamedSharding, view) -> NamedSharding:
  """`sharding` with its fsdp axis replaced by the view's fsdp_outer (the first stage)."""
  def entry(e):
    if e == "fsdp":
      return "fsdp_outer"
    if isinstance(e, tuple):
      return tuple("fsdp_outer" if a == "fsdp" else a for a in e)
    return e
  return NamedSharding(view, P(*(entry(e) for e in sharding.spec)))


def _gather_whole(shards):
  """A tree of arrays -> the same tree gathered whole on every device, as FSDP's forward pass
  uses it; `shards`: their stored shardings (NamedShardings, a tree of the same structure).

  Each array is first constrained to its shard, then to a full copy: an all-gather. Its
  gradient is constrained to the shard, so it goes from the devices' partial sums straight to
  the shard (a reduce-scatter); the transpose of the two constraints would all-reduce a whole
  copy of the gradient first and keep a slice of it. On a large fsdp axis the gradient goes to a
  shard over fsdp_outer first (`_two_stage`).
  """
  @jax.custom_vjp
  def gather(tree):
    tree = jax.lax.with_sharding_constraint(tree, shards)
    return jax.lax.with_sharding_constraint(
        tree, jax.tree.map(lambda s: NamedSharding(s.mesh, P()), shards))

  def backward(_, grad):
    view = _two_stage(jax.tree.leaves(shards)[0].mesh) if jax.tree.leaves(shards) else None
    if view is not None:
      grad = jax.lax.with_sharding_constraint(
          grad, jax.tree.map(lambda s: _outer_stage(s, view), shards))
    return (jax.lax.with_sharding_constraint(grad, shards),)

  gather.defvjp(lambda tree: (gather(tree), None), backward)
  return gather


def gathered(mesh: Mesh, rules=None, min_size: int = 0, except_stacks: bool = False):
  """params -> params gathered whole on every device, at the start of the forward pass: FSDP's
  weight all-gather (the stored params and optimizer state stay sharded, by `rules` and
  `min_size` as `tree_shardings` shards them; the gradients are reduce-scattered back to those
  shards, `_gather_whole`). Left free, XLA may instead move a batch-sharded activation to the
  layout of a feature-sharded weight. `except_stacks` leaves the scanned blocks' stacks as they
  are, for the model to gather a layer at a time (`layer_gather`). None on a one-device mesh."""
  if mesh.size == 1:
    return None
  rules = [tuple(r) for r in (rules or [])]

  def gather_params(tree):
    leaves, treedef = jax.tree_util.tree_flatten_with_path(tree)
    shards = jax.tree.leaves(tree_shardings(tree, mesh, rules, min_size))
    picked = [i for i, (path, _) in enumerate(leaves)
              if not (except_stacks and scan.STACKED_PATH.search(optim.path_str(path)))]
    whole = _gather_whole([shards[i] for i in picked])([leaves[i][1] for i in picked])
    out = [x for _, x in leaves]
    for i, x in zip(picked, whole):
      out[i] = x
    return jax.tree_util.tree_unflatten(treedef, out)

  return gather_params


def layer_gather(mesh: Mesh, rules, min_size: int = 0):
  """The model's per-layer FSDP hook (`scan.run`): (param path of a scanned stack, its stacked
  params) -> a function that gathers one layer's params inside the scan body.

  The layer's params are gathered from their own shard of the stored sharding (the stack's
  `rules` spec without the layer axis) and their gradient reduce-scattered back to it inside the
  backward scan (`_gather_whole`), so neither the whole model nor its whole gradient is ever
  materialised on one device. None on a one-device mesh.
  """
  if mesh.size == 1:
    return None
  rules = [tuple(r) for r in (rules or [])]

  def for_stack(path: str, stack):
    def layer_sharding(leaf_path, a):
      name = f"{path}/{optim.path_str(leaf_path)}"
      spec = tuple(spec_for(name, a.shape, rules, mesh, min_size))
      if spec and spec[0] is not None:
        raise ValueError(f"sharding rule for {name} {P(*spec)} shards the layer axis of a "
                         "scanned stack; shard another dimension (scan gathers one layer a step)")
      return NamedSharding(mesh, P(*spec[1:]))

    return _gather_whole(jax.tree_util.tree_map_with_path(layer_sharding, stack))

  return for_stack


def activation_constraint(mesh: Mesh):
  """The model's `activation_sharding` hook: x -> x with its leading (batch) dimension sharded
  over the mesh's batch axes, the other dimensions whole. None on a one-device mesh.

  Arrays whose leading dimension does not divide over the batch axes (a batch-1 init trace) are
  left to XLA.
  """
  n = batch_divisor(mesh)
  if n == 1:
    return None
  sharding = batch_sharding(mesh)

  def constrain(x):
    if x.ndim == 0 or x.shape[0] % n:
      return x
    return jax.lax.with_sharding_constraint(x, sharding)

  return constrain


def replicated(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, P())


def batch_divisor(mesh: Mesh) -> int:
  return mesh.shape["data"] * mesh.shape["fsdp"]


def make_global_batch(local_batch: dict, mesh: Mesh) -> dict:
  """Global jax.Arrays from this process's slice of the batch (leading dim = per-process batch).

  Non-array entries (e.g. `meta`) are dropped: they never enter the jitted step.
  """
  sharding = batch_sharding(mesh)
  out = {}
  for k, v in local_batch.items():
    if isinstance(v, (np.ndarray, jnp.ndarray)) and getattr(v, "ndim", 0) >= 1:
      out[k] = jax.make_array_from_process_local_data(sharding, np.asarray(v))
  return out


class DevicePrefetch:
  """Global batches from an iterator of this process's numpy batches, `depth` of them already
  handed to the devices (transfers are asynchronous), so loading and transfer overlap the step.

  Checkpointable like the iterator it wraps: `get_state()` is the wrapped iterator's position
  after the last batch *returned* (batches still queued are read again after a restore), as JSON
  bytes, which grain's per-process checkpoint handler stores (`per_process_state`).
  """
  per_process_state = True

  def __init__(self, iterator, mesh: Mesh, depth: int = 2):
    self.iterator, self.mesh, self.depth = iterator, mesh, max(int(depth), 1)
    self.queue = collections.deque()  # (wrapped state before the batch, global batch)

  def __iter__(self):
    return self

  def __next__(self):
    while len(self.queue) < self.depth:
      before = self._inner_state()
      try:
        local = next(self.iterator)
      except StopIteration:
        if not self.queue:
          raise
        break
      self.queue.append((before, make_global_batch(local, self.mesh)))
    return self.queue.popleft()[1]

  def _inner_state(self):
    return self.iterator.get_state() if hasattr(self.iterator, "get_state") else None

  def get_state(self) -> bytes:
    state = self.queue[0][0] if self.queue else self._inner_state()
    return json.dumps(state).encode()

  def set_state(self, state) -> None:
    self.queue.clear()
    self.iterator.set_state(json.loads(state) if isinstance(state, (bytes, str)) else state)

  def start_prefetch(self) -> None:  # called by grain's checkpoint handler after a restore
    pass


def local_batch_size(global_batch_size: int, mesh: Mesh) -> int:
  """Per-process batch size; checks the global batch divides the mesh and the processes."""
  div = batch_divisor(mesh)
  if global_batch_size % div:
    raise ValueError(f"input.batch_size={global_batch_size} must be divisible by the data*fsdp "
                     f"mesh size {div}")
  if global_batch_size % jax.process_count():
    raise ValueError(f"input.batch_size={global_batch_size} must be divisible by the number of "
                     f"processes {jax.process_count()}")
  return global_batch_size // jax.process_count()


def log_shardings(shardings, params) -> None:
  n_sharded = sum(int(x.size) for x, s in zip(jax.tree.leaves(params), jax.tree.leaves(shardings))
                  if any(a is not None for a in s.spec))
  n = sum(int(x.size) for x in jax.tree.leaves(params))
  logging.info("sharding: %.1f%% of %d parameters sharded", 100 * n_sharded / max(n, 1), n)
