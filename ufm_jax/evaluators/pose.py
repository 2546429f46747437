"""Relative pose benchmarks (ETH3D, ScanNet-1500, TA-WB): the paper's Table 4.

Per pair: sample 5000 matches once from the predicted flow weighted by the predicted covisibility
(threshold-balanced, KDE-balanced; ufm_jax.evaluators.metrics.sample_matches), then `runs` times (DKM: 5)
on a reshuffled order: essential matrix by RANSAC (0.5 px threshold normalised by the mean focal
length, confidence 0.99999), recoverPose; error = max(rotation angle error, translation direction
error) in degrees, 90 on failure. Every run's error is one entry of the AUC (`auc<T>` in percent, standard
SuperGlue/LoFTR integration); `acc<T>` = percent of entries with error < T.
GT: x1 = R x0 + t from meta cam2world0/cam2world1; intrinsics meta K0/K1 at the images' native
resolution (predictions are mapped back to it by `predict`).
"""

from __future__ import annotations

import numpy as np

from ufm_jax.evaluators import metrics


class NoCovisibilityError(ValueError):
  """A metric that needs the model's covisibility, from a model without an uncertainty head."""


class PoseMetrics:
  def __init__(self, thresholds=(5, 10, 15), runs: int = 5, num_matches: int = 5000, seed: int = 0):
    self.thresholds, self.runs, self.num = tuple(thresholds), runs, num_matches
    self.rng = np.random.default_rng(seed)
    self.errors: list[float] = []

  def __call__(self, sample: dict, pred: dict) -> None:
    meta = sample.get("meta", {}) or {}
    for key in ("K0", "K1", "cam2world0", "cam2world1"):
      if meta.get(key) is None:
        raise ValueError(f"pose benchmark: sample meta lacks {key!r} (dataset "
                         f"{meta.get('dataset', '?')}, scene {meta.get('scene', '?')})")
    if pred.get("covisibility") is None:
      raise NoCovisibilityError("pose benchmark: matches are sampled by predicted covisibility, "
                                "and this model predicts none (no uncertainty head, as the "
                                "refinement training recipe's model)")
    R_gt, t_gt = metrics.relative_pose(meta["cam2world0"], meta["cam2world1"])
    kp0, kp1 = metrics.sample_matches(pred["flow"], pred["covisibility"], self.num, self.rng,
                                      target_hw=sample["image1"].shape[:2])
    for _ in range(self.runs):
      est = metrics.estimate_pose(kp0, kp1, meta["K0"], meta["K1"], rng=self.rng)
      self.errors.append(90.0 if est is None else metrics.pose_error(est[0], est[1], R_gt, t_gt))

  def result(self) -> dict[str, float]:
    auc = metrics.pose_auc(self.errors, self.thresholds)
    out = {f"auc{t:g}": 100.0 * v for t, v in auc.items()}
    err = np.asarray(self.errors)
    out.update({f"acc{t:g}": 100.0 * float(np.mean(err < t)) for t in self.thresholds})
    return out
