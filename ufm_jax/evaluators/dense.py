"""Dense wide-baseline benchmarks (ETH3D, DTU, TA-WB, and the embedded synthetic data).

The paper's Table 2 "covisible pixels" rows: AEPE and 1/2/5 px outlier rates over covisible
pixels, pooled over the pixels of all pairs, plus `epe_occluded` (the branch's "EPE Occluded":
pixels with ground truth that are not covisible) and `epe_all` (every pixel with ground truth).
The masks per protocol:

  metric        official (widebaseline_datasets.py:62-93)   native
  epe, px<N>    flow_valid & covisibility                   flow_valid & covisibility & covis_valid
  epe_occluded  flow_valid & ~covisibility                  flow_valid & target inside image1 &
                                                            ~covisibility & covis_valid
  epe_all       flow_valid                                  flow_valid

Official samples carry the branch's masks (flow_valid = its `valid_mask`: in view of image1 with
valid source depth; covisibility = its `covisible_mask`; the prediction mask is all ones,
solutions/ufm.py:47). The branch's per-instance lists (pairs with > 50 covisible pixels, lines
76-82) feed nothing it reports, so they are not kept. Native samples come from
ufm_jax.geometry: flow_valid is "in front of camera 2", so the target-inside test keeps
out-of-view pixels out of `epe_occluded`, and covis_valid keeps only pixels whose covisibility the
depth can decide.
With `baselines`, `epe_zero` (the EPE that predicting no motion gets on the `epe` pixels: the bar
a model that matches must beat) and `covis_acc` (pixels with covis_valid whose thresholded
covisibility >= 0.5 is right) are added; `covis_acc` only for a model that predicts covisibility
(the refinement recipe's has no uncertainty head: a warning says so once).
A model that predicts a flow covariance adds its calibration over the `epe` pixels
(ufm_jax.evaluators.metrics.add_calibration): nll, coverage_1sigma / 2sigma / 3sigma, ause and ause_random
per image (Ilg et al. 2018), ause_pooled and ause_pooled_random pooled over pixels like `epe`.
"""

from __future__ import annotations

import numpy as np
from absl import logging

from ufm_jax import geometry
from ufm_jax.evaluators import metrics


class DenseMetrics:
  def __init__(self, thresholds=(1, 2, 5), baselines: bool = False, official: bool = False):
    self.thresholds = tuple(thresholds)
    self.baselines = baselines
    self.official = official
    self.pooled = metrics.Pooled()
    self.sparsification = metrics.Sparsification()

  def __call__(self, sample: dict, pred: dict) -> None:
    valid = np.asarray(sample["flow_valid"], bool)
    covis_gt = np.asarray(sample["covisibility"], bool)
    covis_valid = np.asarray(sample["covis_valid"], bool)
    if self.official:
      covis, occluded = valid & covis_gt, valid & ~covis_gt
    else:
      in_view = geometry.fov_mask_from_flow(sample["flow"], np.shape(sample["image1"])[:2])
      covis = valid & covis_gt & covis_valid
      occluded = valid & in_view & ~covis_gt & covis_valid
    epe = metrics.endpoint_error(pred["flow"], sample["flow"])
    metrics.add_flow_errors(self.pooled, epe, covis, thresholds=self.thresholds)
    self.pooled.add("epe_occluded", epe, occluded)
    self.pooled.add("epe_all", epe, valid)
    if pred.get("flow_covariance") is not None:
      metrics.add_calibration(self.pooled, self.sparsification, pred["flow"], sample["flow"],
                              pred["flow_covariance"], covis)
    if self.baselines:
      self.pooled.add("epe_zero", np.linalg.norm(np.asarray(sample["flow"], np.float64), axis=-1),
                      covis)
      if pred.get("covisibility") is None:
        logging.log_first_n(logging.WARNING, "the model predicts no covisibility (no uncertainty "
                            "head): covis_acc is not computed", 1)
        return
      right = (np.asarray(pred["covisibility"]) >= 0.5) == covis_gt
      self.pooled.add("covis_acc", right, covis_valid)

  def result(self) -> dict[str, float]:
    return {**self.pooled.result(), **self.sparsification.result()}
