"""One train step on a (data=4, fsdp=2) mesh of 8 fake CPU devices equals the 1-device step."""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from ufm_jax import testing
from ufm_jax.runtime import checkpoint
from ufm_jax.training import model_init

# Slow tier: train.py runs on 8 fake devices and on one (pytest -m slow).
pytestmark = pytest.mark.slow

REPO = pathlib.Path(__file__).resolve().parents[1]


def run_train(workdir, *overrides, devices=8, env_extra=None, timeout=240):
  env = testing.fake_devices_env(devices, **(env_extra or {}))
  cmd = [sys.executable, str(REPO / "train.py"), f"--config={REPO}/ufm_jax/testing/train_support.py",
         f"--workdir={workdir}", *overrides]
  return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, cwd=REPO)


def read_metrics(workdir):
  return [json.loads(l) for l in (pathlib.Path(workdir) / "metrics.jsonl").read_text().splitlines()]


def test_sharded_step_equals_single_device(tmp_path):
  runs = {}
  for name, mesh in (("mesh", "data:4,fsdp:2"), ("single", "data:1,fsdp:1")):
    wd = tmp_path / name
    r = run_train(wd, f"--config.mesh={mesh}", "--config.total_steps=2", "--config.ckpt_steps=1",
                  "--config.model.width=8")
    assert r.returncode == 0, r.stderr[-3000:]
    runs[name] = wd
  m_mesh, m_single = read_metrics(runs["mesh"]), read_metrics(runs["single"])
  for a, b in zip(m_mesh, m_single):
    assert a["loss"] == pytest.approx(b["loss"], rel=1e-5)
    assert a["loss_robust_epe"] == pytest.approx(b["loss_robust_epe"], rel=1e-5)
  s_mesh, _ = checkpoint.read_state_numpy(runs["mesh"], 2)
  s_single, _ = checkpoint.read_state_numpy(runs["single"], 2)
  flat_a = model_init.flatten(s_mesh["params"])
  flat_b = model_init.flatten(s_single["params"])
  assert flat_a.keys() == flat_b.keys()
  moved = 0
  for k in flat_a:
    np.testing.assert_allclose(flat_a[k], flat_b[k], rtol=1e-5, atol=1e-6, err_msg=k)
    moved += 1
  assert moved == 6
  # The fsdp rule really sharded something: the (4,2) run's kernels are split over fsdp.
  meta = json.loads((runs["mesh"] / "config.json").read_text())
  assert meta["mesh"] == "data:4,fsdp:2"
