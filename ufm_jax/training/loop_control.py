"""When train.py's loop saves and stops: `PreemptionGuard` (SIGTERM on any process -> every
process stops after the same step) and `SaveAndStop` (once per step: save on the interval, at the
end, on preemption; never inside a run of skipped non-finite updates; raise when a background
write failed or too many updates in a row were skipped).
"""

from __future__ import annotations

import signal

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging

from ufm_jax.runtime import checkpoint

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


class NonFiniteSteps(RuntimeError):
  """Too many consecutive updates were skipped for a non-finite loss or gradient."""


class CheckpointWriteError(RuntimeError):
  """A background checkpoint write failed."""


def _step_or_none(step) -> str:
  return "none" if step is None else f"step {step}"


class SaveAndStop:
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
      error = checkpoint.write_error(self.manager)
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
      checkpoint.save(self.manager, step, state, data_iter, force=True)
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
