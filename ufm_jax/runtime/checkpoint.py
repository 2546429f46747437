"""Checkpoints of a training run: the orbax manager (train state + data iterator), restoring the
newest step that restores, and reading a step back as numpy.

Layout of a workdir:
  checkpoints/<step>/state   the TrainState (orbax, sharded arrays, written asynchronously)
  checkpoints/<step>/data    the grain iterator state (one JSON per process)

When to save and stop is `ufm_jax.training.loop_control`; parameters from elsewhere (`model_init`) are
`ufm_jax.training.model_init`.
"""

from __future__ import annotations

import os
import pathlib
import time

import jax
import numpy as np
import orbax.checkpoint as ocp
from absl import logging

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



# ---------------------------------------------------------------------------------------------
# Reading a step back (tools, model_init, to-official)


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
