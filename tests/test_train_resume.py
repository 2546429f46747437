"""Preemption and resume on the synthetic config (tiny UFM, 56x56 synthetic pairs, rendered on
the fly): SIGKILL then resume gives bitwise the same next 20 losses as an uninterrupted run;
SIGTERM saves a checkpoint at the current step and exits with status 0.

The runs share a persistent XLA compilation cache, so only the first one compiles."""

import json
import pathlib
import re
import signal
import subprocess
import sys
import time

import pytest

from ufm_jax.runtime import checkpoint
from ufm_jax.testing import train_support

REPO = pathlib.Path(__file__).resolve().parents[1]
TOTAL = 34
CONFIG = [f"--config={REPO}/configs/synthetic.py:steps={TOTAL},batch=2,size=56,eval=false",
          "--config.ckpt_steps=4", "--config.keep_ckpt=3", "--config.log_training_steps=1"]


def _env(cache):
  return train_support.subprocess_env(REPO, cache)


class Run:
  """train.py in a subprocess; output goes to files (a full pipe would block the child)."""
  n = 0

  def __init__(self, workdir):
    Run.n += 1
    self.out_path = workdir.parent / f"run{Run.n}.out"
    self.err_path = workdir.parent / f"run{Run.n}.err"
    with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
      self.proc = subprocess.Popen(
          [sys.executable, str(REPO / "train.py"), f"--workdir={workdir}", *CONFIG],
          env=_env(workdir.parent / "xla_cache"), stdout=out, stderr=err, cwd=REPO)

  def poll(self):
    return self.proc.poll()

  def kill(self):
    self.proc.kill()

  def send_signal(self, sig):
    self.proc.send_signal(sig)

  def wait(self, timeout=None):
    self.proc.wait(timeout=timeout)

  def communicate(self, timeout=None):
    self.proc.wait(timeout=timeout)
    return self.out_path.read_text(), self.err_path.read_text()

  @property
  def returncode(self):
    return self.proc.returncode

  @property
  def stderr_text(self):
    return self.err_path.read_text()


def _start(workdir):
  return Run(workdir)


def _losses(workdir):
  """step -> loss, the last record of each step (a resumed run re-logs the steps after its start)."""
  out = {}
  path = pathlib.Path(workdir) / "metrics.jsonl"
  if path.exists():
    for line in path.read_text().splitlines():
      if line.strip():
        rec = json.loads(line)
        out[rec["step"]] = rec["loss"]
  return out


def _wait_for(pred, proc, timeout=240):
  t0 = time.time()
  while not pred():
    if proc.poll() is not None:
      raise AssertionError(f"run ended early: {proc.stderr_text[-3000:]}")
    if time.time() - t0 > timeout:
      proc.kill()
      raise AssertionError("timed out")
    time.sleep(0.05)


@pytest.mark.slow
def test_sigkill_resume_bitwise_and_sigterm_saves(tmp_path):
  ref_dir, run_dir = tmp_path / "ref", tmp_path / "run"
  ref = _start(ref_dir)  # the uninterrupted run; it also fills the compilation cache
  out_ref, err_ref = ref.communicate(timeout=600)
  assert ref.returncode == 0, err_ref[-3000:]

  # Interrupted run: SIGKILL once a checkpoint exists and a few more steps were taken.
  p = _start(run_dir)
  _wait_for(lambda: checkpoint.checkpoint_steps(run_dir / "checkpoints")
            and max(_losses(run_dir) or [0]) >= 7, p)
  p.send_signal(signal.SIGKILL)
  p.wait()
  killed_at = max(_losses(run_dir))
  resume_from = checkpoint.checkpoint_steps(run_dir / "checkpoints")[-1]
  assert resume_from < killed_at

  # Resume, then SIGTERM mid-way: must save the current step and exit cleanly.
  p = _start(run_dir)
  _wait_for(lambda: max(_losses(run_dir)) >= killed_at + 3, p)
  p.send_signal(signal.SIGTERM)
  out, err = p.communicate(timeout=120)
  assert p.returncode == 0, err[-3000:]
  assert f"resumed from step {resume_from}" in out
  saved = [l for l in out.splitlines() if l.startswith("preempted: saved step")]
  assert saved, out[-2000:]
  term_step = int(re.search(r"saved step (\d+)", saved[0]).group(1))
  assert checkpoint.checkpoint_steps(run_dir / "checkpoints")[-1] == term_step
  state, _ = checkpoint.read_state_numpy(run_dir, term_step)
  assert int(state["step"]) == term_step
  assert term_step >= killed_at + 3

  # Resume again to the end.
  p = _start(run_dir)
  out, err = p.communicate(timeout=240)
  assert p.returncode == 0, err[-3000:]

  a, b = _losses(ref_dir), _losses(run_dir)
  assert sorted(a) == list(range(1, TOTAL + 1)) and sorted(b) == sorted(a)
  nxt = list(range(resume_from + 1, resume_from + 21))
  assert [b[s] for s in nxt] == [a[s] for s in nxt]  # bitwise: float repr round-trips exactly
  assert all(b[s] == a[s] for s in a)
