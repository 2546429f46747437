"""Optical-flow benchmarks (Sintel, KITTI-2015): the paper's Table 3 and supplementary S2/S3.

Pooling, stated once:
  * Sintel: every metric is pooled over pixels of all pairs (RAFT/unimatch; all Sintel frames have
    the same size, so this equals the mean of per-image means). `epe_all` and the px outlier
    rates use every pixel with finite GT (no occlusion/invalid mask, the standard "Sintel train"
    protocol); `epe_covis` only covisible pixels (not occluded, landing inside image1).
    Breakdowns: `epe_matched`/`epe_unmatched` (meta["matched"], unimatch's approximation of
    the official split), `epe_s0-10`/`epe_s10-40`/`epe_s40+` (GT speed s < 10, 10 <= s <= 40,
    s > 40), `epe_d0-10`/`epe_d10-60`/`epe_d60-140` (distance to an occlusion boundary, an
    approximation; see ufm_jax.evaluators.metrics.boundary_distance_masks).
  * KITTI: `epe_all` (valid GT of flow_occ) and `epe_covis` (covisible valid pixels) are means of
    per-image means (RAFT/SEA-RAFT); `fl_all` = 100 * (EPE > 3 and EPE/|gt| > 5%) pooled over all
    valid pixels of all images (KITTI devkit, RAFT); `fl_bg`/`fl_fg` likewise over background /
    foreground (meta["foreground"], from obj_map) when the source provides it.
  * A model that predicts a flow covariance adds its calibration over the `epe_covis` pixels, the
    ones UFM is trained on (ufm_jax.evaluators.metrics.add_calibration: nll, coverage_{1,2,3}sigma,
    ause / ause_random per image and ause_pooled / ause_pooled_random pooled over pixels),
    on both kinds.
"""

from __future__ import annotations

import numpy as np

from ufm_jax.evaluators import metrics


class FlowMetrics:
  """Accumulates one split of a flow benchmark; `result()` gives the flat metric dict."""

  def __init__(self, kind: str = "sintel", thresholds=(1, 3, 5)):
    if kind not in ("sintel", "kitti"):
      raise ValueError(f"FlowMetrics kind must be 'sintel' or 'kitti', got {kind!r}")
    self.kind, self.thresholds = kind, tuple(thresholds)
    self.pooled, self.per_image = metrics.Pooled(), metrics.PerImage()
    self.sparsification = metrics.Sparsification()

  def __call__(self, sample: dict, pred: dict) -> None:
    gt = np.asarray(sample["flow"], np.float32)
    valid = np.asarray(sample["flow_valid"], bool)
    covis = np.asarray(sample["covisibility"], bool) & valid
    epe = metrics.endpoint_error(pred["flow"], gt)
    meta = sample.get("meta", {}) or {}
    if pred.get("flow_covariance") is not None:
      metrics.add_calibration(self.pooled, self.sparsification, pred["flow"], gt,
                              pred["flow_covariance"], covis)
    if self.kind == "kitti":
      self.per_image.add("epe_all", epe, valid)
      self.per_image.add("epe_covis", epe, covis)
      fl = 100.0 * metrics.fl_outliers(epe, gt)
      self.pooled.add("fl_all", fl, valid)
      fg = meta.get("foreground")
      if fg is not None:
        fg = np.asarray(fg, bool)
        self.pooled.add("fl_fg", fl, valid & fg)
        self.pooled.add("fl_bg", fl, valid & ~fg)
      return
    metrics.add_flow_errors(self.pooled, epe, valid, prefix="", thresholds=self.thresholds)
    self.pooled.add("epe_all", epe, valid)
    self.pooled.add("epe_covis", epe, covis)
    matched = meta.get("matched")
    occlusion = meta.get("occlusion")
    if matched is None and occlusion is not None:
      matched = metrics.matched_mask(gt, occlusion)
    if matched is not None:
      matched = np.asarray(matched, bool)
      self.pooled.add("epe_matched", epe, valid & matched)
      self.pooled.add("epe_unmatched", epe, valid & ~matched)
    for name, m in metrics.speed_masks(gt).items():
      self.pooled.add(f"epe_{name}", epe, valid & m)
    if occlusion is not None:
      dist = metrics.boundary_distance_masks(occlusion)
      for name, m in (dist or {}).items():
        self.pooled.add(f"epe_{name}", epe, valid & m)

  def result(self) -> dict[str, float]:
    out = self.pooled.result()
    out.pop("epe", None)  # same as epe_all here
    out.update(self.per_image.result())
    out.update(self.sparsification.result())
    return out
