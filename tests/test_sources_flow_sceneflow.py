"""Scene-flow covisibility rule (supplementary, "Optical (Scene) Flow") on hand-built scenes."""

import numpy as np
import pytest

from ufm_jax.geometry import sceneflow

F = sceneflow.SCENEFLOW_FOCAL  # depth = F * 1.0 / disparity


def test_table_s1_thresholds():
  assert sceneflow.SCENEFLOW_THRESHOLDS == {"flyingthings": (0.01, 0.001), "monkaa": (0.01, 0.001)}


def test_fov_mask_half_pixel_border():
  flow = np.zeros((1, 4, 2), np.float32)
  flow[0, 0, 0] = -0.5   # lands at -0.5: inside
  flow[0, 1, 0] = -1.6   # lands at -0.6: outside
  flow[0, 2, 0] = 1.49   # lands at 3.49: inside
  flow[0, 3, 0] = 0.5    # lands at 3.5 = W - 0.5: outside
  np.testing.assert_array_equal(sceneflow.fov_mask(flow), [[True, False, True, False]])
  flow[0, 0, 1] = np.nan
  assert not sceneflow.fov_mask(flow)[0, 0]


def test_moving_square_occludes_background():
  # Background plane z=10 is static; a square at z=2 (cols 2..4 of row band) moves 3 px right.
  h, w = 6, 12
  disp0 = np.full((h, w), F / 10.0)
  disp0[1:5, 2:5] = F / 2.0
  disp1 = np.full((h, w), F / 10.0)
  disp1[1:5, 5:8] = F / 2.0
  flow = np.zeros((h, w, 2), np.float32)
  flow[1:5, 2:5, 0] = 3.0
  out = sceneflow.sceneflow_covisibility(flow, disp0, np.zeros((h, w)), disp1, 0.01, 0.001)
  expected = np.ones((h, w), bool)
  expected[1:5, 5:8] = False  # background hidden by the square in frame 2
  np.testing.assert_array_equal(out["covisibility"], expected)
  assert out["covis_valid"].all() and out["fov_mask"].all() and out["valid"].all()
  np.testing.assert_allclose(out["depth0"][2, 3], 2.0, rtol=1e-6)


def test_disparity_change_is_used():
  # A square approaching the camera from z=2 to z=1.6 without moving in the image.
  h, w = 5, 7
  disp0 = np.full((h, w), F / 10.0)
  disp0[1:4, 2:5] = F / 2.0
  disp1 = disp0.copy()
  disp1[1:4, 2:5] = F / 1.6
  change = np.zeros((h, w))
  change[1:4, 2:5] = F / 1.6 - F / 2.0
  flow = np.zeros((h, w, 2), np.float32)
  with_change = sceneflow.sceneflow_covisibility(flow, disp0, change, disp1, 0.01, 0.001)
  assert with_change["covisibility"].all()
  without = sceneflow.sceneflow_covisibility(flow, disp0, np.zeros((h, w)), disp1, 0.01, 0.001)
  assert not without["covisibility"][1:4, 2:5].any() and without["covisibility"][0].all()


@pytest.mark.parametrize("delta,covisible", [(0.0149, True), (0.0151, False), (-0.0149, True),
                                             (-0.0151, False)])
def test_threshold_is_absolute_plus_relative(delta, covisible):
  # Centre pixel of a 5x5 image: the ray norm is 1, so range = z. Expected range r = 5, the
  # threshold is 0.01 + 0.001 * 5 = 0.015.
  disp0 = np.full((5, 5), F / 5.0)
  disp1 = np.full((5, 5), F / (5.0 + delta))
  out = sceneflow.sceneflow_covisibility(np.zeros((5, 5, 2), np.float32), disp0, np.zeros((5, 5)),
                                         disp1, 0.01, 0.001)
  assert out["covisibility"][2, 2] == covisible
  np.testing.assert_allclose(out["error"][2, 2], abs(delta), rtol=1e-4)


def test_ranges_not_z_off_axis():
  # Fronto-parallel plane, 1 px lateral flow, tiny focal so the ray norm varies strongly: expected
  # and observed distances must both be ranges along the target ray (mixing range and z-depth
  # would flag every pixel as occluded).
  h, w = 3, 9
  K = np.array([[2.0, 0, 4.0], [0, 2.0, 1.0], [0, 0, 1]])  # tiny focal: strong ray-norm variation
  disp = np.full((h, w), 2.0 / 4.0)  # z = 4 with f*B = 2
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = 1.0
  out = sceneflow.sceneflow_covisibility(flow, disp, np.zeros((h, w)), disp, 0.01, 0.001, K=K)
  expected = np.ones((h, w), bool)
  expected[:, -1] = False  # leaves the view
  np.testing.assert_array_equal(out["covisibility"], expected)
  np.testing.assert_array_equal(out["fov_mask"], expected)


def test_fractional_target_uses_bilinear_depth():
  # Target depth is a horizontal ramp z1(u) = 4 + 0.1 u; the point lands at u + 0.5 with depth
  # exactly the ramp value there: bilinear interpolation matches, nearest would be off by 0.05.
  h, w = 3, 7
  K = np.array([[1e6, 0, 3.0], [0, 1e6, 1.0], [0, 0, 1]])  # huge focal: ray norm == 1
  z1 = 4 + 0.1 * np.arange(w)[None, :].repeat(h, 0)
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = 0.5
  z_moved = 4 + 0.1 * (np.arange(w) + 0.5)[None, :].repeat(h, 0)
  fb = K[0, 0]
  out = sceneflow.sceneflow_covisibility(flow, fb / z_moved, np.zeros((h, w)), fb / z1, 0.01, 0.0,
                                         K=K)
  assert out["covisibility"][:, :-1].all()
  np.testing.assert_allclose(out["error"][:, :-1], 0.0, atol=1e-6)


def test_supervision_mask():
  h, w = 4, 6
  disp0 = np.full((h, w), F / 10.0)
  disp1 = np.full((h, w), F / 10.0)
  disp0[0, 0] = 0.0            # no source depth: not supervised
  disp1[2, 3] = 0.0            # target depth missing where (2, 3) lands: not supervised
  flow = np.zeros((h, w, 2), np.float32)
  flow[3, 5, 0] = 2.0          # leaves the view with valid source depth: supervised, not covisible
  out = sceneflow.sceneflow_covisibility(flow, disp0, np.zeros((h, w)), disp1, 0.01, 0.001)
  expected_valid = np.ones((h, w), bool)
  expected_valid[0, 0] = expected_valid[2, 3] = False
  np.testing.assert_array_equal(out["covis_valid"], expected_valid)
  assert not out["covisibility"][3, 5] and not out["covisibility"][2, 3]
  assert not out["covisibility"][0, 0] and out["covisibility"][1, 1]


def test_shape_errors():
  with pytest.raises(ValueError, match="disparity1 has shape"):
    sceneflow.sceneflow_covisibility(np.zeros((2, 2, 2)), np.ones((2, 2)), np.zeros((2, 2)),
                                     np.ones((3, 2)), 0.01, 0.001)


def test_invalid_target_neighbour_falls_back_to_nearest():
  # The point lands at u = 2.25 next to an invalid target pixel (u = 3): blending the invalid
  # value in would break the match; the nearest valid sample (u = 2) carries the right depth.
  h, w = 1, 6
  K = np.array([[1e6, 0, 2.5], [0, 1e6, 0.0], [0, 0, 1]])
  fb = K[0, 0]
  disp0 = np.full((h, w), fb / 4.0)
  disp1 = np.full((h, w), fb / 4.0)
  disp1[0, 3] = 0.0
  flow = np.zeros((h, w, 2), np.float32)
  flow[0, 2, 0] = 0.25
  out = sceneflow.sceneflow_covisibility(flow, disp0, np.zeros((h, w)), disp1, 0.01, 0.0, K=K)
  assert out["covisibility"][0, 2] and out["covis_valid"][0, 2]
  assert not out["covisibility"][0, 3] and not out["covis_valid"][0, 3]


# The official preprocess's rule (official_sceneflow_covisibility), params (abs, temp, rel).
OFFICIAL = (0.01, 0.01, 0.001)


@pytest.mark.parametrize("delta,covisible", [(0.0218, True), (0.0220, False), (-0.0218, True),
                                             (-0.0220, False)])
def test_official_threshold_has_the_temperature_term(delta, covisible):
  # z = 5: 0.01 + 0.001 * 5 - ln(0.5) * 0.01 = 0.021931 (the paper's rule stops at 0.015).
  disp0 = np.full((5, 5), F / 5.0)
  disp1 = np.full((5, 5), F / (5.0 + delta))
  out = sceneflow.official_sceneflow_covisibility(np.zeros((5, 5, 2), np.float32), disp0,
                                                  np.zeros((5, 5)), disp1, OFFICIAL)
  assert out["covisibility"][2, 2] == covisible
  np.testing.assert_allclose(out["error"][2, 2], abs(delta), rtol=1e-3)


def test_official_compares_z_not_range_and_has_no_half_pixel_margin():
  # Off-axis pixels of a fronto-parallel plane: equal z-depths match whatever the ray norm.
  h, w = 3, 9
  K = np.array([[2.0, 0, 4.0], [0, 2.0, 1.0], [0, 0, 1]])
  disp = np.full((h, w), 2.0 / 4.0)
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = 0.5          # column 8 lands at 8.5
  out = sceneflow.official_sceneflow_covisibility(flow, disp, np.zeros((h, w)), disp, OFFICIAL, K=K)
  # in view iff 0 <= u < W: column 8 (u = 8.5 < 9) is in view, but its bilinear right tap is the
  # zero padding: sampled z = 2 instead of 4, occluded.
  np.testing.assert_array_equal(out["fov_mask"], np.ones((h, w), bool))
  expected = np.ones((h, w), bool)
  expected[:, -1] = False
  np.testing.assert_array_equal(out["covisibility"], expected)
  flow[..., 0] = -0.25        # column 0 lands at -0.25: out of view (the paper's rule keeps it)
  out = sceneflow.official_sceneflow_covisibility(flow, disp, np.zeros((h, w)), disp, OFFICIAL, K=K)
  assert not out["fov_mask"][:, 0].any() and out["fov_mask"][:, 1:].all()
  assert out["covis_valid"][:, 0].all()   # out of view with valid depth: supervised negative


def test_official_target_holes_pull_the_bilinear_sample_to_zero():
  # A point landing a quarter pixel from a hole (depth 0) is occluded: the zero is blended in.
  h, w = 1, 6
  K = np.array([[1e6, 0, 2.5], [0, 1e6, 0.0], [0, 0, 1]])
  fb = K[0, 0]
  disp0 = np.full((h, w), fb / 4.0)
  disp1 = np.full((h, w), fb / 4.0)
  disp1[0, 3] = 0.0
  flow = np.zeros((h, w, 2), np.float32)
  flow[0, 2, 0] = 0.25
  out = sceneflow.official_sceneflow_covisibility(flow, disp0, np.zeros((h, w)), disp1, OFFICIAL,
                                                  K=K)
  assert not out["covisibility"][0, 2] and out["covis_valid"][0, 2]   # nearest target valid
  assert not out["covisibility"][0, 3] and not out["covis_valid"][0, 3]
  np.testing.assert_allclose(out["error"][0, 2], 1.0, rtol=1e-5)      # 0.75 * 4 vs 4
