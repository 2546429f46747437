"""Analytic scenes with closed-form flow and covisibility for ufm_jax.geometry."""

import numpy as np
import pytest

from ufm_jax import geometry as g

H, W = 40, 56
FX, FY, CX, CY = 50.0, 48.0, 27.5, 19.0
K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
TAU = (0.1, 0.005)


def translation(t):
  T = np.eye(4)
  T[:3, 3] = t
  return T


def grid():
  v, u = np.mgrid[0:H, 0:W].astype(np.float64)
  return u, v


def test_fronto_parallel_plane_translation_gives_constant_flow():
  z, t = 8.0, np.array([0.37, -0.21, 0.0])
  depth = np.full((H, W), z)
  out = g.correspondence_from_depth(depth, K, np.eye(4), depth, K, translation(t), *TAU)
  du, dv = -FX * t[0] / z, -FY * t[1] / z
  u, v = grid()
  inside = (u + du >= -0.5) & (u + du < W - 0.5) & (v + dv >= -0.5) & (v + dv < H - 0.5)
  assert out["flow"].dtype == np.float32
  np.testing.assert_allclose(out["flow"][..., 0], du, atol=1e-4)
  np.testing.assert_allclose(out["flow"][..., 1], dv, atol=1e-4)
  np.testing.assert_array_equal(out["fov_mask"], inside)
  np.testing.assert_array_equal(out["covisibility"], inside)
  assert out["valid"].all() and 0 < inside.sum() < H * W


def rot(axis, angle):
  return g.axis_angle_to_rotation(axis, angle)


def plane_depth(n, d, K_, c2w):
  """z-depth of the world plane n.X = d seen from camera c2w (independent ray intersection)."""
  u, v = grid()
  r = np.stack([(u - K_[0, 2]) / K_[0, 0], (v - K_[1, 2]) / K_[1, 1], np.ones_like(u)], -1)
  dirs = r @ c2w[:3, :3].T  # world direction with camera z-component 1
  o = c2w[:3, 3]
  return (d - n @ o) / (dirs @ n)  # ray o + s * dirs, s = camera z-depth


@pytest.mark.parametrize("t", [np.zeros(3), np.array([0.3, 0.1, -0.2])])
def test_tilted_plane_under_rotation_gives_homography_flow(t):
  n = np.array([0.2, -0.1, 1.0])
  n /= np.linalg.norm(n)
  d = 6.0
  R = rot([0.3, 1.0, 0.2], np.deg2rad(8))
  c2w1 = g.pose_from_rt(R, t)
  depth0 = plane_depth(n, d, K, np.eye(4))
  depth1 = plane_depth(n, d, K, c2w1)
  out = g.correspondence_from_depth(depth0, K, np.eye(4), depth1, K, c2w1, *TAU)
  # X1 = R^T (X0 - t) and n.X0 = d  =>  x1 ~ K R^T (I - t n^T / d) K^-1 x0
  Hmg = K @ R.T @ (np.eye(3) - np.outer(t, n) / d) @ np.linalg.inv(K)
  u, v = grid()
  p = np.stack([u, v, np.ones_like(u)], -1) @ Hmg.T
  tu, tv = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
  np.testing.assert_allclose(out["flow"][..., 0], tu - u, atol=1e-3)
  np.testing.assert_allclose(out["flow"][..., 1], tv - v, atol=1e-3)
  inside = (tu >= -0.5) & (tu < W - 0.5) & (tv >= -0.5) & (tv < H - 0.5)
  np.testing.assert_array_equal(out["fov_mask"], inside)
  np.testing.assert_array_equal(out["covisibility"], inside)
  assert 0 < inside.sum() < H * W


def two_plane_depth(cam_x, x_edge, z_near=5.0, z_far=10.0):
  """Near half-plane (world x < x_edge) at z_near in front of a far plane, camera at (cam_x,0,0)."""
  u, _ = grid()
  x_at_near = cam_x + (u - CX) / FX * z_near
  return np.where(x_at_near < x_edge, z_near, z_far)


@pytest.mark.parametrize("search", [0.0, 0.5])
def test_near_plane_occludes_far_plane(search):
  x_edge, tx = 0.0, -1.0
  depth0, depth1 = two_plane_depth(0.0, x_edge), two_plane_depth(tx, x_edge)
  out = g.correspondence_from_depth(depth0, K, np.eye(4), depth1, K, translation([tx, 0, 0]), *TAU,
                                    subpixel_search=search)
  u, v = grid()
  near = depth0 == 5.0
  du = np.where(near, -FX * tx / 5.0, -FX * tx / 10.0)
  np.testing.assert_allclose(out["flow"][..., 0], du, atol=1e-4)
  np.testing.assert_allclose(out["flow"][..., 1], 0.0, atol=1e-4)
  # Far-plane world x in [2 x_edge, 2 x_edge + |tx|) hides behind the near plane from camera 1.
  x_far = (u - CX) / FX * 10.0
  occluded = ~near & (x_far < 2 * x_edge - tx)
  in_view = (u + du >= -0.5) & (u + du < W - 0.5)
  expected = in_view & ~occluded
  # Bilinear depth mixing is ambiguous within a pixel of a depth edge in image 1: skip those.
  target_x = tx + (u + du - CX) / FX * 5.0  # where the ray to the target pixel crosses z = 5
  edge_px = np.abs(target_x - x_edge) / 5.0 * FX
  sure = edge_px > 1.5 + search
  assert occluded[sure].sum() >= 3 * H  # the test scene really has an occluded band
  np.testing.assert_array_equal(out["covisibility"][sure], expected[sure])
  assert out["fov_mask"][occluded].all()  # occlusion is not a field-of-view matter
  assert g.labels_from_correspondence(out)["covis_valid"].all()  # all depths valid


def box_scene(c0, c1, theta, cam_t, half=1.2, z_box=5.0, z_far=10.0):
  """Camera 0 at the origin, camera 1 translated by cam_t; a thin square slab facing the cameras,
  centre c0 at time 0, centre c1 and rotated by theta about the optical axis at time 1."""
  def render(center, angle, cam_c):
    u, v = grid()
    ray = np.stack([(u - CX) / FX, (v - CY) / FY], -1)
    s = z_box - cam_c[2]
    hit = cam_c[:2] + ray * s - center[:2]
    c, sn = np.cos(-angle), np.sin(-angle)
    local = np.stack([c * hit[..., 0] - sn * hit[..., 1], sn * hit[..., 0] + c * hit[..., 1]], -1)
    on = (np.abs(local) < half).all(-1)
    return np.where(on, s, z_far - cam_c[2]), on, local
  depth0, on0, _ = render(c0, 0.0, np.zeros(3))
  depth1, on1, _ = render(c1, theta, cam_t)
  return depth0, on0, depth1, on1


def test_moving_rigid_box():
  c0, c1 = np.array([-0.5, 0.2, 5.0]), np.array([0.1, 0.0, 5.0])
  theta, cam_t = np.deg2rad(20), np.array([0.33, 0.0, 0.0])
  depth0, on0, depth1, _ = box_scene(c0, c1, theta, cam_t)
  seg = on0.astype(np.int32)  # 0 background (static), 1 the box
  pose0 = {0: np.eye(4), 1: translation(c0)}
  pose1 = {0: np.eye(4), 1: g.pose_from_rt(rot([0, 0, 1], theta), c1)}
  c2w1 = translation(cam_t)
  out = g.correspondence_from_rigid_objects(depth0, K, np.eye(4), seg, pose0, depth1, K, c2w1,
                                            pose1, *TAU)
  u, v = grid()
  # Box: X = c0 + q -> c1 + Rz q, viewed from cam_t at depth 5.
  q = np.stack([(u - CX) / FX * 5.0 - c0[0], (v - CY) / FY * 5.0 - c0[1]], -1)
  c, s = np.cos(theta), np.sin(theta)
  xb = c1[0] + c * q[..., 0] - s * q[..., 1] - cam_t[0]
  yb = c1[1] + s * q[..., 0] + c * q[..., 1] - cam_t[1]
  box_u, box_v = CX + FX * xb / 5.0, CY + FY * yb / 5.0
  bg_u, bg_v = u - FX * cam_t[0] / 10.0, v - FY * cam_t[1] / 10.0
  tu, tv = np.where(on0, box_u, bg_u), np.where(on0, box_v, bg_v)
  np.testing.assert_allclose(out["flow"][..., 0], tu - u, atol=1e-3)
  np.testing.assert_allclose(out["flow"][..., 1], tv - v, atol=1e-3)
  # Background covisible iff the ray from camera 1 to it misses the moved box.
  P = np.stack([(u - CX) / FX * 10.0, (v - CY) / FY * 10.0], -1)
  cross = cam_t[:2] + (P - cam_t[:2]) * 0.5 - c1[:2]  # at z = 5 (half way to z = 10)
  local = np.stack([c * cross[..., 0] + s * cross[..., 1], -s * cross[..., 0] + c * cross[..., 1]], -1)
  hidden = ~on0 & (np.abs(local) < 1.2).all(-1)
  in_view = (tu >= -0.5) & (tu < W - 0.5) & (tv >= -0.5) & (tv < H - 0.5)
  expected = in_view & ~hidden
  edge_px = np.abs(np.abs(local) - 1.2).min(-1) / 5.0 * FX
  # Box pixels land at object coordinates q on the moved box; near its silhouette the bilinear
  # target depth mixes box and background (the paper's accepted 1-px band): skip those too.
  box_edge_px = (1.2 - np.abs(q)).min(-1) / 5.0 * FX
  sure = np.where(on0, box_edge_px > 1.5, edge_px > 1.5)
  assert hidden[sure].sum() > 20
  np.testing.assert_array_equal(out["covisibility"][sure], expected[sure])


def test_rigid_unknown_object_id_is_invalid():
  depth = np.full((H, W), 5.0)
  seg = np.zeros((H, W), np.int32)
  seg[:5] = 7
  out = g.correspondence_from_rigid_objects(depth, K, np.eye(4), seg, {0: np.eye(4)}, depth, K,
                                            np.eye(4), {0: np.eye(4)}, *TAU)
  assert not out["valid"][:5].any() and out["valid"][5:].all()
  assert out["covisibility"][5:].all() and not out["covisibility"][:5].any()


def test_invalid_depths():
  depth0 = np.full((H, W), 8.0)
  depth0[0, 0], depth0[0, 1], depth0[0, 2] = 0.0, np.inf, np.nan
  depth1 = np.full((H, W), 8.0)
  depth1[10:20, 10:20] = 0.0
  depth1[10:20, 30:32] = np.nan
  out = g.correspondence_from_depth(depth0, K, np.eye(4), depth1, K, np.eye(4), *TAU)
  assert not out["valid"][0, :3].any() and out["valid"].sum() == H * W - 3
  assert not out["covisibility"][0, :3].any() and not out["fov_mask"][0, :3].any()
  assert np.isfinite(out["flow"]).all()
  # Target holes: not covisible (no depth to confirm) and not supervised.
  assert not out["covisibility"][11:19, 11:19].any()
  assert not out["covisibility"][11:19, 30:32].any()
  labels = g.labels_from_correspondence(out)
  assert not labels["covis_valid"][10:20, 10:20].any()
  assert labels["covis_valid"][25:, :].all()
  assert not labels["covis_valid"][0, :3].any()


def test_point_behind_target_camera_not_in_fov():
  depth = np.full((H, W), 4.0)
  R = rot([0, 1, 0], np.pi)  # camera 1 looks backwards from 10 m behind the plane
  c2w1 = g.pose_from_rt(R, [0, 0, 20.0])
  out = g.correspondence_from_depth(depth, K, np.eye(4), depth, K, c2w1, *TAU)
  assert out["fov_mask"].all()  # facing the plane from the other side: in view
  c2w1 = g.pose_from_rt(np.eye(3), [0, 0, 10.0])  # now the plane is behind camera 1
  out = g.correspondence_from_depth(depth, K, np.eye(4), depth, K, c2w1, *TAU)
  assert not out["fov_mask"].any() and not out["covisibility"].any()
  assert not out["in_front"].any() and (out["flow"] == 0).all()


def test_relative_threshold_scales_with_distance():
  # Target depth off by a constant 0.2 along z: fails tau_d alone, passes with tau_r at range >= 20.
  for z, expect in ((10.0, False), (40.0, True)):
    d0 = np.full((H, W), z)
    out = g.correspondence_from_depth(d0, K, np.eye(4), d0 + 0.2, K, np.eye(4), 0.1, 0.005)
    assert out["covisibility"][H // 2, W // 2] == expect


def test_converters():
  depth = np.random.default_rng(0).uniform(1, 9, (H, W))
  u, v = grid()
  rng_map = depth * np.sqrt(1 + ((u - CX) / FX) ** 2 + ((v - CY) / FY) ** 2)
  np.testing.assert_allclose(g.z_to_range(depth, K), rng_map)
  np.testing.assert_allclose(g.range_to_z(rng_map, K), depth)
  # w2c -> c2w: the camera centre is -R^T t.
  R, t = rot([1, 2, 3], 0.7), np.array([1.0, -2.0, 0.5])
  c2w = g.world2cam_to_cam2world(g.pose_from_rt(R, t))
  np.testing.assert_allclose(c2w[:3, 3], -R.T @ t)
  np.testing.assert_allclose(c2w @ g.pose_from_rt(R, t), np.eye(4), atol=1e-12)
  # OpenGL camera looking down world -z from the origin: a point at world z=-3 is in front.
  c2w_cv = g.opengl_to_opencv(np.eye(4))
  X_cam = g.transform(g.invert_pose(c2w_cv), np.array([1.0, 2.0, -3.0]))
  np.testing.assert_allclose(X_cam, [1.0, -2.0, 3.0])
  # NED camera (x forward, y right, z down) with identity pose: world x is the optical axis.
  X_cam = g.transform(g.invert_pose(g.ned_to_opencv(np.eye(4))), np.array([5.0, 1.0, 2.0]))
  np.testing.assert_allclose(X_cam, [1.0, 2.0, 5.0])
  # Quaternion (w, x, y, z) of 90 deg about z.
  np.testing.assert_allclose(g.quaternion_to_rotation([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]),
                             [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
  # look_at: optical axis points at the target, image-down is world +y by default.
  T = g.look_at([0, 0, -5.0], [0, 0, 0])
  np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-12)
  uv, z = g.project(g.transform(g.invert_pose(T), np.array([0, 0, 0.0])), K)
  np.testing.assert_allclose(uv, [CX, CY])
  np.testing.assert_allclose(z, 5.0)
  # unproject / project round trip.
  pts = g.unproject(depth, K)
  uv, z = g.project(pts, K)
  np.testing.assert_allclose(uv, np.stack([u, v], -1), atol=1e-9)
  np.testing.assert_allclose(z, depth)


def test_supervision_masks():
  v1 = np.array([1, 1, 1, 1, 0, 0, 0, 0], bool)
  f1 = np.array([1, 1, 0, 0, 1, 1, 0, 0], bool)
  vo = np.array([1, 0, 1, 0, 1, 0, 1, 0], bool)
  # (V1 and not F1) or (F1 and V_other), written out by hand.
  np.testing.assert_array_equal(g.covis_supervision_mask(v1, f1, vo), [1, 0, 1, 1, 1, 0, 0, 0])
  flow = np.zeros((4, 5, 2), np.float32)
  flow[0, 0] = (-0.6, 0.0)  # leaves the image on the left
  flow[1, 4] = (0.49, 0.0)  # still inside (u < W - 0.5)
  flow[2, 2] = (0.0, 1.6)  # v = 3.6 >= H - 0.5
  labels = g.flyingchairs_labels(flow)
  expected = np.ones((4, 5), bool)
  expected[0, 0] = expected[2, 2] = False
  np.testing.assert_array_equal(labels["covisibility"], expected)
  assert labels["flow_valid"].all() and not labels["covis_valid"].any()
  valid1 = np.ones((4, 5), bool)
  valid1[3, 2] = False
  other = g.other_view_validity(valid1, flow)
  assert not other[0, 0] and not other[2, 2] and other[1, 4]
  flow[1, 1] = (0.6, 1.6)  # lands on (u, v) = (1.6, 2.6): nearest pixel row 3, column 2, invalid
  assert not g.other_view_validity(valid1, flow)[1, 1]
  flow[1, 1] = (0.6, 1.4)  # (1.6, 2.4): row 2, column 2, valid
  assert g.other_view_validity(valid1, flow)[1, 1]


def test_bilinear_sample_against_hand_values():
  img = np.array([[0.0, 1.0], [2.0, 3.0]])
  vals, ok = g.bilinear_sample(img, np.array([[0.5, 0.5], [0.25, 0.0], [-0.4, 1.0], [1.3, 1.3]]))
  np.testing.assert_allclose(vals, [1.5, 0.25, 2.0, 3.0])
  assert ok.all()
  valid = np.array([[True, False], [True, True]])
  vals, ok = g.bilinear_sample(img, np.array([[0.5, 0.0], [1.0, 0.0]]), valid)
  np.testing.assert_allclose(vals[0], 0.0)  # the invalid neighbour is ignored, not mixed in
  assert ok[0] and not ok[1]


def test_thresholds_table_s1():
  T = g.COVIS_THRESHOLDS
  for name in ("blendedmvs", "megadepth", "scannetpp", "habitat", "kubric4d"):
    assert T[name] == (0.1, 0.005)
  assert T["tartanair_v2"] == (0.1, 0.01)
  assert T["flyingthings"] == T["monkaa"] == (0.01, 0.001)
  with pytest.raises(KeyError, match="flyingchairs"):
    g.covis_thresholds("flyingchairs")


def test_shape_errors_name_the_argument():
  d = np.ones((4, 4))
  with pytest.raises(ValueError, match="K1"):
    g.correspondence_from_depth(d, K, np.eye(4), d, np.eye(4)[:3, :2], np.eye(4), *TAU)
  with pytest.raises(ValueError, match="depth0"):
    g.correspondence_from_depth(np.ones(4), K, np.eye(4), d, K, np.eye(4), *TAU)


def test_target_image_of_another_size():
  # Same camera centre, target at half resolution: target pixel = (u + 0.5) / 2 - 0.5 for the
  # centre-at-integer convention (K1 = S K0 with the half-pixel shift).
  z = 7.0
  S = np.array([[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1.0]])
  K1 = S @ K
  depth0, depth1 = np.full((H, W), z), np.full((H // 2, W // 2), z)
  out = g.correspondence_from_depth(depth0, K, np.eye(4), depth1, K1, np.eye(4), *TAU)
  u, v = grid()
  np.testing.assert_allclose(out["flow"][..., 0], (u + 0.5) / 2 - 0.5 - u, atol=1e-6)
  np.testing.assert_allclose(out["flow"][..., 1], (v + 0.5) / 2 - 0.5 - v, atol=1e-6)
  assert out["covisibility"].all()
