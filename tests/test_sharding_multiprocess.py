"""Two CPU processes on localhost (jax.distributed + gloo), each with 2 fake devices, run the same
train.py job on a 4-device mesh: both must see the same losses, and equal the 1-process run. On
the recipes' default mesh (data:1,fsdp:-1) the train state is sharded across the two processes."""

import json
import pathlib
import re
import socket
import subprocess
import sys

import pytest

from ufm_jax import testing

# Slow tier: train.py jobs of two processes (pytest -m slow).
pytestmark = pytest.mark.slow

REPO = pathlib.Path(__file__).resolve().parents[1]


def _free_port():
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _losses(stderr):
  out = {}
  for m in re.finditer(r"process (\d+) metrics (\{.*\})", stderr):
    rec = json.loads(m.group(2))
    out[rec["step"]] = rec["loss"]
  return out


@pytest.mark.multiprocess
@pytest.mark.parametrize("mesh", ["data:-1,fsdp:2", "data:1,fsdp:-1"])
def test_two_processes_same_loss(tmp_path, mesh):
  port = _free_port()
  procs = []
  for pid in range(2):
    env = testing.fake_devices_env(2)
    env.update({
        "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}", "JAX_NUM_PROCESSES": "2",
        "JAX_PROCESS_ID": str(pid), "JAX_CPU_COLLECTIVES_IMPLEMENTATION": "gloo"})
    cmd = [sys.executable, str(REPO / "train.py"), f"--config={REPO}/ufm_jax/testing/train_support.py",
           f"--workdir={tmp_path / 'mp'}", "--config.total_steps=2", "--config.ckpt_steps=2",
           f"--config.mesh={mesh}", "--verbosity=0"]  # per-process metrics logs
    procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, cwd=REPO))
  outs = []
  for p in procs:
    try:
      out, err = p.communicate(timeout=240)
    except subprocess.TimeoutExpired:
      for q in procs:
        q.kill()
      raise
    outs.append((p.returncode, out, err))
  for rc, out, err in outs:
    assert rc == 0, err[-3000:]
  l0, l1 = _losses(outs[0][2]), _losses(outs[1][2])
  assert sorted(l0) == [1, 2] and l0 == l1
  # Same global batch and mesh size as a single process with 4 devices.
  env = testing.fake_devices_env(4)
  r = subprocess.run([sys.executable, str(REPO / "train.py"),
                      f"--config={REPO}/ufm_jax/testing/train_support.py",
                      f"--workdir={tmp_path / 'sp'}", "--config.total_steps=2",
                      "--config.ckpt_steps=2", f"--config.mesh={mesh}", "--verbosity=0"],
                     env=env, capture_output=True, text=True, timeout=240, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  ls = _losses(r.stderr)
  for k in ls:
    assert l0[k] == pytest.approx(ls[k], rel=1e-5)
