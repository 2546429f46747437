"""Dense wide-baseline benchmarks (ETH3D, DTU, TA-WB, and the embedded synthetic data).

The paper's Table 2 "covisible pixels" rows: AEPE and 1/2/5 px outlier rates over covisible pixels
(covisibility & flow_valid & covis_valid of the depth-derived GT), pooled over the pixels of all
pairs. `epe_all` adds the EPE over every pixel with valid GT flow (depth-valid, reprojected),
covisible or not, pooled likewise. With `baselines`, `epe_zero` (the EPE that predicting no
motion gets on the `epe` pixels: the bar a model that matches must beat) and `covis_acc` (pixels
with covis_valid whose thresholded covisibility >= 0.5 is right) are added.
"""

from __future__ import annotations

import numpy as np

from ufm_jax import metrics


class DenseMetrics:
  def __init__(self, thresholds=(1, 2, 5), baselines: bool = False):
    self.thresholds = tuple(thresholds)
    self.baselines = baselines
    self.pooled = metrics.Pooled()

  def __call__(self, sample: dict, pred: dict) -> None:
    valid = np.asarray(sample["flow_valid"], bool)
    covis_gt = np.asarray(sample["covisibility"], bool)
    covis_valid = np.asarray(sample["covis_valid"], bool)
    covis = valid & covis_gt & covis_valid
    epe = metrics.endpoint_error(pred["flow"], sample["flow"])
    metrics.add_flow_errors(self.pooled, epe, covis, thresholds=self.thresholds)
    self.pooled.add("epe_all", epe, valid)
    if self.baselines:
      self.pooled.add("epe_zero", np.linalg.norm(np.asarray(sample["flow"], np.float64), axis=-1),
                      covis)
      right = (np.asarray(pred["covisibility"]) >= 0.5) == covis_gt
      self.pooled.add("covis_acc", right, covis_valid)

  def result(self) -> dict[str, float]:
    return self.pooled.result()
