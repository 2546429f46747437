"""launch/slurm/train.sbatch on a real Slurm: the synthetic config as two processes (two tasks of
one job, jax.distributed from Slurm's environment). `scancel --signal=TERM` stops it after a
checkpoint, and the same command submitted again resumes at that step; a requeued job (what
preemption does, and what the script does itself before the time limit) starts again by itself and
resumes.

Needs a Slurm controller with a node that runs 2 tasks; docs/launch.md sets one up on one machine
(launch/slurm/local_cluster.sh), and .ci/run does in CI. Skipped where there is none, except under
CI=true, where a missing cluster fails: the launcher must not break silently.
"""

import os
import pathlib
import re
import shutil
import subprocess
import sys
import time

import pytest

from ufm_jax import testing
from ufm_jax.runtime import checkpoint

REPO = pathlib.Path(__file__).resolve().parents[1]
SBATCH = REPO / "launch" / "slurm" / "train.sbatch"


_CI_NOTE = "CI=true: .ci/run installs slurm-wlm and munge and starts launch/slurm/local_cluster.sh"


def _require_slurm():
  if shutil.which("sbatch") is None:
    testing.skip_or_fail("Slurm is not installed (no sbatch on PATH); docs/launch.md sets up a "
                         "one-node cluster", _CI_NOTE)
  r = subprocess.run(["sinfo", "-h", "-o", "%t"], capture_output=True, text=True, timeout=30)
  if r.returncode or not any(s.strip() in ("idle", "mix", "alloc") for s in r.stdout.split()):
    testing.skip_or_fail(f"no Slurm controller with a usable node answers (sinfo: "
                         f"{(r.stdout + r.stderr).strip()[:200]!r}); "
                         "launch/slurm/local_cluster.sh start", _CI_NOTE)


def _submit(out, workdir, *flags):
  # Each start of the job compiles the same step in both tasks; JAX's persistent cache beside the
  # workdir lets the restarts load it (the test's minutes are mostly those compiles).
  env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_CPU_COLLECTIVES_IMPLEMENTATION="gloo",
             JAX_COMPILATION_CACHE_DIR=str(pathlib.Path(workdir).parent / "xla_cache"),
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


def _runs(text):
  """The appended log split at the script's start line: one piece per start of the job."""
  return re.split(r"^job \d+ \(restart \d+\)", text, flags=re.M)[1:]


def _saved(run):
  saved = {int(s) for s in re.findall(r"preempted: saved step (\d+), exiting", run)}
  assert len(saved) == 1, run[-3000:]   # every process saved the same step
  return saved.pop()


def _steps(run):
  return [int(s) for s in re.findall(r"^step (\d+)/", run, re.M)]


@pytest.mark.slurm
@pytest.mark.slow
def test_sbatch_stop_requeue_and_resume(tmp_path):
  """Every way a job stops, on one run of two processes; each time both tasks save the same step,
  and the next start resumes from it, trains no step twice and skips none:
  1. `scontrol requeue` (what preemption does on a partition with PreemptMode=REQUEUE): Slurm
     signals the tasks and starts the same job again by itself (restart 1).
  2. USR1 to the batch script (the time-limit warning, `--signal=B:USR1@300`): the script has the
     tasks save, then requeues the job itself (restart 2).
  3. `scancel --signal=TERM`: the job ends COMPLETED; the same command submitted again (with
     total_steps two steps further) resumes and finishes.
  """
  _require_slurm()
  workdir, out, out2 = tmp_path / "run", tmp_path / "job.out", tmp_path / "job2.out"
  text = lambda: out.read_text() if out.exists() else ""   # noqa: E731
  jobs = []
  try:
    jobs.append(_submit(out, workdir, "--config.total_steps=100000"))
    job = jobs[0]
    stops = (["scontrol", "requeue", job], ["scancel", "--batch", "--signal=USR1", job],
             ["scancel", "--signal=TERM", job])
    for start, stop in enumerate(stops, 1):
      # Stop it once this start's loop has run two steps (both processes are in it: every step
      # is a collective).
      _wait_until(lambda: len(_runs(text())) == start and len(_steps(_runs(text())[-1])) >= 2,
                  900, f"two steps of start {start} in {out}")
      subprocess.run(stop, check=True, timeout=30)
      if start < len(stops):
        _wait_until(lambda: len(_runs(text())) == start + 1 and _steps(_runs(text())[-1]),
                    900, f"a step after restart {start} in {out}")
    _wait_until(lambda: _ended(job), 300, f"job {job} to end")
    runs = _runs(text())
    assert _state(job) == "COMPLETED", runs[-1][-3000:]
    assert len(runs) == 3, text()[-3000:]
    assert "DUE TO JOB REQUEUE" in runs[0], runs[0][-3000:]
    assert f"requeueing job {job}" in runs[1], runs[1][-3000:]
    assert "requeueing" not in runs[2], runs[2][-3000:]
    step = _saved(runs[2])
    assert checkpoint.checkpoint_steps(workdir / "checkpoints")[-1] == step

    jobs.append(_submit(out2, workdir, f"--config.total_steps={step + 2}"))
    _wait_until(lambda: _ended(jobs[1]), 900, f"job {jobs[1]} to end")
    runs.append(out2.read_text())
    assert _state(jobs[1]) == "COMPLETED", runs[-1][-3000:]
  finally:
    for j in jobs:
      subprocess.run(["scancel", j], capture_output=True, timeout=30)
  assert "2 tasks" in runs[0], runs[0][-3000:]
  for before, after in zip(runs, runs[1:]):
    step = _saved(before)
    assert f"resumed from step {step}" in after, after[-3000:]
    assert _steps(after)[0] == step + 1, after[-3000:]
  assert _steps(runs[-1])[-1] == step + 2, runs[-1][-3000:]
  assert checkpoint.checkpoint_steps(workdir / "checkpoints")[-1] == step + 2
