"""benchmarks/inference.py counts the FLOPs the forward really does.

The CPU attention path is a loop over heads and query chunks, and XLA's cost analysis counts a
loop body once; a share of peak built on that count would understate the work. Checked against
the matmul FLOPs of attention written out from its shapes.
"""

import json
import pathlib
import subprocess
import sys

import pytest

from ufm_jax.models import variants

REPO = pathlib.Path(__file__).resolve().parents[1]


def _breakdown(config, tmp_path):
  """The JSON of one `--breakdown` run of benchmarks/inference.py at 56x56."""
  out = tmp_path / "bench.json"
  cmd = [sys.executable, str(REPO / "benchmarks" / "inference.py"), "--config", config,
         "--size", "56x56", "--runs", "1", "--warmup", "0", "--breakdown", "--json", str(out)]
  r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  return json.loads(out.read_text())


@pytest.mark.slow
def test_breakdown_counts_every_head_of_cpu_attention(tmp_path):
  res = _breakdown("fixture_small", tmp_path)
  enc = variants.get("fixture_small").encoder
  b, n, c = 2, (56 // enc.patch_size) ** 2 + 1, enc.embed_dim  # two images; patches + cls token
  # qkv and output projections, then q.k and p.v over all heads.
  matmuls = 2 * b * n * c * 4 * c + 2 * 2 * b * n * n * c
  stage = next(s for s in res["stages"] if s["stage"] == "encoder attention")
  assert matmuls <= stage["gflop"] * 1e9 <= 1.25 * matmuls, (stage, matmuls / 1e9)


@pytest.mark.slow
def test_breakdown_times_the_refiner_stages(tmp_path):
  # UFMRefine shares the refiner's scope with the root: its stages must still be found.
  stages = {s["stage"]: s for s in _breakdown("tiny_refine", tmp_path)["stages"]}
  assert stages["refiner U-Net"]["calls"] == 1                 # both views in one batch
  assert stages["refiner classification head"]["calls"] == 2   # per view
  assert stages["refiner local refinement"]["calls"] == 1
  assert all(stages[k]["gflop"] > 0 for k in stages if k.startswith("refiner"))


@pytest.mark.slow
def test_official_side_by_side_says_why_it_is_not_available(tmp_path):
  # A folder without the official packages: the benchmark starts again with it on PYTHONPATH
  # (the clone is a checkout, not an installed package), still cannot import `uniflowmatch`,
  # and reports the official side as not available instead of failing.
  out = tmp_path / "bench.json"
  clone = tmp_path / "not_a_clone"
  clone.mkdir()
  cmd = [sys.executable, str(REPO / "benchmarks" / "inference.py"), "--config", "fixture_small",
         "--size", "28x28", "--runs", "1", "--warmup", "0", "--official", str(clone),
         "--json", str(out)]
  r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  res = json.loads(out.read_text())
  assert res["official"] == "not available"
  assert "not importable" in res["official_reason"]
  assert "official PyTorch code: not available" in r.stdout
