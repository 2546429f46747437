"""The fast correspondence path against the plain float64 formulas it replaced.

`_reference` below is the straightforward implementation (world points as [H, W, 3] stacks,
`camera.transform` / `camera.project`, the float64 `bilinear_sample`): the fast path must give the
same masks pixel for pixel, except where the reference itself is within float rounding of a
decision (error within 1e-5 relative of the threshold, a nearest-pixel tie), and the same flow.
"""

import numpy as np
import pytest

from ufm_jax import geometry as g
from ufm_jax.geometry import camera
from ufm_jax.geometry import covisibility


def _reference(points_world, valid0, depth1, K1, cam2world1, tau_d, tau_r, search=0.0):
  pc = camera.transform(camera.invert_pose(cam2world1), points_world)
  uv, z = camera.project(pc, K1)
  h1, w1 = depth1.shape
  with np.errstate(invalid="ignore"):
    in_front = valid0 & np.isfinite(pc).all(-1) & (z > 1e-6) & np.isfinite(uv).all(-1)
  fov = in_front & g.inside_image(uv, h1, w1)
  valid1 = camera.valid_depth(depth1)
  range1 = np.where(valid1, depth1, 0.0) * camera.ray_norms(h1, w1, K1)
  uv_safe = np.where(in_front[..., None], uv, 0.0)
  sampled, ok = g.bilinear_sample(range1, uv_safe, valid1)
  expected = np.linalg.norm(np.where(in_front[..., None], pc, 0.0), axis=-1)
  error = np.where(fov & ok, np.abs(expected - sampled), np.inf)
  threshold = tau_d + tau_r * expected
  covis = fov & ok & (error < threshold)
  near = fov & ~covis & ok & (np.abs(error - threshold) < 1e-5 * threshold)
  if search:
    for dx in (-search, 0.0, search):
      for dy in (-search, 0.0, search):
        if dx or dy:
          val, ok_t = g.bilinear_sample(range1, uv_safe + (dx, dy), valid1)
          e = np.abs(expected - val)
          covis |= fov & ok_t & (e < threshold)
          near |= fov & ok_t & (np.abs(e - threshold) < 1e-5 * threshold)
  near |= fov & (np.abs(error - threshold) < 1e-5 * threshold)
  frac = uv_safe - np.floor(uv_safe)
  tie = (np.abs(frac - 0.5) < 1e-6).any(-1)
  valid_other = fov & g.nearest_sample(valid1, uv_safe)
  flow = np.where(in_front[..., None], uv_safe - camera.pixel_grid(*valid0.shape), 0.0)
  return dict(flow=flow, covisibility=covis, fov_mask=fov, in_front=in_front,
              valid_other=valid_other, near=near, tie=tie)


def _scene(rng, hw0, hw1, holes=True, skew=0.0):
  """A plane seen by two random cameras (depth rendered analytically in both views), with a bumpy
  perturbation of the target depth straddling the threshold, a nearer occluder in the target and
  holes (0, nan, inf) in both."""
  def K(hw):
    h, w = hw
    f = rng.uniform(0.7, 1.3) * w
    return np.array([[f, skew, w / 2 + rng.uniform(-3, 3)], [0, f * rng.uniform(0.9, 1.1),
                     h / 2 + rng.uniform(-3, 3)], [0, 0, 1.0]])

  def plane_depth(hw, K_, c2w, n, dd):
    h, w = hw
    rays = camera.rays(camera.pixel_grid(h, w), K_) @ c2w[:3, :3].T
    return (dd - n @ c2w[:3, 3]) / (rays @ n)

  c2w0 = camera.pose_from_rt(camera.axis_angle_to_rotation(rng.normal(size=3), rng.uniform(0, 3)),
                             rng.normal(size=3) * 100)  # far from the origin: large world coords
  rel = camera.pose_from_rt(camera.axis_angle_to_rotation(rng.normal(size=3), rng.uniform(0, 0.1)),
                            rng.normal(size=3) * 0.3)
  c2w1 = c2w0 @ rel
  n = c2w0[:3, :3] @ np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), -1.0])
  n /= np.linalg.norm(n)
  dd = n @ (c2w0[:3, :3] @ np.array([0, 0, 5.0]) + c2w0[:3, 3])
  K0, K1 = K(hw0), K(hw1)
  d0 = plane_depth(hw0, K0, c2w0, n, dd)
  d1 = plane_depth(hw1, K1, c2w1, n, dd)
  h1, w1 = hw1
  v, u = np.mgrid[0:h1, 0:w1]
  d1 = d1 * (1 + 0.03 * np.sin(0.9 * u) * np.cos(0.7 * v))  # ~ +-0.15: around the threshold
  d1[h1 // 2:, : w1 // 3] *= 0.6  # occluder
  for d in ((d0, d1) if holes else ()):
    h, w = d.shape
    d[rng.random((h, w)) < 0.05] = 0.0
    d[h // 3:h // 3 + 3, w // 4:w // 4 + 5] = np.nan
    d[0, -1] = np.inf
  return d0.astype(np.float32), K0, c2w0, d1.astype(np.float32), K1, c2w1


def _compare(out, ref, flow_atol=1e-5):
  for key in ("fov_mask", "in_front"):
    np.testing.assert_array_equal(out[key], ref[key], err_msg=key)
  bad = (out["covisibility"] != ref["covisibility"]) & ~ref["near"]
  assert not bad.any(), f"{bad.sum()} covisibility pixels differ"
  bad = (out["valid_other"] != ref["valid_other"]) & ~ref["tie"]
  assert not bad.any(), f"{bad.sum()} valid_other pixels differ"
  assert out["flow"].dtype == np.float32
  np.testing.assert_allclose(out["flow"], ref["flow"].astype(np.float32), atol=flow_atol, rtol=0)
  assert 0.2 < ref["covisibility"].mean() and (~ref["covisibility"] & ref["fov_mask"]).any()


@pytest.mark.parametrize("seed,hw0,hw1,skew,search,block", [
    (0, (30, 40), (30, 40), 0.0, 0.0, None),
    (1, (33, 47), (21, 29), 0.7, 0.0, None),
    (2, (40, 28), (40, 28), 0.0, 0.5, None),
    (3, (1, 9), (2, 9), 0.0, 0.0, None),
    (4, (33, 47), (30, 40), 0.0, 0.0, 100),  # several row blocks, the last one partial
    (5, (40, 28), (40, 28), 0.0, 0.5, 60),
])
def test_depth_matches_float64_reference(seed, hw0, hw1, skew, search, block, monkeypatch):
  if block:
    monkeypatch.setattr(covisibility, "_BLOCK_PIXELS", block)
  rng = np.random.default_rng(seed)
  d0, K0, c2w0, d1, K1, c2w1 = _scene(rng, hw0, hw1, holes=hw0[0] > 1, skew=skew)
  tau = (0.05, 0.01)
  out = g.correspondence_from_depth(d0, K0, c2w0, d1, K1, c2w1, *tau, subpixel_search=search)
  valid0 = camera.valid_depth(d0)
  pts = camera.transform(c2w0, camera.unproject(np.where(valid0, d0, 0.0), K0))
  ref = _reference(pts, valid0, d1, K1, c2w1, *tau, search)
  if hw0[0] == 1:  # degenerate 1-row images: only check that it runs and agrees on the masks
    np.testing.assert_array_equal(out["fov_mask"], ref["fov_mask"])
    return
  _compare(out, ref)
  np.testing.assert_array_equal(out["valid"], valid0)
  # The public world-points entry point runs the same core.
  out2 = g.covisibility_from_points(pts, valid0, d1, K1, c2w1, *tau, subpixel_search=search)
  _compare(out2, ref)


def test_rigid_matches_float64_reference(monkeypatch):
  monkeypatch.setattr(covisibility, "_BLOCK_PIXELS", 200)  # several row blocks
  rng = np.random.default_rng(7)
  d0, K0, c2w0, d1, K1, c2w1 = _scene(rng, (36, 44), (36, 44))
  seg = np.zeros(d0.shape, np.int32)
  seg[5:20, 5:25], seg[18:30, 20:40], seg[0:4, :] = 1, 3, 9  # 9: no pose -> invalid
  poses0 = {k: camera.pose_from_rt(camera.axis_angle_to_rotation(rng.normal(size=3), 0.2),
                                   rng.normal(size=3)) for k in (1, 3)}
  poses1 = {k: camera.pose_from_rt(camera.axis_angle_to_rotation(rng.normal(size=3), 0.1),
                                   T[:3, 3] + 0.1 * rng.normal(size=3)) @ T
            for k, T in poses0.items()}
  poses0[0] = poses1[0] = np.eye(4)
  tau = (0.05, 0.01)
  out = g.correspondence_from_rigid_objects(d0, K0, c2w0, seg, poses0, d1, K1, c2w1, poses1, *tau)
  motions, known = g.object_motions(poses0, poses1)
  ids = np.where(seg < len(motions), seg, 0)
  valid0 = camera.valid_depth(d0) & (seg < len(motions)) & known[ids]
  pts = camera.transform(c2w0, camera.unproject(np.where(valid0, d0, 0.0), K0))
  M = motions[ids]
  moved = np.einsum("hwij,hwj->hwi", M[..., :3, :3], pts) + M[..., :3, 3]
  ref = _reference(moved, valid0, d1, K1, c2w1, *tau)
  np.testing.assert_array_equal(out["valid"], valid0)
  assert not valid0[:4].any() and valid0[seg == 3].mean() > 0.8
  _compare(out, ref)
  # On a pixel grid (the training pipeline's lazy labels): the full result there, bit for bit.
  rows, cols = np.unique(rng.integers(0, 36, 20)), np.unique(rng.integers(0, 44, 25))
  sub = g.correspondence_from_rigid_objects(d0, K0, c2w0, seg, poses0, d1, K1, c2w1, poses1,
                                            *tau, rows=rows, cols=cols)
  for k, v in out.items():
    expected = np.ascontiguousarray(v[np.ix_(rows, cols)])
    assert np.array_equal(np.ascontiguousarray(sub[k]).view(np.uint8), expected.view(np.uint8)), k


def test_source_load_benchmark_covers_every_reader():
  import pathlib
  import subprocess
  import sys
  repo = pathlib.Path(__file__).resolve().parents[1]
  out = subprocess.run([sys.executable, str(repo / "benchmarks" / "source_load.py"), "--shape",
                        "28,42", "--repeats", "1"], capture_output=True, text=True, timeout=600)
  assert out.returncode == 0, out.stderr[-2000:]
  expected = {"blendedmvs", "megadepth", "tartanair_v2", "scannetpp", "habitat", "staticthings",
              "kubric4d", "eth3d", "dtu", "tawb", "flyingchairs", "flyingthings", "monkaa",
              "sintel_clean", "spring", "hd1k", "kitti2015"}
  rows = {line.split()[0]: line for line in out.stdout.splitlines() if " ms CPU " in line}
  assert set(rows) == expected, out.stdout
  for name, line in rows.items():
    cpu, wall = float(line.split()[1]), float(line.split()[4])
    assert cpu >= 0 and wall > 0, line


def test_sceneflow_row_blocks_give_the_unblocked_result(monkeypatch):
  from ufm_jax.geometry import sceneflow
  rng = np.random.default_rng(3)
  h, w = 37, 23
  flow = rng.normal(0, 3, (h, w, 2)).astype(np.float32)
  flow[0, :3] = np.nan
  d0 = rng.uniform(5, 30, (h, w)).astype(np.float32)
  d1 = d0 + rng.normal(0, 0.5, (h, w)).astype(np.float32)
  d0[5, 5] = d1[7, 7] = 0
  change = rng.normal(0, 0.3, (h, w)).astype(np.float32)
  whole = sceneflow.sceneflow_covisibility(flow, d0, change, d1, 0.01, 0.001)
  monkeypatch.setattr(sceneflow, "_BLOCK_PIXELS", 50)  # 2-row blocks
  blocked = sceneflow.sceneflow_covisibility(flow, d0, change, d1, 0.01, 0.001)
  assert whole["covisibility"].any() and not whole["covisibility"].all()
  for key, value in whole.items():
    np.testing.assert_array_equal(blocked[key], value, err_msg=key)


@pytest.mark.parametrize("channels", [None, 1, 2, 3, 4, 8])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_finite_pixels_equals_isfinite_all(channels, dtype):
  rng = np.random.default_rng(channels or 0)
  shape = (7, 9) if channels is None else (7, 9, channels)
  a = rng.normal(size=shape).astype(dtype)
  a.reshape(-1)[rng.choice(a.size, a.size // 3, replace=False)] = rng.choice(
      [np.nan, np.inf, -np.inf], a.size // 3)
  want = np.isfinite(a) if channels is None else np.isfinite(a).all(-1)
  for view in (a, a[:, ::-1], np.asfortranarray(a)):  # the non-contiguous fallback too
    got = camera.finite_pixels(view)
    assert got.dtype == bool and got.shape == view.shape[:2]
    np.testing.assert_array_equal(got, np.isfinite(view) if channels is None
                                  else np.isfinite(view).all(-1))
  assert want.any() and not want.all()


@pytest.mark.parametrize("search", [0.0, 0.3])
def test_depth_on_a_pixel_grid_equals_the_full_result_there(search):
  """correspondence_from_depth(rows=, cols=) is the full result at those pixels, bit for bit."""
  rng = np.random.default_rng(5)
  h, w = 50, 70
  K = np.array([[60.0, 0.0, 34.5], [0.0, 55.0, 24.0], [0.0, 0.0, 1.0]])
  d0 = rng.uniform(2, 3, (h, w)).astype(np.float32)
  d0[5:9, 7:20] = 0
  d0[30, 40] = np.nan
  d1 = rng.uniform(2, 3, (h, w)).astype(np.float32)
  d1[10:30, 50:60] = 0
  c2w1 = np.eye(4)
  a = 0.1
  c2w1[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
  c2w1[:3, 3] = [0.3, -0.1, 0.2]
  full = g.correspondence_from_depth(d0, K, np.eye(4), d1, K, c2w1, 0.05, 0.02, search)
  rows, cols = np.unique(rng.integers(0, h, 30)), np.unique(rng.integers(0, w, 40))
  sub = g.correspondence_from_depth(d0, K, np.eye(4), d1, K, c2w1, 0.05, 0.02, search,
                                    rows=rows, cols=cols)
  assert full["covisibility"].any() and not full["covisibility"].all()
  for k, v in full.items():
    expected = np.ascontiguousarray(v[np.ix_(rows, cols)])
    assert sub[k].shape == expected.shape, k
    assert np.array_equal(np.ascontiguousarray(sub[k]).view(np.uint8), expected.view(np.uint8)), k
