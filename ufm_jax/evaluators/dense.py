"""Dense wide-baseline benchmarks (ETH3D, DTU, TA-WB, and the embedded synthetic data).

The paper's Table 2 "covisible pixels" rows: AEPE and 1/2/5 px outlier rates over covisible pixels
(covisibility & flow_valid & covis_valid of the depth-derived GT), pooled over the pixels of all
pairs. `epe_all` adds the EPE over every pixel with valid GT flow (depth-valid, reprojected),
covisible or not, pooled likewise.
"""

from __future__ import annotations

import numpy as np

from ufm_jax import metrics


class DenseMetrics:
  def __init__(self, thresholds=(1, 2, 5)):
    self.thresholds = tuple(thresholds)
    self.pooled = metrics.Pooled()

  def __call__(self, sample: dict, pred: dict) -> None:
    valid = np.asarray(sample["flow_valid"], bool)
    covis = valid & np.asarray(sample["covisibility"], bool) & np.asarray(sample["covis_valid"], bool)
    epe = metrics.endpoint_error(pred["flow"], sample["flow"])
    metrics.add_flow_errors(self.pooled, epe, covis, thresholds=self.thresholds)
    self.pooled.add("epe_all", epe, valid)

  def result(self) -> dict[str, float]:
    return self.pooled.result()
