"""Benchmark metrics. Every formula is stated here; evaluators only decide masks and pooling.

Conventions (the benchmark protocols that use them: docs/benchmarks.md):
  * EPE per pixel: e = sqrt((u - u_gt)^2 + (v - v_gt)^2), in pixels at GT resolution.
  * N-px outlier rate (the paper's "1px/2px/3px/5px" columns): 100 * mean(e > N), a STRICT
    inequality (a pixel with error exactly N is not an outlier), in percent.
  * KITTI Fl-all: a pixel is an outlier iff e > 3 AND e / |gt| > 0.05 (both strict);
    Fl = 100 * outliers / valid pixels.
  * Pooling: `Pooled` accumulates sums and counts over pixels of ALL images ("per-pixel pooling",
    RAFT/unimatch on Sintel, KITTI Fl-all, and our dense wide-baseline benches). `PerImage` takes
    the mean of per-image means (RAFT/SEA-RAFT KITTI EPE). Each evaluator states which it uses.
  * Pose: error = max(angle of the rotation error, angle between translation directions with the
    sign ambiguity removed), degrees; AUC@T integrates recall(error) from 0 to T (SuperGlue/LoFTR).
  * Calibration of a predicted flow covariance Sigma (models with a flow_cov head; formulas at
    `add_calibration`): `nll` and `nll_laplace` (nats per pixel), `coverage_{1,2,3}sigma` (percent
    of pixels whose Mahalanobis distance is within 1, 2, 3), `ause` / `ause_random` per image
    (Ilg et al. 2018's protocol) and `ause_pooled` / `ause_pooled_random` over the pooled pixels
    (px, `Sparsification`).
"""

from __future__ import annotations

import collections

import cv2
import numpy as np

# ----------------------------------------------------------------------------------------------
# Dense flow
# ----------------------------------------------------------------------------------------------


def endpoint_error(flow: np.ndarray, flow_gt: np.ndarray) -> np.ndarray:
  """Per-pixel EPE [..., H, W] = ||flow - flow_gt||_2 (float64 for exact accumulation)."""
  flow, flow_gt = np.asarray(flow, np.float64), np.asarray(flow_gt, np.float64)
  if flow.shape != flow_gt.shape or flow.shape[-1] != 2:
    raise ValueError(f"endpoint_error: prediction {flow.shape} and GT {flow_gt.shape} must both be [..., H, W, 2]")
  return np.sqrt(((flow - flow_gt) ** 2).sum(-1))


def outlier_rate(epe: np.ndarray, threshold: float, mask: np.ndarray | None = None) -> float:
  """100 * mean(epe > threshold) over `mask` (strict >), percent; NaN on an empty mask."""
  e = np.asarray(epe)[np.asarray(mask, bool)] if mask is not None else np.asarray(epe).ravel()
  return float(100.0 * np.mean(e > threshold)) if e.size else float("nan")


def fl_outliers(epe: np.ndarray, flow_gt: np.ndarray) -> np.ndarray:
  """KITTI outlier map: (epe > 3 px) AND (epe / |flow_gt| > 0.05)."""
  mag = np.sqrt((np.asarray(flow_gt, np.float64) ** 2).sum(-1))
  with np.errstate(divide="ignore", invalid="ignore"):
    rel = np.where(mag > 0, epe / mag, np.inf)
  return (epe > 3.0) & (rel > 0.05)


class Pooled:
  """Per-pixel pooling: sum and count per named quantity over every image added."""

  def __init__(self):
    self.sum = collections.defaultdict(float)
    self.count = collections.defaultdict(int)

  def add(self, name: str, values: np.ndarray, mask: np.ndarray | None = None) -> None:
    v = np.asarray(values, np.float64)
    v = v[np.asarray(mask, bool)] if mask is not None else v.ravel()
    self.sum[name] += float(v.sum())
    self.count[name] += int(v.size)

  def mean(self, name: str) -> float:
    return self.sum[name] / self.count[name] if self.count[name] else float("nan")

  def result(self, scale: dict[str, float] | None = None) -> dict[str, float]:
    scale = scale or {}
    return {k: self.mean(k) * scale.get(k, 1.0) for k in self.sum}


class PerImage:
  """Mean over images of per-image means (images with an empty mask are skipped)."""

  def __init__(self):
    self.values = collections.defaultdict(list)

  def add(self, name: str, values: np.ndarray, mask: np.ndarray | None = None) -> None:
    v = np.asarray(values, np.float64)
    v = v[np.asarray(mask, bool)] if mask is not None else v.ravel()
    if v.size:
      self.values[name].append(float(v.mean()))

  def mean(self, name: str) -> float:
    return float(np.mean(self.values[name])) if self.values[name] else float("nan")

  def result(self, scale: dict[str, float] | None = None) -> dict[str, float]:
    scale = scale or {}
    return {k: self.mean(k) * scale.get(k, 1.0) for k in self.values}


def add_flow_errors(acc, epe: np.ndarray, mask: np.ndarray | None, prefix: str = "",
                    thresholds=(1, 3, 5)) -> None:
  """Adds `<prefix>epe` and `<prefix>px<N>` (outlier indicators e > N, x100 = percent) to `acc`."""
  acc.add(f"{prefix}epe", epe, mask)
  for n in thresholds:
    acc.add(f"{prefix}px{n:g}", 100.0 * (np.asarray(epe) > n), mask)


# ---------------------------------------------------------------------------------------------
# Calibration of a predicted flow covariance
# ---------------------------------------------------------------------------------------------
COVERAGE_SIGMAS = (1, 2, 3)


def calibration_errors(flow, flow_gt, cov):
  """(d^2, per-pixel NLL, per-pixel Laplace NLL, uncertainty) [H, W] of a prediction with
  covariance `cov` [H, W, 3] ((var_x, var_y, cov_xy), px^2; ufm_jax.models.covariance), float64:

    r = flow - flow_gt,  d^2 = r^T Sigma^-1 r (the squared Mahalanobis distance),
    nll = 0.5 d^2 + 0.5 log|Sigma| + log(2 pi)  (the 2D Gaussian's negative log-likelihood, nats),
    nll_laplace = sqrt(3) d + 0.5 log|Sigma| + log(2 pi / 3)  (the elliptical Laplace's with the
                  same covariance, covariance.laplace_nll_from: lower than `nll` where the
                  residuals have heavier tails than a Gaussian's),
    uncertainty = trace(Sigma) = var_x + var_y = E[|r|^2] under the prediction: the expected
                  squared EPE, so ordering by it orders by the error the covariance predicts
                  (the order of `Sparsification`; sigma_max^2 or |Sigma| would rank a thin
                  ellipse's pixel by one axis or by its area instead).
  """
  from ufm_jax.models import covariance
  cov = np.asarray(cov, np.float64)
  r = np.asarray(flow, np.float64) - np.asarray(flow_gt, np.float64)
  d2 = covariance.mahalanobis_sq(cov, r)
  with np.errstate(divide="ignore", invalid="ignore"):
    log_det = np.log(covariance.determinant(cov))
  nll = 0.5 * d2 + 0.5 * log_det + covariance.LOG_2PI
  nll_laplace = covariance.laplace_nll_from(d2, log_det, constant=True)
  return d2, nll, nll_laplace, cov[..., 0] + cov[..., 1]


def add_calibration(acc: "Pooled", sparsification: "Sparsification", flow, flow_gt, cov,
                    mask) -> None:
  """Adds the calibration of one image over `mask` to `acc` (pooled over pixels) and to
  `sparsification` (per image):

    nll               mean per-pixel NLL (`calibration_errors`)
    nll_laplace       the same under the elliptical Laplace of that covariance
    coverage_<k>sigma 100 * share of pixels with d <= k, k = 1, 2, 3; a calibrated 2D Gaussian
                      gives 100 (1 - e^(-k^2 / 2)) = 39.3, 86.5, 98.9 (d^2 is chi-square with 2
                      degrees of freedom)
  """
  d2, nll, nll_laplace, unc = calibration_errors(flow, flow_gt, cov)
  acc.add("nll", nll, mask)
  acc.add("nll_laplace", nll_laplace, mask)
  for k in COVERAGE_SIGMAS:
    acc.add(f"coverage_{k}sigma", 100.0 * (d2 <= k * k), mask)
  sparsification.add(endpoint_error(flow, flow_gt), unc, mask)


class Sparsification:
  """AUSE, the area under the sparsification error (Ilg et al. 2018, "Uncertainty Estimates and
  Multi-Hypotheses Networks for Optical Flow"):

    curve(f)  = mean EPE of the pixels left after removing the share f of them with the highest
                predicted uncertainty, f = 0, 0.01, ..., 0.99 (floor(f n) pixels removed);
    oracle(f) = the same with the pixels ordered by their true EPE (the best any order can do);
    AUSE      = integral over f of curve - oracle (trapezoid rule), in px; 0 is a perfect order;
    random    = the same for a random order, whose expected curve is flat at the mean EPE: the
                baseline beside it (an uncertainty that ranks errors gets well under it).

  The predicted uncertainty is trace(Sigma), the expected squared EPE (`calibration_errors`).
  Two poolings, both reported:
    ause, ause_random                 the standard protocol (Ilg et al. 2018): each image's own
                                      curves (exact sorts), the areas averaged over images (which
                                      pixels of one pair to trust); the random baseline likewise
                                      per image, then averaged;
    ause_pooled, ause_pooled_random   one curve over every pixel of every image added: the
                                      sparsification of the bench's pooled EPE (which pixels of
                                      the whole bench to trust). Kept as histograms (HIST_BINS log
                                      bins per decade of uncertainty and of EPE; a removal that
                                      ends inside a bin takes that bin's mean EPE), so any bench
                                      fits in memory.
  """

  FRACTIONS = np.arange(100) / 100.0
  HIST_BINS = 256                      # per decade: bins 0.9% wide
  UNC_DECADES = (-8.0, 8.0)            # log10 of the uncertainty (trace, px^2)
  EPE_DECADES = (-6.0, 5.0)            # log10 of the EPE (px)

  def __init__(self):
    self.ause_image, self.ause_image_random = [], []
    n_unc = int((self.UNC_DECADES[1] - self.UNC_DECADES[0]) * self.HIST_BINS)
    n_epe = int((self.EPE_DECADES[1] - self.EPE_DECADES[0]) * self.HIST_BINS)
    self.by_unc = np.zeros((2, n_unc))     # (count, EPE sum) per uncertainty bin
    self.by_epe = np.zeros((2, n_epe))     # (count, EPE sum) per EPE bin

  @classmethod
  def curve(cls, epe: np.ndarray, order_key: np.ndarray) -> np.ndarray:
    """Mean EPE left after removing floor(f n) pixels of largest `order_key`, per fraction."""
    e = np.asarray(epe, np.float64)[np.argsort(-np.asarray(order_key), kind="stable")]
    n = e.size
    removed = np.floor(cls.FRACTIONS * n).astype(np.int64)
    left_sum = e.sum() - np.concatenate([[0.0], np.cumsum(e)])[removed]
    return left_sum / (n - removed)

  @classmethod
  def curve_from_histogram(cls, hist: np.ndarray) -> np.ndarray:
    """`curve` from (count, EPE sum) per bin of the ordering key (ascending bins)."""
    count, total = hist[0][::-1], hist[1][::-1]        # the largest key first
    n, s = count.sum(), total.sum()
    removed = np.floor(cls.FRACTIONS * n)
    c_count, c_sum = np.concatenate([[0], np.cumsum(count)]), np.concatenate([[0], np.cumsum(total)])
    i = np.clip(np.searchsorted(c_count, removed, side="right") - 1, 0, len(count) - 1)
    partial = removed - c_count[i]
    mean_i = np.where(count[i] > 0, total[i] / np.maximum(count[i], 1), 0.0)
    return (s - c_sum[i] - partial * mean_i) / (n - removed)

  def _bin(self, values, decades) -> np.ndarray:
    n = int((decades[1] - decades[0]) * self.HIST_BINS)
    with np.errstate(divide="ignore"):
      x = (np.log10(values) - decades[0]) * self.HIST_BINS
    return np.clip(np.nan_to_num(x, nan=n - 1, neginf=0, posinf=n - 1), 0, n - 1).astype(np.int64)

  def add(self, epe, uncertainty, mask=None) -> None:
    e = np.asarray(epe, np.float64)
    u = np.asarray(uncertainty, np.float64)
    if mask is not None:
      m = np.asarray(mask, bool)
      e, u = e[m], u[m]
    else:
      e, u = e.ravel(), u.ravel()
    if e.size == 0:
      return
    oracle = self.curve(e, e)
    area = lambda c: float(np.trapezoid(c - oracle, self.FRACTIONS))  # noqa: E731
    self.ause_image.append(area(self.curve(e, u)))
    self.ause_image_random.append(area(np.full_like(oracle, e.mean())))
    for hist, key, decades in ((self.by_unc, u, self.UNC_DECADES),
                               (self.by_epe, e, self.EPE_DECADES)):
      idx = self._bin(key, decades)
      hist[0] += np.bincount(idx, minlength=hist.shape[1])
      hist[1] += np.bincount(idx, weights=e, minlength=hist.shape[1])

  def result(self) -> dict[str, float]:
    if not self.ause_image:
      return {}
    oracle = self.curve_from_histogram(self.by_epe)
    mean = self.by_epe[1].sum() / self.by_epe[0].sum()
    area = lambda c: float(np.trapezoid(c - oracle, self.FRACTIONS))  # noqa: E731
    return {"ause": float(np.mean(self.ause_image)),
            "ause_random": float(np.mean(self.ause_image_random)),
            "ause_pooled": area(self.curve_from_histogram(self.by_unc)),
            "ause_pooled_random": area(np.full_like(oracle, mean))}


# ---------------------------------------------------------------------------------------------
# Sintel breakdowns
# ---------------------------------------------------------------------------------------------
def speed_masks(flow_gt: np.ndarray) -> dict[str, np.ndarray]:
  """Speed bins of the GT magnitude s (unimatch): s0-10: s < 10; s10-40: 10 <= s <= 40; s40+: s > 40."""
  s = np.sqrt((np.asarray(flow_gt, np.float64) ** 2).sum(-1))
  return {"s0-10": s < 10, "s10-40": (s >= 10) & (s <= 40), "s40+": s > 40}


def matched_mask(flow_gt: np.ndarray, occlusion: np.ndarray) -> np.ndarray:
  """Sintel "matched" pixels (unimatch's approximation of the official definition).

  matched = not occluded AND x + flow inside [0, W-1] x [0, H-1] AND |u| <= W-1, |v| <= H-1;
  "unmatched" is every other pixel.
  """
  h, w = flow_gt.shape[:2]
  xs, ys = np.meshgrid(np.arange(w), np.arange(h))
  x1, y1 = xs + flow_gt[..., 0], ys + flow_gt[..., 1]
  inside = (x1 >= 0) & (x1 <= w - 1) & (y1 >= 0) & (y1 <= h - 1)
  small = (np.abs(flow_gt[..., 0]) <= w - 1) & (np.abs(flow_gt[..., 1]) <= h - 1)
  return ~np.asarray(occlusion, bool) & inside & small


def boundary_distance_masks(occlusion: np.ndarray) -> dict[str, np.ndarray] | None:
  """d0-10 / d10-60 / d60-140: Euclidean distance to the nearest occlusion boundary in [0, 10],
  (10, 60], (60, 140] px. The boundary is the set of pixels with a 4-neighbour of the other
  occlusion state (an approximation: Sintel's own boundary maps are not public). None when the
  frame has no occlusion boundary.
  """
  occ = np.asarray(occlusion, bool)
  edge = np.zeros_like(occ)
  edge[:, 1:] |= occ[:, 1:] != occ[:, :-1]
  edge[:, :-1] |= occ[:, 1:] != occ[:, :-1]
  edge[1:] |= occ[1:] != occ[:-1]
  edge[:-1] |= occ[1:] != occ[:-1]
  if not edge.any():
    return None
  d = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
  return {"d0-10": d <= 10, "d10-60": (d > 10) & (d <= 60), "d60-140": (d > 60) & (d <= 140)}


# ---------------------------------------------------------------------------------------------
# Relative pose
# ---------------------------------------------------------------------------------------------


def rotation_error_deg(R: np.ndarray, R_gt: np.ndarray) -> float:
  """Angle of R^T R_gt in degrees: arccos(clip((trace - 1) / 2, -1, 1))."""
  c = (np.trace(np.asarray(R).T @ np.asarray(R_gt)) - 1) / 2
  return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_error_deg(t: np.ndarray, t_gt: np.ndarray) -> float:
  """Angle between translation directions in degrees, folded to [0, 90] (E's sign ambiguity)."""
  t, t_gt = np.ravel(t).astype(np.float64), np.ravel(t_gt).astype(np.float64)
  n = np.linalg.norm(t) * np.linalg.norm(t_gt)
  if n == 0:
    return 90.0
  e = float(np.degrees(np.arccos(np.clip(t @ t_gt / n, -1.0, 1.0))))
  return min(e, 180.0 - e)


def pose_error(R, t, R_gt, t_gt) -> float:
  """max(rotation error, translation direction error), degrees."""
  return max(rotation_error_deg(R, R_gt), translation_error_deg(t, t_gt))


def relative_pose(cam2world0: np.ndarray, cam2world1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(R, t) with x_1 = R x_0 + t from camera-to-world poses (OpenCV axes)."""
  T = np.linalg.inv(np.asarray(cam2world1, np.float64)) @ np.asarray(cam2world0, np.float64)
  return T[:3, :3], T[:3, 3]


def estimate_pose(kpts0: np.ndarray, kpts1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
                  threshold_px: float = 0.5, confidence: float = 0.99999, rng=None):
  """Essential-matrix RANSAC on normalised coordinates (RoMa/DKM protocol).

  Keypoints (pixel coordinates, OpenCV centres) are normalised with K^-1; the RANSAC threshold is
  threshold_px / mean(fx0, fy0, fx1, fy1); every stacked solution of findEssentialMat goes through
  recoverPose and the one with most inliers wins. `rng` reshuffles the matches first (the
  protocol repeats RANSAC on shuffled orders). Returns (R, t, n_inliers) or None (< 5 matches or
  no solution).
  """
  kpts0, kpts1 = np.asarray(kpts0, np.float64), np.asarray(kpts1, np.float64)
  if len(kpts0) < 5:
    return None
  if rng is not None:
    perm = rng.permutation(len(kpts0))
    kpts0, kpts1 = kpts0[perm], kpts1[perm]
  K0, K1 = np.asarray(K0, np.float64), np.asarray(K1, np.float64)
  n0 = (kpts0 - K0[[0, 1], [2, 2]]) / K0[[0, 1], [0, 1]]
  n1 = (kpts1 - K1[[0, 1], [2, 2]]) / K1[[0, 1], [0, 1]]
  thr = threshold_px / np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]])
  E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), threshold=thr, prob=confidence, method=cv2.RANSAC)
  if E is None:
    return None
  best = None
  for i in range(0, E.shape[0] - E.shape[0] % 3, 3):
    n, R, t, _ = cv2.recoverPose(E[i:i + 3], n0, n1, np.eye(3), 1e9, mask=mask.copy())[:4]
    if best is None or n > best[2]:
      best = (R, t.ravel(), int(n))
  return best


def _kde_exact(x: np.ndarray, sigma: float) -> np.ndarray:
  """RoMa's `kde`: sum_j exp(-|x_i - x_j|^2 / (2 sigma^2)) over all rows (self included), by
  chunked pairwise distances (O(N^2) time)."""
  x = np.asarray(x, np.float32)
  density = np.zeros(len(x))
  sq = (x * x).sum(1)
  for s in range(0, len(x), 2048):  # 80000^2 distances would not fit at once
    d2 = sq[s:s + 2048, None] + sq[None] - 2 * x[s:s + 2048] @ x.T
    density[s:s + 2048] = np.exp(-np.maximum(d2, 0) / (2 * sigma**2)).sum(1)
  return density


def _bspline3(f: np.ndarray) -> np.ndarray:
  """[..., 4] cubic B-spline weights of the nodes -1, 0, 1, 2 around a point at fraction f."""
  g = 1.0 - f
  return np.stack([g**3, 3 * f**3 - 6 * f**2 + 4, 3 * g**3 - 6 * g**2 + 4, f**3], -1) / 6.0


def _kde_grid(x: np.ndarray, sigma: float, spacing: float = 0.5, chunk: int = 4096) -> np.ndarray:
  """The same sums as `_kde_exact` in O(N 4^D + G D m) time: every point is spread onto a grid of
  spacing sigma * `spacing` with cubic B-spline weights, the grid is blurred by a Gaussian along
  each axis, and each point reads the blurred grid back with the same weights.

  Spreading and reading back each widen the kernel by the B-spline's variance h^2 / 3 per axis,
  so the grid blur uses sigma_b^2 = sigma^2 - 2 h^2 / 3 and is scaled by sigma / sigma_b per axis
  (a unit-mass spline then gives the unit-peak kernel of the exact sum). What is left is the
  splines' position-dependent shape error, of order (h / sigma)^4: at h = sigma / 2 within 0.2% of
  the exact sum for points with density >= 10 on UFM-sized inputs (docs/cpu_inference.md).
  """
  x = np.asarray(x, np.float64)
  n, d = x.shape
  h = sigma * spacing
  u = (x - x.min(0)) / h
  base = np.floor(u).astype(np.int64)          # node base - 1 .. base + 2, shifted by one below
  frac = u - base
  shape = base.max(0) + 4
  strides = np.array([int(np.prod(shape[k + 1:])) for k in range(d)], np.int64)
  taps = np.arange(4)

  def corners(lo, hi):
    """Flat node indices and weights [c, 4^D] of points lo..hi (outer products over the axes)."""
    idx = np.zeros((hi - lo,) + (1,) * d, np.int64)
    wgt = np.ones((hi - lo,) + (1,) * d)
    for k in range(d):
      at = (slice(None),) + tuple(slice(None) if j == k else None for j in range(d))
      idx = idx + ((base[lo:hi, k, None] + taps) * strides[k])[at]
      wgt = wgt * _bspline3(frac[lo:hi, k])[at]
    return idx.reshape(hi - lo, -1), wgt.reshape(hi - lo, -1)

  size = int(np.prod(shape))
  grid = np.zeros(size)
  for lo in range(0, n, chunk):
    idx, wgt = corners(lo, min(n, lo + chunk))
    grid += np.bincount(idx.ravel(), wgt.ravel(), minlength=size)
  grid = grid.reshape(shape)
  var_b = sigma**2 - 2 * h**2 / 3
  for k in range(d):  # each step blurs the leading axis and moves it last: one matmul, no copies
    a = np.arange(shape[k]) * h
    blur = np.exp(-(a[:, None] - a[None]) ** 2 / (2 * var_b)) * (sigma / np.sqrt(var_b))
    grid = np.tensordot(grid, blur, axes=([0], [1]))
  grid = grid.reshape(-1)
  density = np.empty(n)
  for lo in range(0, n, chunk):
    idx, wgt = corners(lo, min(n, lo + chunk))
    density[lo:lo + len(idx)] = (grid[idx] * wgt).sum(1)
  return density


# Below this many candidates the exact pairwise sum is as fast as the grid's fixed cost.
KDE_EXACT_MAX = 4096


def kde_density(x: np.ndarray, sigma: float, method: str = "auto") -> np.ndarray:
  """RoMa's KDE of the match candidates: [N] sums of exp(-|x_i - x_j|^2 / (2 sigma^2)).

  "exact": the pairwise sum, O(N^2) (142 s for N = 80000, the 20000-match request); "grid":
  `_kde_grid`, near-linear in N; "auto": exact up to KDE_EXACT_MAX points, else the grid.
  """
  if method == "auto":
    method = "exact" if len(x) <= KDE_EXACT_MAX else "grid"
  if method == "exact":
    return _kde_exact(x, sigma)
  if method == "grid":
    return _kde_grid(x, sigma)
  raise ValueError(f"kde method {method!r}; expected 'auto', 'exact' or 'grid'")


def sample_matches(flow: np.ndarray, covisibility: np.ndarray, num: int, rng, target_hw=None,
                   certainty_threshold: float = 0.05, balanced: bool = True,
                   kde_sigma: float = 0.1, min_covisibility: float = 0.0,
                   return_index: bool = False, kde: str = "auto", stats: dict | None = None):
  """Draws `num` matches from a dense flow weighted by covisibility (DKM/RoMa `sample`).

  Certainty = covisibility, zeroed where x + flow leaves the target image (size `target_hw`,
  default the source's; RoMa does the same); values above `certainty_threshold` count as 1
  ("threshold_balanced"). Draw min(4 num, N) candidates without replacement proportional to
  certainty; with `balanced`, re-draw min(num, #candidates) of them without replacement
  proportional to 1 / (1 + KDE density) (Gaussian, sigma 0.1 in the [-1, 1]-normalised 4-D match
  space; 1e-7 where density < 10) so that dense clusters do not dominate. The density is
  `kde_density(..., method=kde)`: exact for small draws, near-linear on a grid for large ones.
  Pixels with covisibility below `min_covisibility` are never drawn (ufm_jax.match; the pose
  benchmark keeps 0).
  Returns (kpts0 [n, 2], kpts1 [n, 2]) in pixels (x, y), pixel centres at integers, plus the flat
  source-pixel indices [n] with `return_index`; n = min(num, the eligible pixels), which a dict
  passed as `stats` gets as "eligible" (pixels with certainty > 0) so a caller can say why n < num.
  """
  flow = np.asarray(flow, np.float64)
  h, w = flow.shape[:2]
  h1, w1 = target_hw or (h, w)
  ys, xs = np.mgrid[0:h, 0:w]
  k0 = np.stack([xs, ys], -1).reshape(-1, 2).astype(np.float64)
  k1 = k0 + flow.reshape(-1, 2)
  cert = np.asarray(covisibility, np.float64).reshape(-1)
  inside = (k1[:, 0] >= -0.5) & (k1[:, 0] < w1 - 0.5) & (k1[:, 1] >= -0.5) & (k1[:, 1] < h1 - 0.5)
  keep = inside & np.isfinite(cert) & np.isfinite(k1).all(1) & (cert >= min_covisibility)
  cert = np.where(keep, cert, 0.0)
  cert = np.where(cert > certainty_threshold, 1.0, cert)
  nz = np.flatnonzero(cert > 0)
  if stats is not None:
    stats["eligible"] = int(nz.size)
  if nz.size == 0:
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    return empty + (np.zeros(0, np.int64),) if return_index else empty
  n_cand = min(4 * num if balanced else num, nz.size)
  cand = rng.choice(nz, size=n_cand, replace=False, p=cert[nz] / cert[nz].sum())
  if balanced and n_cand > num:
    x = np.concatenate([(k0[cand] + 0.5) / [w, h] * 2 - 1,
                        (k1[cand] + 0.5) / [w1, h1] * 2 - 1], 1).astype(np.float32)
    density = kde_density(x, kde_sigma, kde)
    q = 1.0 / (density + 1.0)
    q[density < 10] = 1e-7
    cand = rng.choice(cand, size=num, replace=False, p=q / q.sum())
  return (k0[cand], k1[cand], cand) if return_index else (k0[cand], k1[cand])


def pose_auc(errors, thresholds=(5, 10, 20)) -> dict[float, float]:
  """AUC of the recall-vs-error curve up to each threshold, normalised by it (SuperGlue/LoFTR).

  Errors are sorted, recall_i = i / N; the curve starts at (0, 0); for threshold t the curve is
  cut at the last error < t and held flat to t; AUC@t = trapezoid area / t (a value in [0, 1]).
  """
  errors = np.sort(np.asarray(errors, np.float64))
  if errors.size == 0:
    return {t: float("nan") for t in thresholds}
  recall = (np.arange(len(errors)) + 1) / len(errors)
  errors = np.r_[0.0, errors]
  recall = np.r_[0.0, recall]
  out = {}
  for t in thresholds:
    last = np.searchsorted(errors, t)
    e = np.r_[errors[:last], t]
    r = np.r_[recall[:last], recall[last - 1]]
    out[t] = float(np.trapezoid(r, x=e) / t)
  return out


def pose_from_flow(flow, covisibility, K0, K1, rng, num: int = 5000, target_hw=None,
                   threshold_px: float = 0.5, balanced: bool = True):
  """Samples matches from flow + covisibility and estimates (R, t, n_inliers); None on failure."""
  kp0, kp1 = sample_matches(flow, covisibility, num, rng, target_hw=target_hw, balanced=balanced)
  if len(kp0) < 5:
    return None
  return estimate_pose(kp0, kp1, K0, K1, threshold_px=threshold_px, rng=rng)
