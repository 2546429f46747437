"""`python train.py --config=configs/ufm560.py --config.input.data_root=ROOT` on a data root in
the official layout (every dataset of the official 560 recipe as a tiny tree) runs a few steps."""

import json
import os
import pathlib
import subprocess
import sys
import tempfile

import pytest

from ufm_jax.data import mixture
from ufm_jax.testing import official_trees

REPO = pathlib.Path(__file__).resolve().parents[1]
XLA_CACHE = pathlib.Path(tempfile.gettempdir()) / "ufm_jax_test_xla_cache"


@pytest.mark.slow
def test_ufm560_trains_on_an_official_data_root(tmp_path):
  root = tmp_path / "root_data_dir"
  official_trees.write_official_root(str(root), hw=(36, 48))
  env = dict(os.environ, PYTHONPATH=str(REPO), JAX_PLATFORMS="cpu",
             JAX_COMPILATION_CACHE_DIR=str(XLA_CACHE),
             JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
  env.pop("XLA_FLAGS", None)
  work = tmp_path / "work"
  r = subprocess.run(
      [sys.executable, str(REPO / "train.py"), "--config=configs/ufm560.py:model=tiny",
       f"--workdir={work}", f"--config.input.data_root={root}", "--config.total_steps=3",
       # 4 rows: the recipe's 8 loss groups (one per GPU of the paper's run) need 16; 2 here
       "--config.input.batch_size=4", "--config.loss.groups=2", "--config.input.num_workers=0",
       "--config.input.shapes=((42, 56),)",
       "--config.log_training_steps=1", "--verbosity=0"],
      env=env, capture_output=True, text=True, timeout=900, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  metrics = [json.loads(l) for l in (work / "metrics.jsonl").read_text().splitlines()]
  assert [m["step"] for m in metrics] == [1, 2, 3] and metrics[-1]["skipped"] == 0
  log = r.stdout + r.stderr
  for name in mixture.RECIPES["ufm560"]:   # every dataset found in its official layout
    assert f"dataset {name}: official layout at {root}" in log, name
  assert "dropped from the mixture" not in log
