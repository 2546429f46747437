"""train.py's held-out evaluator: EPE, the zero-flow bar and covisibility accuracy, by hand."""

import pathlib
import sys

import ml_collections
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
import train  # noqa: E402
from ufm_jax import sharding  # noqa: E402


def _evaluator():
  cfg = ml_collections.ConfigDict({
      "source": "synthetic", "root": None, "num_pairs": 5, "shape": (28, 28), "batch_size": 2,
      "kwargs": {"split": "val", "num_pairs": 5, "size": (28, 28), "pair_type": "shift",
                 "max_shift": 5}})
  return train.HeldoutEval(cfg, sharding.make_mesh("data:-1,fsdp:1"))


def test_zero_flow_and_exact_predictions():
  ev = _evaluator()
  samples = ev.samples
  covis = np.concatenate([s["covisibility"].ravel() for s in samples])
  speed = np.concatenate([np.linalg.norm(s["flow"], axis=-1).ravel() for s in samples])
  zero_bar = speed[covis].mean()

  def still(params, batch):
    del params
    return {"flow": np.zeros(batch["flow"].shape, np.float32),
            "covisibility": np.ones(batch["covisibility"].shape, np.float32)}

  res = ev.run(still, None).scalars
  assert abs(res["epe"] - zero_bar) < 1e-9 and abs(res["epe_zero"] - zero_bar) < 1e-9
  # Predicting "all covisible" is right exactly on the covisible pixels (all are covis_valid).
  assert abs(res["covis_acc"] - covis.mean()) < 1e-9
  assert res["px1"] == 100.0 * (speed[covis] > 1).mean()

  def oracle(params, batch):
    del params
    return {"flow": np.asarray(batch["flow"]),
            "covisibility": np.asarray(batch["covisibility"], np.float32)}

  res = ev.run(oracle, None).scalars
  assert res["epe"] == 0.0 and res["covis_acc"] == 1.0 and res["num_pairs"] == 5.0
  assert abs(res["epe_zero"] - zero_bar) < 1e-9
