"""A jax.profiler trace of chosen training steps: `--config.profile_steps=A:B` (docs/training.md).

Steps are numbered as train.py prints them (step 1 is the first update). A:B traces steps A to
B-1, as a Python slice: the trace starts before step A fetches its batch and stops once step B-1
has finished on the device. It is written under WORKDIR/profile (plugins/profile/<time>/
<host>.xplane.pb), which TensorBoard's profile plugin and XProf read. A run resumed past A traces
nothing; one that stops inside the range (preemption, the last step) ends the trace there.
"""

from __future__ import annotations

import pathlib

from absl import logging


def profile_steps(value) -> tuple[int, int] | None:
  """(A, B) of `config.profile_steps` "A:B" (1 <= A < B), None when unset or empty; ValueError
  naming the key otherwise."""
  if value is None or str(value).strip() == "":
    return None
  text = str(value).strip()
  a, sep, b = text.partition(":")
  try:
    first, stop = int(a), int(b)
  except ValueError:
    first = stop = None
  if not sep or first is None or not 1 <= first < stop:
    raise ValueError(f"--config.profile_steps={text!r}: expected A:B, the steps A to B-1 "
                     f"(1 <= A < B), e.g. 10:15")
  return first, stop


class StepTrace:
  """Starts and stops the trace around train.py's steps (`before_step`, `after_step`)."""

  def __init__(self, steps: tuple[int, int] | None, folder, start_step: int):
    self.steps = steps
    self.folder = pathlib.Path(folder)
    self.active = False
    self._annotation = None
    if steps is not None and start_step >= steps[0]:
      logging.warning("profile_steps %d:%d: the run resumed at step %d, past the range: no "
                      "trace", steps[0], steps[1], start_step)
      self.steps = None

  def before_step(self, step: int):
    """Before step `step` (the one the loop is about to make) fetches its batch."""
    import jax
    if self.steps is None:
      return
    if step == self.steps[0] and not self.active:
      self.folder.mkdir(parents=True, exist_ok=True)
      jax.profiler.start_trace(str(self.folder))
      self.active = True
    if self.active:
      self._annotation = jax.profiler.StepTraceAnnotation("train", step_num=step)
      self._annotation.__enter__()

  def after_step(self, step: int, outputs):
    """After step `step` was dispatched; the trace ends once step B-1 is done on the device."""
    import jax
    if not self.active:
      return
    self._annotation.__exit__(None, None, None)
    self._annotation = None
    if step >= self.steps[1] - 1:
      jax.block_until_ready(outputs)
      self.stop()

  def stop(self):
    """Ends the trace (idempotent): at the range's end, or when the loop stops inside it."""
    import jax
    if not self.active:
      return
    if self._annotation is not None:
      self._annotation.__exit__(None, None, None)
      self._annotation = None
    jax.profiler.stop_trace()
    self.active = False
    self.steps = None
    print(f"profile: trace written under {self.folder} (tensorboard --logdir={self.folder}, "
          f"or xprof --logdir={self.folder})", flush=True)
