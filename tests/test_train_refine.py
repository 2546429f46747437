"""The refine stage end to end (tiny UFM-Refine, synthetic pairs): the base stays bitwise frozen,
the refiner moves, and the refinement loss is what is logged."""

import json
import os
import pathlib
import subprocess
import sys
import tempfile

import jax
import numpy as np
import pytest

from ufm_jax.runtime import checkpoint
from ufm_jax.training import model_init

# Slow tier: a train.py run (pytest -m slow).
pytestmark = pytest.mark.slow

REPO = pathlib.Path(__file__).resolve().parents[1]
XLA_CACHE = pathlib.Path(tempfile.gettempdir()) / "ufm_jax_test_xla_cache"
REFINER = ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias")


def test_refine_stage_trains_only_the_refiner(tmp_path):
  env = dict(os.environ, PYTHONPATH=str(REPO),
             JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(XLA_CACHE),
             JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
  env.pop("XLA_FLAGS", None)
  r = subprocess.run(
      [sys.executable, str(REPO / "train.py"),
       f"--config={REPO}/configs/ufm560_refine.py:model=tiny_refine,data=synthetic,steps=3",
       f"--workdir={tmp_path}", "--config.ckpt_steps=1", "--config.keep_ckpt=5",
       "--config.apply_kwargs.symmetrized=False"],
      env=env, capture_output=True, text=True, timeout=900, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  s1, _ = checkpoint.read_state_numpy(tmp_path, 1)
  s3, _ = checkpoint.read_state_numpy(tmp_path, 3)
  f1, f3 = model_init.flatten(s1["params"]), model_init.flatten(s3["params"])
  moved = []
  for k in f1:
    if k.split("/")[0] in REFINER:
      moved.append(not np.array_equal(f1[k], f3[k]))
    else:
      np.testing.assert_array_equal(f1[k], f3[k], err_msg=k)  # frozen base
  assert moved and any(moved)
  # No optimizer state for the frozen base: Adam moments only for refiner leaves.
  n_refiner = sum(v.size for k, v in f1.items() if k.split("/")[0] in REFINER)
  n_state = sum(v.size for v in jax.tree.leaves(s3["opt_state"]) if np.ndim(v) > 0)
  assert n_state == 2 * n_refiner
  rec = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert "loss_refinement_cross_entropy" in rec[-1]
  assert "refinement_cross_entropy/ratio_in_refinement_range" in rec[-1]
