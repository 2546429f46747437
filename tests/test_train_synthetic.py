"""The synthetic config trains: held-out EPE and the training loss fall (tiny UFM, 56x56 pairs).

A short run of train.py on the synthetic scene pairs with `tiny` (the README's run,
`python train.py --config=configs/synthetic.py --workdir=DIR`, is 2000 steps of the shift task:
minutes, too long here; its figures are in docs/synthetic_training.md): held-out EPE must drop
by >= 10%, the training loss must fall and everything a user looks at must be written; the
console gets one line per log step; `evaluate.py --checkpoint` on the workdir scores the task it
was trained on, with the zero-flow EPE beside the model's.
"""

import json
import os
import pathlib
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from ufm_jax import data

REPO = pathlib.Path(__file__).resolve().parents[1]
XLA_CACHE = pathlib.Path(tempfile.gettempdir()) / "ufm_jax_test_xla_cache"


@pytest.mark.slow
def test_synthetic_config_learns(tmp_path):
  env = dict(os.environ, PYTHONPATH=str(REPO),
             JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(XLA_CACHE),
             JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
  env.pop("XLA_FLAGS", None)
  steps = 60
  r = subprocess.run(
      [sys.executable, str(REPO / "train.py"),
       f"--config={REPO}/configs/synthetic.py:pairs=flow,model=tiny,loss=paper,steps={steps},"
       "batch=2,size=56",
       f"--workdir={tmp_path}", "--config.log_training_steps=1", "--config.ckpt_steps=1000",
       f"--config.evals.heldout.every={steps}", "--config.evals.heldout.num_pairs=16",
       "--config.evals.heldout.kwargs.num_pairs=16"],
      env=env, capture_output=True, text=True, timeout=900, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  evals = [json.loads(l) for l in (tmp_path / "eval.jsonl").read_text().splitlines()]
  assert [e["step"] for e in evals] == [0, steps]
  assert evals[1]["epe"] < 0.9 * evals[0]["epe"], evals
  metrics = [json.loads(l) for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert len(metrics) == steps
  first = sum(m["loss"] for m in metrics[:10]) / 10
  last = sum(m["loss"] for m in metrics[-10:]) / 10
  assert last < first, (first, last)
  for key in ("step", "epoch", "loss", "loss_robust_epe", "loss_covisibility_ce", "lr", "lr_encoder",
              "pairs_per_s"):
    assert key in metrics[-1]
  # What users see besides the metrics: the config, the command and TensorBoard events.
  assert json.loads((tmp_path / "config.json").read_text())["model_name"] == "tiny"
  assert "configs/synthetic.py" in (tmp_path / "command.txt").read_text()
  assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
  assert (tmp_path / "checkpoints" / str(steps)).is_dir()  # the final save

  # The console: one line per log step and one per held-out eval, each once; no INFO chatter.
  lines = (r.stdout + r.stderr).splitlines()
  step_lines = [l for l in lines if l.startswith("step ")]
  assert len(step_lines) == steps and len(set(step_lines)) == steps, step_lines[:4]
  evals_printed = [l for l in lines if l.startswith("[eval heldout]")]
  assert len(evals_printed) == 2
  # Each names what it scored, with evaluate.py's metric names and nothing undefined.
  assert evals_printed[1].startswith(
      f"[eval heldout] step {steps} (synthetic val split, 16 pairs, the params of step {steps}): ")
  assert " px2=" in evals_printed[1] and "px3" not in evals_printed[1]
  assert "nan" not in evals_printed[1]
  # The run ends with its checkpoint and the next commands.
  assert lines[-3] == f"checkpoint: {tmp_path}/checkpoints/{steps} (step {steps} of {tmp_path})"
  assert lines[-2] == (f"evaluate:   python evaluate.py --checkpoint {tmp_path} "
                       f"--out {tmp_path}/results")
  assert lines[-1].startswith(f"infer:      python -m ufm_jax infer SOURCE.png TARGET.png "
                              f"--checkpoint {tmp_path} ")
  assert not [l for l in lines if "INFO" in l], lines[:10]
  assert len(lines) <= steps + 2 + 3 + 3, lines   # a few warnings at most

  # evaluate.py on the workdir: its training task (flow pairs at 56 px), test split.
  out = tmp_path / "eval"
  r = subprocess.run([sys.executable, str(REPO / "evaluate.py"), "--checkpoint", str(tmp_path),
                      "--max_pairs", "4", "--out", str(out), "--no_progress"],
                     env=env, capture_output=True, text=True, timeout=600, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  assert "| epe | epe_zero |" in r.stdout
  assert f"model: {tmp_path}\nsynthetic: 4 pairs of the test split\n" in r.stdout
  # Standard JSON (no bare NaN), and the task scored at the size the run trained at (56x56, as its
  # held-out eval), not resized to the model config's inference resolution.
  results = json.loads((out / "results.json").read_text(),
                       parse_constant=lambda c: pytest.fail(f"results.json holds a bare {c}"))
  assert results["bench_resolutions"] == {"synthetic": "native"}
  assert results["checkpoint"] == str(tmp_path) and results["step"] == steps
  m = results["metrics"]
  src = data.get_source("synthetic", None, split="test", size=(56, 56), pair_type="flow")
  norm, count = 0.0, 0
  for i in range(4):
    s = src[i]
    covis = s["flow_valid"] & s["covisibility"] & s["covis_valid"]
    norm += np.linalg.norm(s["flow"].astype(np.float64), axis=-1)[covis].sum()
    count += int(covis.sum())
  assert m["synthetic/epe_zero"] == pytest.approx(norm / count, rel=1e-6)
  assert np.isfinite(m["synthetic/epe"])

  # ufm_jax.load + predict on the workdir infer at the size it trained at, not at 420x560.
  import ufm_jax
  from ufm_jax.runtime import inference
  model, _ = ufm_jax.load(tmp_path)
  assert inference.inference_resolutions(model) == [(56, 56)]
