"""Faults around checkpoints, in-process on a real orbax manager: a corrupt newest step (train or
data-iterator state) is skipped and moved aside; SIGTERM on a save step saves once; saves wait out
a run of non-finite updates and too long a run stops; a failed background write is reported."""

import logging
import pathlib
import time

import grain
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from orbax.checkpoint._src.path import atomicity

from ufm_jax.runtime import checkpoint
from ufm_jax.training import loop_control, optim


def _iterator(n=40):
  return iter(grain.MapDataset.range(n).map(lambda i: {"x": np.int64(i)})
              .batch(2).to_iter_dataset())


def _state(step):
  state = optim.TrainState.create({"w": jnp.arange(64.0)}, optim.optax.adam(1e-3))
  return state.replace(step=jnp.int32(step), params={"w": jnp.arange(64.0) + step})


def _abstract(state):
  dev = jax.sharding.SingleDeviceSharding(jax.devices()[0])
  return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=dev), state)


def _saved_run(tmp_path, steps=(2, 4, 6)):
  """Checkpoints at `steps`; returns the manager and the batch index each step's iterator is at."""
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=2, keep=5)
  it = _iterator()
  for step in range(1, max(steps) + 1):
    next(it)
    if step in steps:
      checkpoint.save(mngr, step, _state(step), it, force=True)
  mngr.wait_until_finished()
  assert checkpoint.checkpoint_steps(tmp_path) == list(steps)
  return mngr


def _truncate(path: pathlib.Path):
  data = path.read_bytes()
  path.write_bytes(data[:len(data) // 2])


def _largest_state_file(tmp_path, step):
  """The biggest array-data file of the step (state/d/: the OCDBT database restore reads; the
  per-process ocdbt.process_*/ copies are merged into it at save)."""
  files = list((tmp_path / "checkpoints" / str(step) / "state" / "d").iterdir())
  return max(files, key=lambda f: f.stat().st_size)


@pytest.mark.parametrize("what", ["state", "data"])
def test_restore_skips_and_moves_aside_a_corrupt_newest_step(tmp_path, what, caplog):
  mngr = _saved_run(tmp_path)
  if what == "state":
    _truncate(_largest_state_file(tmp_path, 6))
  else:
    (json_file,) = (tmp_path / "checkpoints" / "6" / "data").glob("*.json")
    _truncate(json_file)
  mngr.close()
  # A fresh start (as a restarted job): the corrupt step 6 is the latest the manager knows.
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=2, keep=5)
  assert mngr.latest_step() == 6
  it = _iterator()
  with caplog.at_level(logging.WARNING):
    restored, step = checkpoint.restore_latest(mngr, _abstract(_state(0)), it)
  assert step == 4 and int(restored.step) == 4
  np.testing.assert_array_equal(restored.params["w"], np.arange(64.0) + 4)
  assert int(next(it)["x"][0]) == 8  # batches 0..3 consumed: the iterator is at step 4 too
  assert any("step 6" in r.getMessage() and "does not restore" in r.getMessage()
             for r in caplog.records)
  moved = list((tmp_path / "checkpoints").glob("6.corrupt-*"))
  assert len(moved) == 1 and "did not restore" in (moved[0] / "CORRUPT.txt").read_text()
  assert checkpoint.checkpoint_steps(tmp_path) == [2, 4] and mngr.all_steps() == [2, 4]
  # Step 6 can be written again (the run continues from 4), and a restart does not retry it.
  checkpoint.save(mngr, 6, _state(6), it, force=True)
  mngr.close()
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=2, keep=5)
  restored, step = checkpoint.restore_latest(mngr, _abstract(_state(0)), _iterator())
  assert step == 6
  mngr.close()


def test_restore_fails_naming_every_step_when_none_restores_and_moves_nothing(tmp_path):
  mngr = _saved_run(tmp_path, steps=(2, 4))
  mngr.close()
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=2, keep=5)
  wrong = optim.TrainState.create({"w": jnp.zeros(3)}, optim.optax.adam(1e-3))  # another model
  with pytest.raises(RuntimeError, match=r"(?s)no checkpoint .* restores.*step 4: .*step 2: "):
    checkpoint.restore_latest(mngr, _abstract(wrong), _iterator())
  assert checkpoint.checkpoint_steps(tmp_path) == [2, 4]
  assert not list((tmp_path / "checkpoints").glob("*.corrupt-*"))
  mngr.close()


def _keeper(tmp_path, max_nonfinite=100, start_step=0):
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=4, keep=10)
  guard = loop_control.PreemptionGuard()
  return mngr, guard, loop_control.SaveAndStop(mngr, guard, max_nonfinite, start_step)


def _run(keeper, oks, it, total=None, sigterm_at=None):
  """Calls end_of_step for steps 1..len(oks) (update_ok = oks[step - 1]); returns the stop step."""
  total = total or len(oks)
  for step, ok in enumerate(oks, start=1):
    next(it)
    if step == sigterm_at:
      keeper.guard.requested = True
    if keeper.end_of_step(step, _state(step), it, jnp.bool_(ok), step == total):
      return step
  return None


def test_sigterm_on_a_save_step_saves_that_step_once(tmp_path):
  mngr, _, keeper = _keeper(tmp_path)
  assert _run(keeper, [True] * 12, _iterator(), total=100, sigterm_at=8) == 8
  assert keeper.message == "preempted: saved step 8, exiting"
  assert mngr.all_steps() == [1, 4, 8]  # orbax saves the first step of a fresh run too
  mngr.close()


def test_saves_wait_for_a_finite_update_and_a_long_nonfinite_run_stops(tmp_path):
  mngr, _, keeper = _keeper(tmp_path, max_nonfinite=5)
  oks = [True] * 3 + [False, False] + [True] + [True] * 4 + [False] * 8
  #      1..3       4 (save step) 5    6: the deferred save  7..10 (8 saves)  11..18
  with pytest.raises(loop_control.NonFiniteSteps,
                     match=r"5 consecutive updates skipped .*steps 11-15.*last finite update: "
                           r"step 10; newest checkpoint: step 8"):
    _run(keeper, oks, _iterator(), total=100)
  assert mngr.all_steps() == [1, 6, 8]  # 4 was deferred to 6; 12 and 16 never written
  mngr.close()


def test_sigterm_during_nonfinite_updates_writes_no_checkpoint(tmp_path):
  mngr, _, keeper = _keeper(tmp_path)
  oks = [True] * 5 + [False] * 5
  assert _run(keeper, oks, _iterator(), total=100, sigterm_at=7) == 7
  assert "not saved; newest checkpoint: step 4" in keeper.message
  assert mngr.all_steps() == [1, 4]
  mngr.close()


def test_failed_background_write_is_reported_within_a_few_steps(tmp_path, monkeypatch):
  mngr, _, keeper = _keeper(tmp_path)
  finalize = atomicity.AtomicRenameTemporaryPath.finalize

  async def failing_finalize(self, *a, **k):
    if self.get_final().name == "8":
      raise OSError(28, "No space left on device (injected)", str(self.get_final()))
    return await finalize(self, *a, **k)

  monkeypatch.setattr(atomicity.AtomicRenameTemporaryPath, "finalize", failing_finalize)
  it = _iterator()
  for step in range(1, 9):  # saves 1, 4 and (in the background) 8
    next(it)
    assert not keeper.end_of_step(step, _state(step), it, jnp.bool_(True), False)
  t0 = time.time()
  while mngr.is_saving_in_progress():  # the write of step 8 fails in the background...
    assert time.time() - t0 < 60, "the background write of step 8 never ended"
    time.sleep(0.01)
  next(it)
  with pytest.raises(loop_control.CheckpointWriteError,  # ...and the next step reports it
                     match=r"writing checkpoint step 8 .* failed: .*No space left on device.*"
                           r"newest complete checkpoint is step 4"):
    keeper.end_of_step(9, _state(9), it, jnp.bool_(True), False)
  assert mngr.latest_step() == 4
  mngr.close()
  mngr = checkpoint.make_manager(tmp_path, save_interval_steps=4, keep=10)
  restored, step = checkpoint.restore_latest(mngr, _abstract(_state(0)), _iterator())
  assert step == 4 and int(restored.step) == 4
  mngr.close()
