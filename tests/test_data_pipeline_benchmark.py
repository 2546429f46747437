"""benchmarks/data_pipeline.py --table1: every Table 1 dataset, written in its real on-disk format
and in the official processed layout, goes through the symmetrized training pipeline, and the
host CPU per row is counted for every row (synchronous reads: no prefetched row escapes the
timed window)."""

import json
import pathlib
import subprocess
import sys

import pytest

from ufm_jax.data import mixture

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_table1_mixture_cpu_per_row(tmp_path):
  cmd = [sys.executable, str(REPO / "benchmarks" / "data_pipeline.py"), "--table1",
         "--longest_side", "112", "--batches", "2", "--warmup", "1", "--batch_size", "4"]
  r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
  assert r.returncode == 0, r.stderr[-3000:]
  res = json.loads(r.stdout.strip().splitlines()[-1])
  assert sorted(res["ms_per_row"]) == sorted(mixture.QUOTAS)
  # Decoding and augmenting an 84x112 pair costs well over 0.1 ms of CPU; a row made before the
  # timed window (prefetch) would show as ~0.
  assert all(ms > 0.1 for ms in res["ms_per_row"].values()), res["ms_per_row"]
  weights = sum(mixture.QUOTAS.values())
  mean = sum(mixture.QUOTAS[k] * v for k, v in res["ms_per_row"].items()) / weights
  assert abs(res["table1_mean_ms_per_row"] - mean) < 1e-6
  quotas = {k: q for k, (q, _) in mixture.RECIPES["ufm560"].items()}
  assert sorted(res["official_ms_per_row"]) == sorted(quotas)
  assert all(ms > 0.1 for ms in res["official_ms_per_row"].values()), res["official_ms_per_row"]
  mean = sum(quotas[k] * v for k, v in res["official_ms_per_row"].items()) / sum(quotas.values())
  assert abs(res["official_mean_ms_per_row"] - mean) < 1e-6
