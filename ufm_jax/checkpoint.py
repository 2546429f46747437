"""Checkpoints: the orbax manager (train state + data iterator), `model_init`, preemption.

Layout of a workdir:
  checkpoints/<step>/state   the TrainState (orbax, sharded arrays, written asynchronously)
  checkpoints/<step>/data    the grain iterator state (one JSON per process)

`model_init` sources (string, optionally prefixed with a kind):
  ckpt:DIR       a training workdir or its checkpoints/ folder (latest step), or a
                 `python -m ufm_jax.convert` output (read through `ufm_jax.load`)
  snapshot:DIR   a Hugging Face snapshot of the official PyTorch release (`ufm_jax.load_official`)
  dinov2:PATH    DINOv2 weights for the encoder: HF `facebook/dinov2-*` model.safetensors (or its
                 folder), transformers naming, no torch needed; or the original `dinov2_vit*14*.pth`
                 (needs the optional torch extra)
Without a prefix the kind is guessed from what is on disk.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import re
import signal
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from absl import logging
from flax import traverse_util

from ufm_jax import convert

# ---------------------------------------------------------------------------------------------
# Manager


def _grain_iterator(it) -> bool:
  """Iterators whose state grain's handler checkpoints per process: grain's own, and wrappers
  that declare `per_process_state` (sharding.DevicePrefetch)."""
  import grain
  return isinstance(it, (grain.DatasetIterator, grain.DataLoaderIterator)) or bool(
      getattr(it, "per_process_state", False))


def make_manager(workdir, save_interval_steps: int, keep: int, async_save: bool = True):
  directory = pathlib.Path(workdir).absolute() / "checkpoints"
  options = ocp.CheckpointManagerOptions(
      max_to_keep=keep, save_interval_steps=max(int(save_interval_steps), 1), create=True,
      enable_async_checkpointing=async_save, cleanup_tmp_directories=True)
  return ocp.CheckpointManager(directory, options=options, item_names=("state", "data"))


def _data_save_args(data_iter):
  if data_iter is None:
    return None
  if _grain_iterator(data_iter):
    import grain
    return grain.checkpoint.CheckpointSave(data_iter)
  if hasattr(data_iter, "get_state"):  # plain iterators with a JSON-able state
    return ocp.args.JsonSave(data_iter.get_state())
  raise TypeError(f"the data iterator {type(data_iter).__name__} has no get_state(): its position "
                  "could not be checkpointed")


def save(manager, step: int, state, data_iter=None, force: bool = False) -> bool:
  """Saves when `step` is on the interval (or `force`); returns whether a save was started."""
  if not force and not manager.should_save(step):
    return False
  items = {"state": ocp.args.StandardSave(state)}
  data = _data_save_args(data_iter)
  if data is not None:
    items["data"] = data
  return manager.save(step, args=ocp.args.Composite(**items), force=force)


def _all_processes(ok: bool) -> bool:
  """True when `ok` holds on every process; every process gets the same answer."""
  if jax.process_count() == 1:
    return bool(ok)
  from jax.experimental import multihost_utils
  return bool(np.min(multihost_utils.process_allgather(np.int32(bool(ok)))))


def _restore_step(manager, step: int, abstract_state, data_iter):
  items = {"state": ocp.args.StandardRestore(abstract_state)}
  if data_iter is not None:
    if _grain_iterator(data_iter):
      import grain
      items["data"] = grain.checkpoint.CheckpointRestore(data_iter)
    else:
      items["data"] = ocp.args.JsonRestore()
  restored = manager.restore(step, args=ocp.args.Composite(**items))
  if data_iter is not None and not _grain_iterator(data_iter):
    data_iter.set_state(restored["data"])
  return restored["state"]


def quarantine_step(manager, step: int, reason: str) -> pathlib.Path:
  """Moves checkpoint `step` aside to <step>.corrupt-<UTC time>, so no later restart retries it.

  Kept, not deleted: the operator may want to look at it. Process 0 moves it (the checkpoint
  folder is shared, as orbax assumes); every process then re-reads the list of steps.
  """
  directory = pathlib.Path(manager.directory)
  target = directory / f"{step}.corrupt-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
  if jax.process_index() == 0:
    os.replace(directory / str(step), target)
    (target / "CORRUPT.txt").write_text(reason + "\n")
    logging.warning("moved the unrestorable checkpoint step %d to %s", step, target)
  if jax.process_count() > 1:
    from jax.experimental import multihost_utils
    multihost_utils.sync_global_devices(f"ufm_jax quarantine {step}")
  manager.reload()
  return target


def restore_latest(manager, abstract_state, data_iter=None):
  """(state, step) from the newest checkpoint that restores completely, or (None, None) when
  there is none.

  `abstract_state`: a pytree of jax.ShapeDtypeStruct with `.sharding` set, so arrays come back
  sharded as the train step expects. The data iterator is restored in place.

  A step whose train state or data-iterator state does not restore (a truncated or missing file,
  on any process) is logged with the error and skipped for the next older one; once an older step
  restores, the skipped ones are moved aside (`quarantine_step`) so a restart does not trip over
  them again. When no step restores, nothing is moved (the cause is then rather the model or
  mesh than the files) and the error names every step's failure.
  """
  failed = []
  for step in sorted(manager.all_steps(), reverse=True):
    error = None
    try:
      state = _restore_step(manager, step, abstract_state, data_iter)
    except Exception as e:  # noqa: BLE001 - whatever a damaged file raises
      state, error = None, f"{type(e).__name__}: {e}"
    if not _all_processes(error is None):
      error = error or "restored here but not on another process"
      if len(error) > 1000:
        error = error[:1000] + " ..."
      logging.warning("checkpoint step %d in %s does not restore, trying the one before: %s",
                      step, manager.directory, error)
      failed.append((step, error))
      continue
    for bad, why in failed:
      quarantine_step(manager, bad, f"step {bad} did not restore (step {step} did): {why}")
    logging.info("resumed from %s at step %d", manager.directory, step)
    return state, step
  if failed:
    raise RuntimeError(f"no checkpoint under {manager.directory} restores (nothing was moved; "
                       "a changed model, optimizer or mesh is a likely cause):\n  " +
                       "\n  ".join(f"step {s}: {e}" for s, e in failed))
  return None, None


# ---------------------------------------------------------------------------------------------
# Preemption and the other ways a run stops


class PreemptionGuard:
  """Turns SIGTERM into a flag the loop polls, so it can save and exit cleanly.

  With several processes the signal may reach only one of them (one preempted host), yet all
  must stop after the same step, or the others wait forever in the next collective. `poll` ORs
  each flag over all processes with a tiny all-reduce over the mesh, read one step late (while
  the next step runs, so the host never waits for the device); JAX's own preemption sync point
  (when its preemption service is on) counts as SIGTERM too.
  """

  def __init__(self, mesh=None):
    self.requested = False
    self._previous = None
    self._mesh = mesh
    self._reduce = None
    self._pending = None
    self._sync_point = True

  def __enter__(self):
    def handler(signum, frame):
      del frame
      logging.warning("received signal %d: will save a checkpoint and exit", signum)
      self.requested = True
    self._previous = signal.signal(signal.SIGTERM, handler)
    return self

  def __exit__(self, *exc):
    signal.signal(signal.SIGTERM, self._previous or signal.SIG_DFL)

  def _any_process(self, flags: np.ndarray):
    """Issues max over processes of `flags`; returns the result of the previous call (or None)."""
    from jax.sharding import NamedSharding, PartitionSpec
    if self._reduce is None:
      if self._mesh is None:
        self._mesh = jax.sharding.Mesh(np.array(jax.devices()), ("all",))
      axes = tuple(self._mesh.axis_names)
      self._sharding = NamedSharding(self._mesh, PartitionSpec(axes, None))
      self._reduce = jax.jit(lambda x: jnp.max(x, axis=0),
                             out_shardings=NamedSharding(self._mesh, PartitionSpec()))
    rows = np.broadcast_to(flags[None], (self._mesh.devices.size, flags.size))
    x = jax.make_array_from_callback(rows.shape, self._sharding, lambda idx: rows[idx])
    previous, self._pending = self._pending, self._reduce(x)
    return None if previous is None else np.asarray(previous)

  def poll(self, step: int, *flags: bool) -> tuple[bool, ...]:
    """(stop, *flags), each OR-ed over all processes; the same answer on every process when all
    call it once per step."""
    local = np.array([self.requested, *flags], np.int32)
    if jax.process_count() == 1:
      return tuple(bool(v) for v in local)
    agreed = self._any_process(local)
    out = [False] * local.size if agreed is None else [bool(v) for v in agreed]
    if self._sync_point:
      from jax.experimental import multihost_utils
      try:
        out[0] = out[0] or bool(multihost_utils.reached_preemption_sync_point(step))
      except Exception:  # noqa: BLE001 - preemption service unavailable on this platform
        self._sync_point = False
    return tuple(out)

  def should_stop(self, step: int) -> bool:
    return self.poll(step)[0]


class NonFiniteSteps(RuntimeError):
  """Too many consecutive updates were skipped for a non-finite loss or gradient."""


class CheckpointWriteError(RuntimeError):
  """A background checkpoint write failed."""


def write_error(manager) -> BaseException | None:
  """The error of a failed background checkpoint write once the write is over (None while one is
  in flight or when it succeeded); never waits."""
  if manager.is_saving_in_progress():
    return None
  try:
    manager.wait_until_finished()  # the write is over: returns at once, raising its error
    manager.check_for_errors()
  except Exception as e:  # noqa: BLE001 - whatever the writer raised
    return e
  return None


def _step_or_none(step) -> str:
  return "none" if step is None else f"step {step}"


class Keeper:
  """Saves and stops train.py's loop: `end_of_step` once per step, on every process.

  - Saves at the manager's interval, at the last step, and when a process got SIGTERM (once per
    step when these coincide), then returns True for the loop to exit 0 (`message` says what).
  - Never saves a step inside a run of skipped (non-finite) updates: a regular save waits for the
    next finite update, a preemption exits without a new checkpoint. After `max_nonfinite_steps`
    consecutive skipped updates it raises NonFiniteSteps naming the count and the last finite step.
  - Polls the background checkpoint write every step and raises CheckpointWriteError when it
    failed (on any process); the failed step never becomes a checkpoint, the newest complete one
    stays.
  `update_ok` is read one step late unless the step saves, so the host stays a step ahead.
  """

  def __init__(self, manager, guard: PreemptionGuard, max_nonfinite_steps: int | None,
               start_step: int):
    self.manager, self.guard = manager, guard
    self.max_nonfinite = int(max_nonfinite_steps or 0)
    self.last_finite = start_step  # checkpoints are never written inside a non-finite run
    self.streak = 0
    self.saved_step = None
    self.message = ""
    self._unread = None
    self._deferred = False
    self._writing = False

  def _count(self, step: int, update_ok) -> None:
    if bool(jax.device_get(update_ok)):
      if self.streak:
        logging.warning("step %d: finite again after %d skipped updates", step, self.streak)
      self.last_finite, self.streak = step, 0
    else:
      if not self.streak:
        logging.warning("step %d: non-finite loss or gradient, update skipped", step)
      self.streak += 1
    if self.max_nonfinite and self.streak >= self.max_nonfinite:
      newest = self.manager.latest_step()
      try:
        self.manager.wait_until_finished()  # a save in flight is of a finite step: let it finish
      except Exception:  # noqa: BLE001 - this error is the one to report
        pass
      raise NonFiniteSteps(
          f"{self.streak} consecutive updates skipped for a non-finite loss or gradient (steps "
          f"{step - self.streak + 1}-{step}, max_nonfinite_steps={self.max_nonfinite}); last "
          f"finite update: step {self.last_finite}; newest checkpoint: {_step_or_none(newest)}")

  def end_of_step(self, step: int, state, data_iter, update_ok, last: bool) -> bool:
    if self._unread is not None:
      self._count(*self._unread)
      self._unread = None
    regular = last or self._deferred or self.manager.should_save(step)
    error = None
    if self._writing:
      error = write_error(self.manager)
      self._writing = self.manager.is_saving_in_progress()
    stop, failed = self.guard.poll(step, error is not None)
    if failed:
      self._write_failed(error)
    if not (regular or stop):
      self._unread = (step, update_ok)
      return False
    self._count(step, update_ok)
    if self.streak:
      self._deferred = regular and not stop
      logging.warning("step %d: not saved, %d updates in a row were skipped (last finite update: "
                      "step %d)%s", step, self.streak, self.last_finite,
                      "; saving at the next finite one" if self._deferred else "")
    elif self.saved_step != step:
      self._deferred = False
      save(self.manager, step, state, data_iter, force=True)
      self.saved_step, self._writing = step, True
    if stop:
      self.wait()
      self.message = (
          f"preempted: saved step {step}, exiting" if self.saved_step == step else
          f"preempted at step {step} during skipped updates: not saved; newest checkpoint: "
          f"{_step_or_none(self.manager.latest_step())}, exiting")
    return stop

  def _write_failed(self, error):
    how = f": {type(error).__name__}: {error}" if error is not None else " on another process"
    raise CheckpointWriteError(
        f"writing checkpoint step {self.saved_step} to {self.manager.directory} failed{how}; "
        f"the newest complete checkpoint is {_step_or_none(self.manager.latest_step())}")

  def wait(self):
    """Waits for the checkpoint write in flight; CheckpointWriteError when it failed."""
    try:
      self.manager.wait_until_finished()
    except Exception as e:  # noqa: BLE001 - whatever the writer raised
      self._write_failed(e)


# ---------------------------------------------------------------------------------------------
# model_init: parameters from elsewhere


@dataclasses.dataclass
class InitReport:
  source: str
  loaded: list[str]
  resized: list[str]
  left_at_init: list[str]
  unused: list[str]

  def summary(self) -> str:
    lines = [f"model_init from {self.source}: {len(self.loaded)} loaded, {len(self.resized)} "
             f"resized, {len(self.left_at_init)} left at init, {len(self.unused)} unused"]
    for name, items in (("resized", self.resized), ("left at init", self.left_at_init),
                        ("unused", self.unused)):
      if items:
        shown = ", ".join(items[:20]) + (f", ... ({len(items) - 20} more)" if len(items) > 20 else "")
        lines.append(f"  {name}: {shown}")
    return "\n".join(lines)


def _flat(tree) -> dict[str, Any]:
  return traverse_util.flatten_dict(dict(tree), sep="/")


def merge_into(template, loaded: dict[str, np.ndarray], source: str,
               resizable: str = r"pos_embed") -> tuple[Any, InitReport]:
  """Fills `template` (a param tree) with `loaded` (flat "a/b/c" -> array) where paths match.

  Shape mismatches on `resizable` params (position embeddings) are resized; other mismatches
  are an error naming both shapes. Returns (params, report).
  """
  flat_t = _flat(template)
  out, rep = {}, InitReport(source, [], [], [], sorted(set(loaded) - set(flat_t)))
  mismatched = []
  for k, v in flat_t.items():
    if k not in loaded:
      out[k] = v
      rep.left_at_init.append(k)
      continue
    w = np.asarray(loaded[k])
    if w.shape == tuple(v.shape):
      out[k] = jnp.asarray(w, v.dtype)
      rep.loaded.append(k)
    elif re.search(resizable, k):
      out[k] = jnp.asarray(convert.resize_pos_embed(w, v.shape), v.dtype)
      rep.resized.append(f"{k} {w.shape}->{tuple(v.shape)}")
    else:
      mismatched.append(f"{k}: checkpoint {w.shape} vs model {tuple(v.shape)}")
  if mismatched:
    raise ValueError(f"model_init {source}: shape mismatch for\n  " + "\n  ".join(mismatched))
  return traverse_util.unflatten_dict(out, sep="/"), rep


# --- UFM parameters --------------------------------------------------------------------------


def checkpoint_steps(path) -> list[int]:
  """Completed checkpoint steps in a workdir or its checkpoints/ folder."""
  path = pathlib.Path(path)
  d = path / "checkpoints" if (path / "checkpoints").is_dir() else path
  return sorted(int(x.name) for x in d.glob("*") if x.name.isdigit() and (x / "state").is_dir()
                and not x.name.endswith(".orbax-checkpoint-tmp"))


def read_state_numpy(path, step: int | None = None) -> tuple[dict, int]:
  """The saved TrainState as a tree of numpy arrays (any mesh it was written from) and its step."""
  path = pathlib.Path(path).absolute()
  d = path / "checkpoints" if (path / "checkpoints").is_dir() else path
  steps = checkpoint_steps(d)
  if not steps:
    raise FileNotFoundError(f"no checkpoint steps under {d}")
  step = steps[-1] if step is None else step
  if step not in steps:
    raise FileNotFoundError(f"no checkpoint step {step} under {d} (steps: {steps})")
  # The item's own handler: a Checkpointer opened on checkpoints/<step>/state looks there for the
  # step's _CHECKPOINT_METADATA (make_manager writes it one level up) and warns that it is
  # missing; a manager warns that the data item has no handler here.
  handler = ocp.PyTreeCheckpointHandler()
  item = d / str(step) / "state"
  try:
    tree = handler.metadata(item).tree
    restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), tree)
    return handler.restore(item, args=ocp.args.PyTreeRestore(restore_args=restore_args)), step
  finally:
    handler.close()


def _latest_params_from_workdir(path: pathlib.Path):
  state, step = read_state_numpy(path)
  return _flat(state["params"]), f"{path}@{step}"


def guess_kind(spec: str) -> tuple[str, str]:
  if ":" in spec and spec.split(":", 1)[0] in ("ckpt", "snapshot", "dinov2"):
    kind, path = spec.split(":", 1)
    return kind, path
  p = pathlib.Path(spec)
  if p.is_file():
    if p.suffix == ".pth":
      return "dinov2", spec
    if p.suffix == ".safetensors":
      from safetensors import safe_open
      with safe_open(str(p), "np") as f:
        keys = list(f.keys())
      return ("snapshot" if any(k.startswith("info_sharing.") for k in keys) else "dinov2"), spec
  if (p / "config.json").is_file() and (p / "model.safetensors").is_file():
    cfg = json.loads((p / "config.json").read_text())
    return ("dinov2" if cfg.get("model_type", "").startswith("dinov2") else "snapshot"), spec
  if (p / "checkpoints").is_dir() or any(x.name.isdigit() for x in p.glob("*")) \
      or (p / "params").exists() or (p / "model_config.json").exists():
    return "ckpt", spec
  raise FileNotFoundError(f"model_init: cannot tell what {spec!r} is (expected a training workdir, "
                          "a converted checkpoint, a UFM HF snapshot or DINOv2 weights)")


def load_init_params(spec: str, template, config=None) -> tuple[Any, InitReport]:
  """Parameters for `template` (the freshly initialised tree) from the `model_init` source.

  `config` (the model's UFMConfig) puts the loaded blocks into the template's layout: per-layer
  sources (snapshots, DINOv2, unscanned runs) stacked for a `scan_blocks` model, stacked ones
  (scan runs) split for a per-layer model. Without it the layouts must already agree.
  """
  kind, path = guess_kind(spec)
  if kind == "dinov2":
    loaded = convert.dinov2_to_flax(convert.read_dinov2(path))
  elif kind == "snapshot":
    _, params = convert.load_official(path)
    loaded = {k: np.asarray(v) for k, v in _flat(params).items()}
  else:
    p = pathlib.Path(path)
    if (p / "checkpoints").is_dir() or any(x.name.isdigit() for x in p.glob("*")):
      loaded, path = _latest_params_from_workdir(p)
    else:
      _, params = convert.load(path)
      loaded = {k: np.asarray(v) for k, v in _flat(params).items()}
  if config is not None:
    from ufm_jax.models import scan
    tree = traverse_util.unflatten_dict(loaded, sep="/")
    loaded = _flat(scan.to_layout(tree, config))
  params, report = merge_into(template, loaded, f"{kind}:{path}")
  logging.info("%s", report.summary())
  return params, report
