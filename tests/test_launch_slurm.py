"""launch/slurm/train.sbatch on a real Slurm: the synthetic config as two processes (two tasks of
one job, jax.distributed from Slurm's environment), `scancel --signal=TERM` stops it after a
checkpoint, and the same command submitted again resumes at that step.

Needs a Slurm controller with a node that runs 2 tasks; docs/launch.md sets one up on one machine
(launch/slurm/local_cluster.sh). Skipped where there is none.
"""

import os
import pathlib
import re
import shutil
import subprocess
import sys
import time

import pytest

from ufm_jax import checkpoint

REPO = pathlib.Path(__file__).resolve().parents[1]
SBATCH = REPO / "launch" / "slurm" / "train.sbatch"


def _require_slurm():
  if shutil.which("sbatch") is None:
    pytest.skip("Slurm is not installed (no sbatch on PATH); docs/launch.md sets up a one-node "
                "cluster")
  r = subprocess.run(["sinfo", "-h", "-o", "%t"], capture_output=True, text=True, timeout=30)
  if r.returncode or not any(s.strip() in ("idle", "mix", "alloc") for s in r.stdout.split()):
    pytest.skip(f"no Slurm controller with a usable node answers (sinfo: "
                f"{(r.stdout + r.stderr).strip()[:200]!r}); launch/slurm/local_cluster.sh start")


def _submit(out, workdir, *flags):
  env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_CPU_COLLECTIVES_IMPLEMENTATION="gloo",
             UFM_PYTHON=sys.executable, UFM_REPO=str(REPO),
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  cmd = ["sbatch", "--parsable", "--nodes=1", "--ntasks=2", "--ntasks-per-node=2",
         "--time=30", f"--output={out}", "--export=ALL", str(SBATCH),
         "configs/synthetic.py:eval=false", str(workdir), "--config.log_training_steps=1", *flags]
  r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO, timeout=60)
  assert r.returncode == 0, r.stderr
  return r.stdout.strip().split(";")[0]


def _state(job):
  r = subprocess.run(["scontrol", "show", "job", "-o", job], capture_output=True, text=True,
                     timeout=30)
  m = re.search(r"JobState=(\w+)", r.stdout)
  return m.group(1) if m else "GONE"


def _wait_until(pred, timeout, what):
  t0 = time.time()
  while time.time() - t0 < timeout:
    if pred():
      return
    time.sleep(2)
  raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _ended(job):
  return _state(job) not in ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED")


@pytest.mark.slurm
@pytest.mark.slow
def test_sbatch_two_processes_stop_with_checkpoint_and_resume(tmp_path):
  _require_slurm()
  workdir = tmp_path / "run"
  out1, out2 = tmp_path / "job1.out", tmp_path / "job2.out"
  jobs = []
  try:
    jobs.append(_submit(out1, workdir, "--config.total_steps=100000"))
    # Stop it once the loop runs (both processes are in it: every step is a collective).
    _wait_until(lambda: out1.exists() and re.search(r"^step 3/", out1.read_text(), re.M),
                900, f"step 3 in {out1}")
    subprocess.run(["scancel", "--signal=TERM", jobs[0]], check=True, timeout=30)
    _wait_until(lambda: _ended(jobs[0]), 300, f"job {jobs[0]} to end")
    text = out1.read_text()
    assert "2 tasks" in text, text[-3000:]
    saved = [int(s) for s in re.findall(r"preempted: saved step (\d+), exiting", text)]
    assert saved and len(set(saved)) == 1, text[-3000:]   # every process stopped after one step
    step = saved[0]
    assert _state(jobs[0]) == "COMPLETED", text[-3000:]
    assert checkpoint.checkpoint_steps(workdir / "checkpoints")[-1] == step

    jobs.append(_submit(out2, workdir, f"--config.total_steps={step + 2}"))
    _wait_until(lambda: _ended(jobs[1]), 900, f"job {jobs[1]} to end")
    text = out2.read_text()
    assert _state(jobs[1]) == "COMPLETED", text[-3000:]
    assert f"resumed from step {step}" in text, text[-3000:]
    assert re.search(rf"^step {step + 2}/{step + 2} ", text, re.M), text[-3000:]
    assert not re.search(rf"^step {step}/", text, re.M)   # no step is trained twice
    assert checkpoint.checkpoint_steps(workdir / "checkpoints")[-1] == step + 2
  finally:
    for job in jobs:
      subprocess.run(["scancel", job], capture_output=True, timeout=30)
