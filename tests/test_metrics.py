"""Metric definitions on hand-computed cases."""

import math

import cv2
import numpy as np
import pytest

from ufm_jax.evaluators import metrics
from ufm_jax.testing import wide_trees


def _gt(h=6, w=8, seed=0):
  return np.random.default_rng(seed).normal(0, 5, (h, w, 2)).astype(np.float32)


def test_perfect_prediction_is_zero():
  gt = _gt()
  epe = metrics.endpoint_error(gt, gt)
  assert epe.max() == 0
  for n in (0.5, 1, 3):
    assert metrics.outlier_rate(epe, n) == 0
  assert not metrics.fl_outliers(epe, gt).any()


def test_constant_one_pixel_offset():
  gt = _gt()
  pred = gt.astype(np.float64) + [1.0, 0.0]
  epe = metrics.endpoint_error(pred, gt)
  np.testing.assert_allclose(epe, 1.0, atol=1e-6)
  acc = metrics.Pooled()
  metrics.add_flow_errors(acc, epe, None, thresholds=(0.5, 1, 3))
  res = acc.result()
  assert abs(res["epe"] - 1) < 1e-6
  assert res["px0.5"] == 100.0   # 1 > 0.5
  assert res["px1"] == 0.0       # strict: an error of exactly 1 px is not a 1-px outlier
  assert res["px3"] == 0.0
  assert metrics.outlier_rate(epe, 0.999) == 100.0


def test_fl_all_needs_both_conditions():
  gt = np.zeros((1, 3, 2))
  gt[0, 0] = (50, 0)    # error 5 > 3 and 5/50 = 10% > 5%  -> outlier
  gt[0, 1] = (200, 0)   # error 5 > 3 but 5/200 = 2.5%     -> not
  gt[0, 2] = (20, 0)    # error 2 < 3 (10%)                -> not
  pred = gt.copy()
  pred[0, :2, 1] += 5     # (0, 5) offset: error exactly 5
  pred[0, 2, 0] += 2
  epe = metrics.endpoint_error(pred, gt)
  np.testing.assert_array_equal(metrics.fl_outliers(epe, gt)[0], [True, False, False])


def test_pooled_vs_per_image():
  pooled, per_image = metrics.Pooled(), metrics.PerImage()
  for values in (np.array([1.0, 1.0, 1.0]), np.array([4.0])):
    pooled.add("epe", values)
    per_image.add("epe", values)
  assert pooled.mean("epe") == pytest.approx(7 / 4)
  assert per_image.mean("epe") == pytest.approx((1 + 4) / 2)
  pooled.add("epe", np.array([100.0]), np.array([False]))  # masked out entirely
  assert pooled.mean("epe") == pytest.approx(7 / 4)


def test_speed_and_matched_masks():
  gt = np.zeros((2, 4, 2))
  gt[0, :, 0] = [9.99, 10, 40, 40.01]
  masks = metrics.speed_masks(gt)
  np.testing.assert_array_equal(masks["s0-10"][0], [True, False, False, False])
  np.testing.assert_array_equal(masks["s10-40"][0], [False, True, True, False])
  np.testing.assert_array_equal(masks["s40+"][0], [False, False, False, True])
  flow = np.zeros((2, 4, 2))
  flow[0, 0] = (3, 0)    # lands on x=3 (= W-1): inside
  flow[0, 1] = (3, 0)    # lands on x=4: outside
  occ = np.zeros((2, 4), bool)
  occ[1, 2] = True
  m = metrics.matched_mask(flow, occ)
  assert m[0, 0] and not m[0, 1] and not m[1, 2] and m[1, 3]


def test_boundary_distance_bins():
  occ = np.zeros((5, 200), bool)
  occ[:, :100] = True             # boundary pixels at columns 99 and 100
  d = metrics.boundary_distance_masks(occ)
  assert d["d0-10"][0, 99] and d["d0-10"][0, 110] and not d["d0-10"][0, 111]
  assert d["d10-60"][0, 111] and d["d10-60"][0, 160] and d["d60-140"][0, 161]
  assert metrics.boundary_distance_masks(np.zeros((4, 4), bool)) is None


def test_pose_auc_hand_computed():
  # errors 1 and 3: curve (0,0) (1,.5) (3,1) then flat to 5: area .25 + 1.5 + 2 = 3.75 -> 0.75;
  # cut at 2: (0,0) (1,.5) (2,.5): area .25 + .5 = .75 -> 0.375; nothing below 0.5 -> 0.
  auc = metrics.pose_auc([3.0, 1.0], thresholds=(0.5, 2, 5))
  assert auc[5] == pytest.approx(0.75)
  assert auc[2] == pytest.approx(0.375)
  assert auc[0.5] == pytest.approx(0.0)
  assert metrics.pose_auc([0.0] * 4, (5,))[5] == pytest.approx(1.0)
  assert metrics.pose_auc([90.0, 90.0], (5, 10))[10] == 0.0


def _rot(axis, deg):
  v = np.zeros(3)
  v[axis] = math.radians(deg)
  return cv2.Rodrigues(v)[0]


def test_pose_errors():
  assert metrics.rotation_error_deg(_rot(2, 30), np.eye(3)) == pytest.approx(30, abs=1e-6)
  assert metrics.rotation_error_deg(_rot(0, 170), np.eye(3)) == pytest.approx(170, abs=1e-6)
  assert metrics.translation_error_deg([1, 0, 0], [-2, 0, 0]) == pytest.approx(0, abs=1e-6)
  assert metrics.translation_error_deg([1, 0, 0], [0, 3, 0]) == pytest.approx(90, abs=1e-6)
  assert metrics.translation_error_deg([1, 1, 0], [1, 0, 0]) == pytest.approx(45, abs=1e-6)
  assert metrics.pose_error(_rot(1, 4), [1, 1, 0], np.eye(3), [1, 0, 0]) == pytest.approx(45)
  c2w0, c2w1 = np.eye(4), np.eye(4)
  c2w1[:3, :3], c2w1[:3, 3] = _rot(1, 10), [1, 0, 0]
  R, t = metrics.relative_pose(c2w0, c2w1)
  np.testing.assert_allclose(R, _rot(1, 10).T, atol=1e-12)   # x1 = R1^T (x0 - c1)
  np.testing.assert_allclose(t, -_rot(1, 10).T @ [1, 0, 0], atol=1e-12)


def test_pose_from_exact_dense_flow():
  flow, K, R, t = wide_trees.two_view_flow()
  covis = np.ones(flow.shape[:2])
  rng = np.random.default_rng(0)
  est = metrics.pose_from_flow(flow, covis, K, K, rng, num=500)
  assert est is not None
  R_est, t_est, n_inl = est
  assert metrics.pose_error(R_est, t_est, R, t) < 0.1
  assert n_inl > 400
  # covisibility weighting: matches only from covisible pixels
  covis[:, : flow.shape[1] // 2] = 0
  k0, _ = metrics.sample_matches(flow, covis, 200, rng)
  assert (k0[:, 0] >= flow.shape[1] // 2).all() and len(k0) == 200


def test_pose_estimation_failure_cases():
  assert metrics.estimate_pose(np.zeros((3, 2)), np.zeros((3, 2)), np.eye(3), np.eye(3)) is None
  flow = np.zeros((8, 8, 2))
  assert metrics.pose_from_flow(flow, np.zeros((8, 8)), np.eye(3), np.eye(3),
                                np.random.default_rng(0)) is None
