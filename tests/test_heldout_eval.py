"""train.py's held-out evaluator (ufm_jax.evaluators.train_evals): EPE, the zero-flow bar and covisibility accuracy, by hand."""

import ml_collections
import numpy as np
import pytest

from ufm_jax.training import sharding, trainer
from ufm_jax.evaluators import train_evals


def _evaluator():
  cfg = ml_collections.ConfigDict({
      "source": "synthetic", "root": None, "num_pairs": 5, "shape": (28, 28), "batch_size": 2,
      "kwargs": {"split": "val", "num_pairs": 5, "size": (28, 28), "pair_type": "shift",
                 "max_shift": 5}})
  return train_evals.HeldoutEval(cfg, sharding.make_mesh("data:-1,fsdp:1"))


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
  assert res["px2"] == 100.0 * (speed[covis] > 2).mean() and "px3" not in res  # evaluate.py's set
  # Shift pairs occlude nothing (what leaves the view is not scored): no epe_occluded at all.
  assert "epe_occluded" not in res
  assert ev.describe() == "synthetic val split, 5 pairs"

  def oracle(params, batch):
    del params
    return {"flow": np.asarray(batch["flow"]),
            "covisibility": np.asarray(batch["covisibility"], np.float32)}

  res = ev.run(oracle, None).scalars
  assert res["epe"] == 0.0 and res["covis_acc"] == 1.0 and res["num_pairs"] == 5.0
  assert abs(res["epe_zero"] - zero_bar) < 1e-9


@pytest.mark.slow
def test_eval_predictions_ignore_the_symmetrized_training_kwarg():
  # Training batches are (a, b), (b, a) rows encoded once (`symmetrized`); evaluation pairs are
  # arbitrary, and predicting them with the training kwargs gives every odd row the reverse of
  # the pair before it (train.py once logged such EPEs).
  import jax
  from ufm_jax.models import variants
  model = variants.build_model("tiny")
  params = trainer.random_params(model, seed=0)
  rng = np.random.default_rng(0)
  batch = {k: rng.integers(0, 256, (4, 28, 28, 3), dtype=np.uint8) for k in ("image0", "image1")}
  want = model.apply({"params": params}, batch["image0"], batch["image1"])["flow"]
  got = jax.jit(trainer.make_predict(model, {"symmetrized": True}))({"params": params}, batch)["flow"]
  np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
