"""benchmarks/gpu_check.py keeps working: its --smoke mode on CPU runs every measurement path."""

import json
import pathlib
import subprocess
import sys

import pytest

from ufm_jax import testing

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_gpu_check_smoke_runs_parity_forward_and_train_step(reference_dir, tmp_path):
  out_file = tmp_path / "results.jsonl"
  out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--smoke",
                        "--fixture", str(reference_dir / "base"), "--out", str(out_file)],
                       capture_output=True, text=True, timeout=900, cwd=REPO)
  assert out.returncode == 0, out.stderr[-3000:]
  res = json.loads(out.stdout.strip().splitlines()[-1])
  assert not res["failures"], res["failures"]
  kinds = [r["kind"] for r in res["results"]]
  assert kinds == ["parity"] * 3 + ["forward", "train"]
  # On CPU every float32 matmul is exact float32: the official outputs within the parity tests'
  # tolerance; bfloat16 is further off but still close to them.
  f32 = [r for r in res["results"] if r["kind"] == "parity" and r["case"].startswith("float32")]
  assert all(r["flow_max_px"] < 1e-3 and r["covis_max"] < 1e-4 for r in f32), f32
  bf16 = res["results"][2]
  assert 1e-3 < bf16["flow_max_px"] < 2.0, bf16
  assert all(r["attention_kernels"] == "none fused" for r in res["results"][:4])
  fwd, train = res["results"][-2:]
  assert fwd["gflop_per_pair"] > 0 and fwd["tflop_s"] > 0  # counted on the host CPU
  assert train["step_ms"] > 0 and train["pairs_per_s"] > 0 and train["batch"] == 2
  assert train["tflop_per_step"] > 0
  assert "| train step tiny (remat=False) |" in out.stdout
  # Each case reached --out as it finished, then the closing line with the failures.
  lines = [json.loads(x) for x in out_file.read_text().splitlines()]
  assert [x.get("kind") for x in lines[:-1]] == kinds and lines[-1]["failures"] == []


def test_attention_kernels_counts_fused_custom_calls():
  gc = testing.load_script("benchmarks/gpu_check.py")
  hlo = ('%a = custom-call(), custom_call_target="__cudnn$fmhaSoftmax"\n'
         '%b = custom-call(), custom_call_target="__cublas$gemm"\n'
         '%c = custom-call(), custom_call_target="__cudnn$fmhaSoftmax"\n')
  assert gc.attention_kernels(hlo) == "2 x __cudnn$fmhaSoftmax"
  assert gc.attention_kernels('custom_call_target="__cublas$gemm"') == "none fused"
