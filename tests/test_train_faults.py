"""train.py under faults, on the tiny test config (ufm_jax/testing/train_support.py): SIGTERM on a save
step, SIGTERM to one of two processes, a corrupt newest checkpoint, a run of non-finite updates,
a failed background checkpoint write. Each run is a subprocess; they share an XLA cache."""

import json
import pathlib
import re
import signal
import socket
import subprocess
import sys
import time

import pytest

from ufm_jax.runtime import checkpoint
from ufm_jax.testing import train_support

# Slow tier: train.py runs killed, corrupted and restarted (pytest -m slow).
pytestmark = pytest.mark.slow

REPO = pathlib.Path(__file__).resolve().parents[1]
CONFIG = f"--config={REPO}/ufm_jax/testing/train_support.py"

# A checkpoint write that fails in the background (as on a full disk): orbax's final rename of the
# step named by UFM_TEST_FAIL_CKPT_STEP raises; everything else runs train.py unchanged.
_FAILING_WRITER = """
import os, runpy, sys
from orbax.checkpoint._src.path import atomicity
_finalize = atomicity.AtomicRenameTemporaryPath.finalize
async def finalize(self, *a, **k):
  if self.get_final().name == os.environ["UFM_TEST_FAIL_CKPT_STEP"]:
    raise OSError(28, "No space left on device (injected)", str(self.get_final()))
  return await _finalize(self, *a, **k)
atomicity.AtomicRenameTemporaryPath.finalize = finalize
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


@pytest.fixture(scope="module")
def xla_cache(tmp_path_factory):
  return tmp_path_factory.mktemp("xla_cache")


def _env(cache, **extra):
  return train_support.subprocess_env(REPO, cache, **extra)


class Run:
  """train.py in a subprocess; output goes to files (a full pipe would block the child)."""

  def __init__(self, workdir, args, env, name, wrapper=None):
    self.out_path = workdir.parent / f"{name}.out"
    self.err_path = workdir.parent / f"{name}.err"
    cmd = [sys.executable] + (["-c", wrapper] if wrapper else [])
    cmd += [str(REPO / "train.py"), f"--workdir={workdir}", CONFIG, "--config.log_training_steps=1",
            "--verbosity=0",  # the per-process metrics lines the tests read
            *args]
    with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
      self.proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=err, cwd=REPO)

  def wait(self, timeout):
    try:
      return self.proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
      self.proc.kill()
      raise AssertionError(f"timed out; stderr: {self.err[-3000:]}") from None

  @property
  def out(self):
    return self.out_path.read_text()

  @property
  def err(self):
    return self.err_path.read_text()


def _records(workdir):
  path = pathlib.Path(workdir) / "metrics.jsonl"
  if not path.exists():
    return {}
  recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
  return {r["step"]: r for r in recs}


def _wait_for(pred, runs, timeout=240):
  t0 = time.time()
  while not pred():
    for r in runs:
      if r.proc.poll() is not None:
        raise AssertionError(f"run ended early: {r.err[-3000:]}")
    if time.time() - t0 > timeout:
      for r in runs:
        r.proc.kill()
      raise AssertionError("timed out")
    time.sleep(0.05)


@pytest.mark.slow
def test_sigterm_on_a_save_step_exits_0_with_one_checkpoint(tmp_path, xla_cache):
  wd = tmp_path / "wd"
  # Every step is a save step, so the signal lands on one.
  run = Run(wd, ["--config.total_steps=100000", "--config.ckpt_steps=1"], _env(xla_cache), "term")
  _wait_for(lambda: max(_records(wd) or [0]) >= 3, [run])
  run.proc.send_signal(signal.SIGTERM)
  assert run.wait(120) == 0, run.err[-3000:]
  assert "StepAlreadyExistsError" not in run.err
  saved = re.search(r"preempted: saved step (\d+), exiting", run.out)
  assert saved, run.out[-2000:]
  step = int(saved.group(1))
  assert checkpoint.checkpoint_steps(wd)[-1] == step
  assert int(checkpoint.read_state_numpy(wd, step)[0]["step"]) == step


@pytest.mark.slow
def test_corrupt_newest_checkpoint_resumes_from_the_one_before(tmp_path, xla_cache):
  wd = tmp_path / "wd"
  args = ["--config.ckpt_steps=4", "--config.keep_ckpt=3"]
  run = Run(wd, ["--config.total_steps=8", *args], _env(xla_cache), "first")
  assert run.wait(240) == 0, run.err[-3000:]
  assert checkpoint.checkpoint_steps(wd)[-2:] == [4, 8]
  data = max((wd / "checkpoints" / "8" / "state" / "d").iterdir(), key=lambda f: f.stat().st_size)
  data.write_bytes(data.read_bytes()[:data.stat().st_size // 2])  # a truncated array file
  run = Run(wd, ["--config.total_steps=10", *args], _env(xla_cache), "resume")
  assert run.wait(240) == 0, run.err[-3000:]
  assert "resumed from step 4" in run.out
  assert re.search(r"checkpoint step 8 .* does not restore", run.err), run.err[-3000:]
  assert len(list((wd / "checkpoints").glob("8.corrupt-*"))) == 1
  assert checkpoint.checkpoint_steps(wd)[-1] == 10


@pytest.mark.slow
def test_runaway_nonfinite_updates_stop_with_status_1(tmp_path, xla_cache):
  wd = tmp_path / "wd"
  run = Run(wd, ["--config.total_steps=40", "--config.ckpt_steps=2", "--config.max_nonfinite_steps=5",
                 "--config.optim.lr.default=1e12"], _env(xla_cache), "nonfinite")
  assert run.wait(240) == 1, run.err[-3000:]
  recs = _records(wd)
  last_finite = max(s for s, r in recs.items() if r["update_ok"])
  assert last_finite < 10 and all(not recs[s]["update_ok"] for s in recs if s > last_finite)
  assert re.search(rf"NonFiniteSteps: 5 consecutive updates skipped .*last finite update: step "
                   rf"{last_finite}\b", run.err), run.err[-3000:]
  steps = checkpoint.checkpoint_steps(wd)
  assert steps and max(steps) <= last_finite


def test_failed_background_checkpoint_write_exits_nonzero_before_the_next_save(tmp_path,
                                                                             xla_cache):
  wd = tmp_path / "wd"
  run = Run(wd, ["--config.total_steps=60", "--config.ckpt_steps=20"],
            _env(xla_cache, UFM_TEST_FAIL_CKPT_STEP="20"), "failwrite", wrapper=_FAILING_WRITER)
  assert run.wait(240) != 0, run.err[-3000:]
  assert re.search(r"CheckpointWriteError: writing checkpoint step 20 .* failed: .*No space left "
                   r"on device.*the newest complete checkpoint is step 1", run.err), run.err[-3000:]
  assert 20 < max(_records(wd)) < 40  # reported before the next save would have found it
  assert checkpoint.checkpoint_steps(wd) == [1]
  state, step = checkpoint.read_state_numpy(wd)
  assert step == 1 and int(state["step"]) == 1


def _free_port():
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _two_processes(wd, args, cache, name):
  port = _free_port()
  runs = []
  for pid in range(2):
    env = _env(cache, XLA_FLAGS="--xla_force_host_platform_device_count=1",
               JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}", JAX_NUM_PROCESSES="2",
               JAX_PROCESS_ID=str(pid), JAX_CPU_COLLECTIVES_IMPLEMENTATION="gloo")
    runs.append(Run(wd, ["--config.mesh=data:-1,fsdp:1", *args], env, f"{name}{pid}"))
  return runs


def _logged_steps(run):
  return [int(m) for m in re.findall(r"process \d+ metrics \{\"step\": (\d+)", run.err)]


@pytest.mark.slow
@pytest.mark.multiprocess
def test_sigterm_to_one_of_two_processes_saves_the_same_step_on_both(tmp_path, xla_cache):
  wd = tmp_path / "wd"
  runs = _two_processes(wd, ["--config.total_steps=100000", "--config.ckpt_steps=1000"],
                        xla_cache, "mp")
  _wait_for(lambda: all(max(_logged_steps(r) or [0]) >= 5 for r in runs), runs)
  runs[1].proc.send_signal(signal.SIGTERM)  # one preempted host
  codes = [r.wait(120) for r in runs]
  assert codes == [0, 0], [r.err[-2000:] for r in runs]
  saved = [re.search(r"preempted: saved step (\d+), exiting", r.out) for r in runs]
  assert all(saved), [r.out[-1000:] for r in runs]
  step = int(saved[0].group(1))
  assert int(saved[1].group(1)) == step
  assert checkpoint.checkpoint_steps(wd)[-1] == step
  runs = _two_processes(wd, [f"--config.total_steps={step + 2}", "--config.ckpt_steps=1000"],
                        xla_cache, "mp_resume")
  assert [r.wait(180) for r in runs] == [0, 0], [r.err[-2000:] for r in runs]
  for r in runs:
    assert f"resumed from step {step}" in r.out
    assert sorted(set(_logged_steps(r))) == [step + 1, step + 2]
