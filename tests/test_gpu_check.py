"""benchmarks/gpu_check.py keeps working: its --smoke mode on CPU runs every measurement path."""

import json
import pathlib
import subprocess
import sys

REPO = pathlib.Path(__file__).resolve().parents[1]


def test_gpu_check_smoke_runs_forward_and_train_step():
  out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--smoke"],
                       capture_output=True, text=True, timeout=900, cwd=REPO)
  assert out.returncode == 0, out.stderr[-3000:]
  res = json.loads(out.stdout.strip().splitlines()[-1])
  assert not res["failures"], res["failures"]
  kinds = [r["kind"] for r in res["results"]]
  assert kinds.count("forward") == 1 and kinds.count("train") == 1
  train = res["results"][-1]
  assert train["step_ms"] > 0 and train["pairs_per_s"] > 0 and train["batch"] == 2
  assert "| train step tiny (remat=False) |" in out.stdout
