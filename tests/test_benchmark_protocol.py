"""The official benchmark protocol (#31): the branch's labels, crops, readers and metrics, each
checked against values derived in the test from the definitions (docs/benchmarks.md)."""

import math
import os

import numpy as np
import pytest

from ufm_jax import evaluators
from ufm_jax.data import get_source
from ufm_jax.data.sources import _benchmark_branch as branch
from ufm_jax.evaluators import base, dense
from ufm_jax import geometry
from ufm_jax.geometry.thresholds import BENCHMARK_RENDERING_PARAMETERS as BENCH_PARAMS
from ufm_jax.testing import bench_trees, wide_trees

LN2 = math.log(2.0)


# ------------------------------------------------------------------------------------- labels
def test_thresholds_include_the_temperature_term():
  # tau = a + r d - ln(0.5) T: ETH3D (0.1 m, T 0.1 m, 0.005), DTU (12 mm, T 12 mm, 0.01); the
  # documented intercepts (docs/benchmarks.md, thresholds.py) from the table's values.
  a, t, r = BENCH_PARAMS["eth3d"]
  assert (a + t * LN2, r) == (pytest.approx(0.169, abs=5e-4), 0.005)
  a, t, r = BENCH_PARAMS["dtu"]
  assert (a + t * LN2, r) == (pytest.approx(20.318, abs=5e-4), 0.01)


def _shifted_pair(h=6, w=8, depth=5.0, shift=-0.25, hole=None):
  """Same pose, target principal point moved by `shift` px: the flow is (shift, 0) everywhere."""
  K0 = wide_trees.K_of(10.0, 10.0, 3.5, 2.5)
  K1 = K0.copy()
  K1[0, 2] += shift
  d0 = np.full((h, w), depth)
  d1 = d0.copy()
  if hole is not None:
    d1[:, hole] = 0
  return d0, K0, d1, K1


def test_zero_padded_bilinear_marks_border_and_hole_neighbours_occluded():
  # Target of source column c is u = c - 0.25, between columns c - 1 (weight 0.25) and c (0.75).
  # Column 0 mixes 0.25 of the zero padding: error 0.25 * range ~ 1.25 m > tau -> occluded.
  # A hole at target column 4 is a neighbour of sources 4 (weight 0.75) and 5 (0.25).
  d0, K0, d1, K1 = _shifted_pair(hole=4)
  lab = geometry.official_labels(d0, K0, np.eye(4), d1, K1, np.eye(4), BENCH_PARAMS["eth3d"])
  np.testing.assert_allclose(lab["flow"], np.broadcast_to([-0.25, 0.0], (6, 8, 2)), atol=1e-5)
  assert lab["flow_valid"].all()       # -0.25 >= -0.5: every target is in view
  expected = np.ones((6, 8), bool)
  expected[:, [0, 4, 5]] = False
  np.testing.assert_array_equal(lab["covisibility"], expected)
  # covis_valid: the nearest target pixel (round(c - 0.25) = c) must have depth -> all but col 4.
  expected = np.ones((6, 8), bool)
  expected[:, 4] = False
  np.testing.assert_array_equal(lab["covis_valid"], expected)


def test_covisible_iff_depth_error_below_tau():
  # Same camera, target depth = source depth + delta: error = delta * ||ray|| at distance
  # d = D * ||ray||; covisible iff error < 0.1 + 0.005 d + 0.1 ln 2.
  h, w, D = 5, 7, 4.0
  K = wide_trees.K_of(3.0, 3.0, 3.0, 2.0)
  ray = np.sqrt(1 + ((np.arange(w) - 3.0) / 3.0)[None] ** 2 + ((np.arange(h) - 2.0) / 3.0)[:, None] ** 2)
  delta = np.linspace(0.1, 0.3, h * w).reshape(h, w)   # spans tau: 0.189 .. 0.25 here
  d0, d1 = np.full((h, w), D), D + delta
  # the target range is sampled where the source pixel lands: on itself (flow 0)
  lab = geometry.official_labels(d0, K, np.eye(4), d1, K, np.eye(4), BENCH_PARAMS["eth3d"])
  tau = 0.1 + 0.005 * D * ray + 0.1 * LN2
  expected = delta * ray < tau
  assert 0 < expected.sum() < expected.size
  np.testing.assert_array_equal(lab["covisibility"], expected)
  # The branch's rule on the same data with DTU constants in mm: tau 20.318 + 0.01 d.
  lab = geometry.official_labels(d0 * 1000, K, np.eye(4), d1 * 1000, K, np.eye(4),
                                 BENCH_PARAMS["dtu"])
  np.testing.assert_array_equal(lab["covisibility"],
                                delta * 1000 * ray < 12 + 10 * D * ray + 12 * LN2)


def test_labels_match_the_plane_homography():
  scene = wide_trees.PlaneScene(hw0=(60, 80))
  lab = geometry.official_labels(scene.z_depth(0), scene.K[0], scene.c2w[0], scene.z_depth(1),
                                 scene.K[1], scene.c2w[1], BENCH_PARAMS["eth3d"])
  e = scene.expected()
  assert np.abs(lab["flow"] - e["flow"])[e["inside"]].max() < 2e-3
  np.testing.assert_array_equal(lab["flow_valid"], e["inside"])
  ok = ~e["ambiguous"]
  np.testing.assert_array_equal(lab["covisibility"][ok], (e["inside"] & ~e["hole1"])[ok])


# -------------------------------------------------------------------------------- crops
def test_crop_resize_view_upscales_then_centre_crops():
  # 400 x 600 (ETH3D processed): scale = max(560/600, 420/400) = 1.05 -> 630 x 420, crop 35 px.
  h, w = 400, 600
  image = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
  depth = np.tile(np.arange(w, dtype=np.float32), (h, 1))          # value = source column
  K = wide_trees.K_of(500.0, 505.0, 299.3, 199.6)
  img, d, K2, _ = branch.crop_resize_view(image, depth, K)
  assert img.shape == (420, 560, 3) and d.shape == (420, 560)
  # OpenCV nearest: output column j of the 630-wide map reads source column floor(j * 600/630).
  cols = np.floor((np.arange(560) + 35) * 600 / 630)
  np.testing.assert_array_equal(d[0], cols)
  s = 1.05 + 1e-8
  np.testing.assert_allclose(K2[0, 0], 500 * s, rtol=1e-6)
  np.testing.assert_allclose(K2[1, 1], 505 * s, rtol=1e-6)
  # pixel corners scale: cx' = (cx + 0.5) s - 0.5 - 35 (the 630 - 560 = 70 px margin halved)
  np.testing.assert_allclose(K2[0, 2], (299.3 + 0.5) * s - 0.5 - 35, atol=1e-3)
  np.testing.assert_allclose(K2[1, 2], (199.6 + 0.5) * s - 0.5, atol=1e-3)
  import PIL.Image
  ref = np.asarray(PIL.Image.fromarray(image).resize((630, 420), PIL.Image.Resampling.BICUBIC))
  np.testing.assert_array_equal(img, ref[:, 35:595])


def test_crop_resize_view_turns_portrait_views_to_landscape():
  """A portrait view is cropped to 560 x 420 (H x W) and turned counter-clockwise (the branch's
  transpose_to_landscape): turned pixel (u, v) is upright pixel (419 - v, u) and sees the same
  ray. The official pipeline on portrait views: tests/test_official_benchmark_parity.py."""
  from ufm_jax.data import official_ops
  h, w = 70, 40
  image = np.random.default_rng(1).integers(0, 256, (h, w, 3), dtype=np.uint8)
  depth = np.tile(np.arange(w, dtype=np.float32), (h, 1)) + 1
  K = wide_trees.K_of(50.0, 52.0, 19.2, 35.1)
  c2w = wide_trees.look_at((0.1, 0.2, 0.0), (0.0, 0.3, 5.0))
  img, d, K2, c2w2 = branch.crop_resize_view(image, depth, K, c2w)
  assert img.shape == (420, 560, 3) and d.shape == (420, 560)
  up = official_ops.resize_cover_center_crop(
      official_ops.StaticView(image, depth, np.array(K, np.float32), c2w), (420, 560), False)
  assert up.image.shape == (560, 420, 3)
  v, u = np.mgrid[0:420:37, 0:560:41]
  x, y = 419 - v, u
  np.testing.assert_array_equal(img[v, u], up.image[y, x])
  np.testing.assert_array_equal(d[v, u], up.depth[y, x])
  ray = lambda Kx, c, a, b: c[:3, :3] @ np.linalg.solve(Kx, [a, b, 1.0])   # noqa: E731
  for a, b in ((0, 0), (300, 100), (559, 419)):
    r = ray(np.asarray(K2, np.float64), np.asarray(c2w2, np.float64), a, b)
    r_up = ray(np.asarray(up.K, np.float64), np.asarray(c2w, np.float64), 419 - b, a)
    np.testing.assert_allclose(r / np.linalg.norm(r), r_up / np.linalg.norm(r_up), atol=1e-6)


def test_resize_short_center_crop_scales_flow_and_tests_the_crop():
  # 480 x 640 -> r = 0.875 -> 420 x 560, no crop; constant flow (8, -16) becomes (7, -14).
  h, w = 480, 640
  rng = np.random.default_rng(1)
  img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
  flow = np.broadcast_to(np.float32([8, -16]), (h, w, 2)).copy()
  nonocc = np.ones((h, w), bool)
  nonocc[:, :64] = False          # source columns 0..63 -> output columns 0..55 (nearest, 8/7)
  fov = np.ones((h, w), bool)
  fov[:48] = False                # rows 0..47 -> output rows 0..41
  i0, i1, f, m = branch.resize_short_center_crop(img, img, flow, {
      "non_occluded": nonocc, "fov": fov, "occlusion_supervision": np.ones((h, w), bool)})
  assert i0.shape == (420, 560, 3) and f.shape == (420, 560, 2)
  np.testing.assert_allclose(f, np.broadcast_to([7.0, -14.0], (420, 560, 2)), atol=1e-5)
  yy, xx = np.mgrid[0:420, 0:560]
  nonocc_out = xx >= 56
  inside = (xx + 7 < 560) & (yy - 14 >= 0)
  np.testing.assert_array_equal(m["non_occluded"], nonocc_out & inside)
  np.testing.assert_array_equal(m["fov"], (yy >= 42) & nonocc_out)      # ANDed, before the test
  np.testing.assert_array_equal(m["occlusion_supervision"], nonocc_out)
  # the images: torch's antialiased bilinear, truncated to uint8 (not rounded)
  from ufm_jax.data import resize
  ref = resize.resize_bilinear_aa(img.astype(np.float32), (420, 560))
  np.testing.assert_array_equal(i0, np.floor(ref).astype(np.uint8))


def test_resize_short_center_crop_crops_wide_inputs():
  # 420 x 600: r = 1 + 1e-8 keeps the size; the centre crop drops 20 columns each side.
  h, w = 420, 600
  img = np.zeros((h, w, 3), np.uint8)
  img[..., 0] = np.arange(w) % 256
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = -np.arange(w)                        # every target at x = 0 of the full image
  i0, _, f, m = branch.resize_short_center_crop(img, img, flow, {"non_occluded": np.ones((h, w), bool)})
  np.testing.assert_array_equal(i0[0, :, 0], np.arange(20, 580) % 256)
  np.testing.assert_array_equal(f[0, :, 0], -np.arange(20, 580))
  # in crop coordinates the target is x - (x + 20) = -20 < 0: outside everywhere
  assert not m["non_occluded"].any()


# ------------------------------------------------------------------------------------ readers
@pytest.fixture(scope="module")
def official_root(tmp_path_factory):
  """An official dataset_root: eth3d_processed/, dtu_processed/, anymap_data_pairs/, TA-WB/."""
  scene = wide_trees.PlaneScene(hw0=(420, 560))
  root = bench_trees.write_official_bench_root(str(tmp_path_factory.mktemp("official")), scene,
                                               tawb_samples(), flow_benches=False)
  return root, scene


def tawb_samples(n=3, h=48, w=64):
  rng = np.random.default_rng(2)
  out = []
  for k in range(n):
    flow = np.zeros((2, h, w), np.float32)
    flow[0] = 4.0 * (k + 1)
    out.append(dict(img0=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                    img1=rng.integers(0, 256, (h, w, 3), dtype=np.uint8), flow_fwd=flow,
                    non_occluded_fwd=np.ones((h, w), bool), fov_mask_fwd=np.ones((h, w), bool),
                    occlusion_supervision_mask_fwd=np.ones((h, w), bool)))
  return out


def _check_plane(sample, scene, units=1.0):
  e = scene.expected()
  assert sample["image0"].shape == (420, 560, 3)
  assert np.abs(sample["flow"] - e["flow"])[e["inside"]].max() < 2e-3
  np.testing.assert_array_equal(sample["flow_valid"], e["inside"])
  ok = ~e["ambiguous"]
  np.testing.assert_array_equal(sample["covisibility"][ok], (e["inside"] & ~e["hole1"])[ok])
  np.testing.assert_allclose(sample["meta"]["cam2world1"][:3, 3], scene.c2w[1][:3, 3] * units,
                             rtol=1e-4, atol=1e-4)


def test_eth3d_official_every_third_pair_and_labels(official_root):
  root, scene = official_root
  src = get_source("eth3d_official", os.path.join(root, "eth3d_processed"))
  # rows 0..3, [::3] -> rows 0 and 3
  assert [p[1] for p in src.pairs] == ["DSC_0", "DSC_6"]
  _check_plane(src[1], scene)


def test_dtu_official_every_50th_pair_in_millimetres(official_root):
  root, scene = official_root
  src = get_source("dtu_official", os.path.join(root, "dtu_processed"))
  assert len(src) == 2      # rows 0 and 50 of 51
  _check_plane(src[0], scene, units=1000.0)


def test_official_pair_table_errors(tmp_path):
  scene = wide_trees.PlaneScene(hw0=(42, 56))
  bench_trees.write_eth3d_processed(str(tmp_path / "eth3d_processed"), scene)
  with pytest.raises(FileNotFoundError, match="eth3d_valid_pairs.npz"):
    get_source("eth3d_official", str(tmp_path / "eth3d_processed"))
  np.savez(tmp_path / "bytes.npz", data=np.array([[b"courtyard", b"DSC_0286", b"DSC_0287", b"1"]]))
  src = get_source("eth3d_official", str(tmp_path / "eth3d_processed"), pairs=str(tmp_path / "bytes.npz"))
  assert src.pairs == [("courtyard", "DSC_0286", "DSC_0287")]
  np.savez(tmp_path / "bad.npz", rows=np.zeros(3))
  with pytest.raises(ValueError, match="bad.npz.*`data`"):
    get_source("eth3d_official", str(tmp_path / "eth3d_processed"), pairs=str(tmp_path / "bad.npz"))


def test_tawb_official_reads_the_data_split(official_root, tmp_path):
  root, _ = official_root
  src = get_source("tawb_official", os.path.join(root, "TA-WB"))
  assert len(src) == 3                        # min(1500, 3); the statistics JSON is skipped
  s = src[2]
  # 48 x 64 -> r = max(420/48, 560/64) = 8.75 -> 420 x 560; flow 12 px -> 105 px
  np.testing.assert_allclose(s["flow"][..., 0], 105.0, atol=1e-4)
  xx = np.arange(560)[None]
  np.testing.assert_array_equal(s["covisibility"], np.broadcast_to(xx + 105 < 560, (420, 560)))
  assert s["flow_valid"].all()
  assert len(get_source("tawb_official", os.path.join(root, "TA-WB"), num=2)) == 2
  bad = tawb_samples(1)
  bad[0]["flow_fwd"] = np.zeros((48, 64, 2), np.float32)
  bench_trees.write_tawb_data(str(tmp_path), bad)
  with pytest.raises(ValueError, match=r"part_000.h5.*flow_fwd is \(48, 64, 2\)"):
    get_source("tawb_official", str(tmp_path))[0]
  # NaN flow where the stored labels say covisible (even outside fov) is refused, not scored.
  bad = tawb_samples(1)
  bad[0]["flow_fwd"][:, 5, 7] = np.nan
  bad[0]["fov_mask_fwd"][5, 7] = False
  bench_trees.write_tawb_data(str(tmp_path / "nan"), bad)
  with pytest.raises(ValueError, match=r"part_000.h5 sample 0: non-finite flow .* at 1 of"):
    get_source("tawb_official", str(tmp_path / "nan"))[0]


def test_sintel_official_covisibility_is_not_occluded_only(tmp_path):
  bench_trees.write_sintel(str(tmp_path), frames=2)
  native = get_source("sintel_clean", str(tmp_path))[0]
  official = get_source("sintel_clean", str(tmp_path), covis_in_image=False)[0]
  occ = native["meta"]["occlusion"]
  h, w = occ.shape
  tx = np.arange(w)[None] + native["flow"][..., 0]
  ty = np.arange(h)[:, None] + native["flow"][..., 1]
  inside = (tx >= -0.5) & (tx < w - 0.5) & (ty >= -0.5) & (ty < h - 0.5)
  assert (~occ & ~inside).any()                # pixels where the two rules differ
  np.testing.assert_array_equal(official["covisibility"], ~occ)
  np.testing.assert_array_equal(native["covisibility"], ~occ & inside)


# ------------------------------------------------------------------------------------ metrics
def _sample(flow, valid, covis, covis_valid=None, hw=(2, 3)):
  return dict(image0=np.zeros(hw + (3,), np.uint8), image1=np.zeros(hw + (3,), np.uint8),
              flow=np.asarray(flow, np.float32), flow_valid=np.asarray(valid, bool),
              covisibility=np.asarray(covis, bool),
              covis_valid=np.ones(hw, bool) if covis_valid is None else np.asarray(covis_valid, bool))


def test_dense_metrics_official_pooled_by_hand():
  # Prediction 0: EPE = |GT|. Sample A (2 x 3): EPEs 0.5 1.5 3 / 4 6 10 (all along x).
  ea = np.array([[0.5, 1.5, 3.0], [4.0, 6.0, 10.0]])
  a = _sample(np.stack([ea, 0 * ea], -1), [[1, 1, 1], [1, 1, 0]], [[1, 1, 0], [1, 0, 1]],
              covis_valid=np.zeros((2, 3)))        # ignored by the official masks
  # Sample B: EPEs 3-4-5 triangles: 5 everywhere, (3, 4) components.
  b = _sample(np.broadcast_to([3.0, 4.0], (2, 3, 2)), np.ones((2, 3)), [[1, 0, 0], [0, 0, 0]])
  acc = dense.DenseMetrics(official=True)
  for s in (a, b):
    acc(s, {"flow": np.zeros_like(s["flow"]), "covisibility": np.ones(s["flow"].shape[:2])})
  r = acc.result()
  covis = [0.5, 1.5, 4.0] + [5.0]                  # valid & covisible
  occluded = [3.0, 6.0] + [5.0] * 5                 # valid & not covisible
  every = [0.5, 1.5, 3.0, 4.0, 6.0] + [5.0] * 6
  assert r["epe"] == pytest.approx(sum(covis) / 4)
  assert r["px1"] == pytest.approx(100 * 3 / 4)     # 1.5, 4, 5 > 1
  assert r["px2"] == pytest.approx(100 * 2 / 4)
  assert r["px5"] == pytest.approx(0.0)             # 5 is not > 5
  assert r["epe_occluded"] == pytest.approx(sum(occluded) / 7)
  assert r["epe_all"] == pytest.approx(sum(every) / 11)


def test_dense_metrics_native_occluded_needs_target_in_view_and_covis_valid():
  # 1 x 4, GT flow x = (0, 0, 0, 10): pixel 3 lands outside a 4-wide image1.
  flow = np.array([[[0, 0], [0, 0], [0, 0], [10, 0]]], np.float32)
  s = _sample(flow, np.ones((1, 4)), [[1, 0, 0, 0]], covis_valid=[[1, 1, 0, 1]], hw=(1, 4))
  pred = {"flow": flow + np.array([2.0, 0.0], np.float32), "covisibility": np.ones((1, 4))}
  acc = dense.DenseMetrics()
  acc(s, pred)
  r = acc.result()
  assert r["epe"] == pytest.approx(2.0) and r["epe_occluded"] == pytest.approx(2.0)
  assert acc.pooled.count["epe_occluded"] == 1     # pixel 1 only: 2 lacks covis_valid, 3 leaves


# --------------------------------------------------------------------------- bench wiring
class ZeroFlow:
  inference_resolution = (42, 56)

  def apply(self, variables, source, target):
    import jax.numpy as jnp
    b, h, w, _ = source.shape
    return {"flow": jnp.zeros((b, h, w, 2)) + 0 * target.mean(), "covisibility": jnp.ones((b, h, w))}


def test_run_bench_official_eth3d_scores_the_crop(official_root):
  root, scene = official_root
  runner = base.Runner(ZeroFlow(), {})
  res, n = evaluators.run_bench("eth3d", runner, root, progress=False)
  assert n == {"eth3d": 2}
  # zero prediction: EPE = |GT flow| pooled over the covisible pixels of both (identical) pairs
  e = scene.expected()
  covis = e["inside"] & ~e["hole1"]
  mag = np.linalg.norm(e["flow"], axis=-1)
  assert res["eth3d/epe"] == pytest.approx(mag[covis].mean(), rel=2e-3)
  assert res["eth3d/epe_all"] == pytest.approx(mag[e["inside"]].mean(), rel=1e-4)
  with pytest.raises(ValueError, match="native"):
    evaluators.run_bench("eth3d", base.Runner(ZeroFlow(), {}, 560), root, progress=False)


def test_bench_table_protocols():
  assert {n for n, b in evaluators.OFFICIAL.items()} == {"sintel", "kitti", "eth3d", "dtu", "tawb"}
  assert evaluators.get_bench("eth3d").protocol == "official"
  assert evaluators.get_bench("eth3d", "native") is evaluators.BENCHES["eth3d"]
  assert evaluators.get_bench("eth3d_pose", "official") is evaluators.BENCHES["eth3d_pose"]
  with pytest.raises(ValueError, match="protocol"):
    evaluators.get_bench("eth3d", "paper")
