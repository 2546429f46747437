"""The embedded synthetic dataset: flow correctness by warping, occlusion, determinism, source."""

import pathlib

import numpy as np
import pytest

from ufm_jax import data
from ufm_jax import geometry as geo
from ufm_jax.data import synthetic as S

SIZE = (48, 64)


def warp_error(sample, shift=0.0):
  """Per-pixel mean |image1(x + flow) - image0| with an independent bilinear sampler."""
  import cv2
  h, w = sample["flow"].shape[:2]
  v, u = np.mgrid[0:h, 0:w].astype(np.float32)
  mx = u + sample["flow"][..., 0] + shift
  my = v + sample["flow"][..., 1]
  warped = cv2.remap(sample["image1"].astype(np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
  return np.abs(warped - sample["image0"].astype(np.float32)).mean(-1)


@pytest.fixture(scope="module")
def pairs():
  cfg = S.SyntheticConfig(size=(64, 80))
  out = []
  for pair_type, moving in (("flow", 0.0), ("flow", 1.0), ("wide", 0.0), ("wide", 1.0)):
    c = S.SyntheticConfig(size=cfg.size, pair_type=pair_type, moving_object_prob=moving)
    for i in range(2):
      out.extend(S.generate_pair(S.pair_seed(7, "train", i), c))
  return out


def near_depth_edge_in_target(sample):
  """Source pixels whose target lands within a pixel of a depth discontinuity of image1, where
  bilinear resampling legitimately mixes the colours of two surfaces."""
  d = sample["meta"]["depth1"].astype(np.float64)
  edge = np.zeros(d.shape, bool)
  jump_x = np.abs(np.diff(d, axis=1)) > 0.05 * np.minimum(d[:, 1:], d[:, :-1])
  jump_y = np.abs(np.diff(d, axis=0)) > 0.05 * np.minimum(d[1:], d[:-1])
  edge[:, 1:] |= jump_x
  edge[:, :-1] |= jump_x
  edge[1:] |= jump_y
  edge[:-1] |= jump_y
  h, w = sample["flow"].shape[:2]
  target = geo.pixel_grid(h, w) + sample["flow"]
  near = np.zeros((h, w), bool)
  for du in (-1, 0, 1):
    for dv in (-1, 0, 1):
      near |= geo.nearest_sample(edge, target + (du, dv))
  return near


def test_warping_image1_by_flow_reproduces_image0_on_covisible_pixels(pairs):
  for s in pairs:
    c = s["covisibility"]
    assert c.sum() > 200, s["meta"]
    err = warp_error(s)
    smooth = c & ~near_depth_edge_in_target(s)
    # Solid textures with periods of >= ~3 px: bilinear resampling error only.
    assert np.median(err[c]) < 2.0 and err[smooth].mean() < 3.0, (s["meta"], err[smooth].mean())
    # The check is sensitive: a 1-pixel flow error is clearly worse.
    assert warp_error(s, shift=1.0)[smooth].mean() > 2 * err[smooth].mean()


def test_pair_types_and_moving_object(pairs):
  angles = [s["meta"]["view_angle_deg"] for s in pairs]
  flow_angles = [a for a, s in zip(angles, pairs) if s["meta"]["pair_type"] == "flow"]
  wide_angles = [a for a, s in zip(angles, pairs) if s["meta"]["pair_type"] == "wide"]
  assert max(flow_angles) < 8 and min(wide_angles) >= 5 and max(wide_angles) <= 95
  moving = [s for s in pairs if s["meta"]["moving_object"]]
  assert moving
  seg_pixels = sum(int((s["meta"]["segmentation0"] == 1).sum()) for s in moving)
  assert seg_pixels > 0


def test_pan_pairs_rotate_in_range_and_warp():
  # Pan pairs: the relative camera rotation is within pan_angle_deg (the eye moves < ~0.3), about
  # an axis in the image plane (no roll), and the flow still reproduces image0 by warping.
  c = S.SyntheticConfig(size=(64, 80), pair_type="pan", moving_object_prob=0.0,
                        pan_angle_deg=(6.0, 9.0))
  for i in range(3):
    s = S.generate_pair(S.pair_seed(11, "train", i), c, directions=(0,))[0]
    assert s["meta"]["pair_type"] == "pan"
    r = s["meta"]["cam2world0"][:3, :3].T @ s["meta"]["cam2world1"][:3, :3]
    angle = np.rad2deg(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
    assert 6.0 - 1e-6 <= angle <= 9.0 + 1e-6, angle
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    assert abs(axis[2]) < 1e-6 * np.linalg.norm(axis) + 1e-9, axis  # camera z: no roll
    assert np.linalg.norm(s["meta"]["cam2world0"][:3, 3] - s["meta"]["cam2world1"][:3, 3]) < 0.3
    cov = s["covisibility"]
    smooth = cov & ~near_depth_edge_in_target(s)
    assert np.median(warp_error(s)[cov]) < 2.0 and warp_error(s)[smooth].mean() < 3.0
    # A pan of >= 6 degrees at a 50..70 degree field of view moves the image by several pixels.
    assert np.median(np.linalg.norm(s["flow"], axis=-1)[cov]) > 3.0


def test_shift_pairs_have_exact_labels():
  # image1(p + d) == image0(p) bit for bit on covisible pixels, exactly the pixels whose p + d
  # leaves the image are not covisible, and the backward pair is the forward one reversed.
  c = S.SyntheticConfig(size=(28, 42), pair_type="shift", max_shift=6)
  for i in range(5):
    fwd, bwd = S.generate_pair(S.pair_seed(0, "train", i), c)
    for s in (fwd, bwd):
      d = s["flow"][0, 0].astype(int)
      assert (s["flow"] == d).all() and np.abs(d).max() <= 6
      assert s["meta"]["shift"] == d.tolist() and s["flow_valid"].all()
      v, u = np.nonzero(s["covisibility"])
      np.testing.assert_array_equal(s["image1"][v + d[1], u + d[0]], s["image0"][v, u])
      assert s["covisibility"].sum() == (28 - abs(d[1])) * (42 - abs(d[0]))
    np.testing.assert_array_equal(bwd["flow"], -fwd["flow"])
    np.testing.assert_array_equal(bwd["image0"], fwd["image1"])


def test_layers_pairs_have_exact_labels():
  # Each view is two layers (background, rectangle on top); a pixel moves with its layer, lands
  # on the same texel of the other view, and is covisible exactly where the other view shows the
  # same layer there (so the rectangle occludes background pixels; checked from layer maps).
  c = S.SyntheticConfig(size=(28, 42), pair_type="layers", max_shift=6)
  occluded = 0
  for i in range(8):
    fwd, bwd = S.generate_pair(S.pair_seed(0, "train", i), c)
    layer_maps = []
    for s in (fwd, bwd):
      t, l, rh, rw = s["meta"]["layer_rect"]
      m = np.zeros((28, 42), bool)
      m[max(t, 0):t + rh, max(l, 0):l + rw] = True
      layer_maps.append(m)
    for k, s in enumerate((fwd, bwd)):
      front, other = layer_maps[k], layer_maps[1 - k]
      d_bg, d_fg = np.array(s["meta"]["shift"]), np.array(s["meta"]["layer_shift"])
      assert np.abs(d_bg).max() <= 6 and np.abs(d_fg).max() <= 6
      np.testing.assert_array_equal(s["flow"], np.where(front[..., None], d_fg, d_bg))
      v, u = np.mgrid[0:28, 0:42]
      x, y = u + s["flow"][..., 0].astype(int), v + s["flow"][..., 1].astype(int)
      in_view = (x >= 0) & (x < 42) & (y >= 0) & (y < 28)
      same = np.zeros_like(in_view)
      same[in_view] = other[y[in_view], x[in_view]] == front[in_view]
      np.testing.assert_array_equal(s["covisibility"], in_view & same)
      vv, uu = np.nonzero(s["covisibility"])
      np.testing.assert_array_equal(s["image1"][y[vv, uu], x[vv, uu]], s["image0"][vv, uu])
      occluded += (in_view & ~same).sum()
    np.testing.assert_array_equal(bwd["image0"], fwd["image1"])
  assert occluded > 0


def test_aligned_shift_fraction():
  c = S.SyntheticConfig(size=(28, 28), pair_type="shift", max_shift=10, aligned_shift_frac=0.5,
                        aligned_shift_step=7)
  shifts = [S.generate_pair(S.pair_seed(0, "train", i), c, (0,))[0]["meta"]["shift"]
            for i in range(200)]
  aligned = [d for d in shifts if d[0] % 7 == 0 and d[1] % 7 == 0]
  # Unaligned draws land on a multiple of 7 in both axes with probability (3/21)^2 ~ 2%.
  assert 0.4 < len(aligned) / len(shifts) < 0.65
  assert max(max(abs(x) for x in d) for d in aligned) == 14
  with pytest.raises(ValueError, match="aligned_shift_frac"):
    S.SyntheticConfig(pair_type="shift", aligned_shift_frac=1.5)


def test_shift_pairs_through_the_source_and_writer(tmp_path):
  src = data.get_source("synthetic", None, split="val", num_pairs=3, size=(28, 28),
                        pair_type="shift", max_shift=4)
  fwd, bwd = src.both(1)
  S.write_pair(str(tmp_path / "p"), fwd, bwd)  # no scene, so no depth.npz
  back = data.get_source("pairs_folder", str(tmp_path))[0]
  np.testing.assert_array_equal(back["flow"], fwd["flow"])
  np.testing.assert_array_equal(back["image1"], fwd["image1"])
  assert not (tmp_path / "p" / "depth.npz").exists()


def test_occlusion_exists(pairs):
  # Somewhere a pixel is in view of camera 1 with valid depth there but hidden: not covisible.
  occluded = [((s["covis_valid"] & ~s["covisibility"]) &
               geo.fov_mask_from_flow(s["flow"])).sum() for s in pairs]
  assert sum(o > 10 for o in occluded) >= 2


def test_backward_is_consistent_with_forward(pairs):
  fwd, bwd = pairs[0], pairs[1]
  np.testing.assert_array_equal(fwd["image0"], bwd["image1"])
  np.testing.assert_array_equal(fwd["meta"]["cam2world0"], bwd["meta"]["cam2world1"])
  # Forward-backward cycle: x -> x + f(x) -> back to x on covisible pixels.
  back, ok = geo.bilinear_sample(bwd["flow"], geo.pixel_grid(*fwd["flow"].shape[:2])
                                 + fwd["flow"], bwd["covisibility"])
  sel = fwd["covisibility"] & ok
  cycle = np.linalg.norm(fwd["flow"] + back, axis=-1)[sel]
  assert np.median(cycle) < 0.05


def test_determinism_and_split_disjointness():
  cfg = S.SyntheticConfig(size=SIZE)
  a = S.generate_pair(S.pair_seed(3, "train", 5), cfg)[0]
  b = S.generate_pair(S.pair_seed(3, "train", 5), cfg)[0]
  for k in ("image0", "image1", "flow", "covisibility", "covis_valid", "flow_valid"):
    np.testing.assert_array_equal(a[k], b[k])
  c = S.generate_pair(S.pair_seed(3, "val", 5), cfg)[0]
  d = S.generate_pair(S.pair_seed(4, "train", 5), cfg)[0]
  assert not np.array_equal(a["image0"], c["image0"])
  assert not np.array_equal(a["image0"], d["image0"])


def test_source_registered():
  src = data.get_source("synthetic", None, split="val", num_pairs=3, seed=1, size="48x64")
  assert len(src) == 3
  s = src[2]
  assert set(data.SAMPLE_KEYS) <= set(s)
  assert s["image0"].shape == (48, 64, 3) and s["image0"].dtype == np.uint8
  assert s["flow"].shape == (48, 64, 2) and s["flow"].dtype == np.float32
  for k in ("covisibility", "flow_valid", "covis_valid"):
    assert s[k].shape == (48, 64) and s[k].dtype == bool
  for k, shape in (("K0", (3, 3)), ("K1", (3, 3)), ("cam2world0", (4, 4)),
                   ("cam2world1", (4, 4)), ("depth0", (48, 64)), ("depth1", (48, 64))):
    assert s["meta"][k].shape == shape
  # The labels are those of the geometry code on the meta's cameras and depths (static pair).
  if not s["meta"]["moving_object"]:
    m = s["meta"]
    corr = geo.correspondence_from_depth(m["depth0"], m["K0"], m["cam2world0"], m["depth1"],
                                         m["K1"], m["cam2world1"], *geo.COVIS_THRESHOLDS["synthetic"])
    np.testing.assert_allclose(corr["flow"], s["flow"], atol=2e-3)
  bwd = src.backward(2)
  np.testing.assert_array_equal(bwd["image0"], s["image1"])
  f, b = src.both(2)
  np.testing.assert_array_equal(f["flow"], s["flow"])
  np.testing.assert_array_equal(b["flow"], bwd["flow"])
  with pytest.raises(IndexError):
    src[3]
  with pytest.raises(ValueError, match="split"):
    data.get_source("synthetic", None, split="nope")


def test_every_ray_hits_and_no_camera_inside_an_object():
  cfg = S.SyntheticConfig(size=(14, 14))
  for i in range(40):
    fwd, _ = S.generate_pair(S.pair_seed(11, "train", i), cfg)
    for k in ("depth0", "depth1"):
      d = fwd["meta"][k]
      assert np.isfinite(d).all() and d.min() > 0.2, (i, k, d.min())
    assert fwd["flow_valid"].any()


def _ray_cast_visibility(scene, sample):
  """Independent visibility oracle: cast a ray from camera 1 to every source pixel's 3D point (at
  time 1) and check that nothing is hit first."""
  m = sample["meta"]
  h, w = scene.size
  pts = geo.transform(m["cam2world0"], geo.unproject(m["depth0"].astype(np.float64), m["K0"]))
  for prim in scene.primitives:
    if prim.object_id == 1:  # the moving object: carry its points along
      M = prim.pose1 @ geo.invert_pose(prim.pose0)
      pts = np.where((m["segmentation0"] == 1)[..., None], geo.transform(M, pts), pts)
  c2w1 = scene.cam2world1
  pc = geo.transform(geo.invert_pose(c2w1), pts)
  uv, z = geo.project(pc, scene.K1)
  in_view = (z > 0) & geo.inside_image(uv, h, w)
  dirs = (pc / z[..., None]).reshape(-1, 3) @ c2w1[:3, :3].T
  first = np.full(h * w, np.inf)
  for prim in scene.primitives:
    first = np.minimum(first, S._intersect(prim, prim.pose1, c2w1[:3, 3], dirs))
  # The float32 depth in meta limits the agreement to ~1e-6 relative.
  return in_view & (np.abs(first.reshape(h, w) - z) < 1e-4 * np.abs(z)), in_view


def test_covisibility_agrees_with_ray_cast_visibility():
  cfg = S.SyntheticConfig(size=(64, 80))
  counts = np.zeros(4)  # false positives, false negatives (paper rule), fn (sub-pixel search), n
  for i in range(8):
    seed = S.pair_seed(21, "train", i)
    scene = S.make_scene(seed, cfg)
    fwd, _ = S.generate_pair(seed, cfg)
    visible, in_view = _ray_cast_visibility(scene, fwd)
    np.testing.assert_array_equal(fwd["covisibility"] & ~in_view, False)
    m = fwd["meta"]
    args = (m["depth0"], m["K0"], m["cam2world0"], m["depth1"], m["K1"], m["cam2world1"],
            *geo.COVIS_THRESHOLDS["synthetic"])
    if scene.moving:
      searched = geo.correspondence_from_rigid_objects(
          m["depth0"], m["K0"], m["cam2world0"], m["segmentation0"], S._object_poses(scene, 0),
          m["depth1"], m["K1"], m["cam2world1"], S._object_poses(scene, 1), *args[-2:],
          subpixel_search=0.5)
    else:
      searched = geo.correspondence_from_depth(*args, subpixel_search=0.5)
    c = fwd["covisibility"]
    counts += ((c & ~visible).sum(), (~c & visible).sum(),
               (~searched["covisibility"] & visible).sum(), c.size)
  fp, fn, fn_search = counts[:3] / counts[3]
  # Paper rule: only a thin band along silhouettes/creases (bilinear depth mixing) is lost.
  assert fp < 0.005 and fn < 0.04, (fp, fn)
  assert fn_search < fn / 2, (fn_search, fn)


def test_synthetic_config_supervises_out_of_view_pixels_as_not_covisible():
  """configs/synthetic.py's shift pairs are non-covisible only where the match leaves the view.
  The official rule drops those pixels from covis_valid (the covisibility head would see no
  negative); the config keeps them supervised, and the official default is unchanged."""
  from ufm_jax.training import config_lib
  from ufm_jax.data import pipeline
  for keep in (True, False):
    c = config_lib.load_config(str(pathlib.Path(__file__).resolve().parents[1] / "configs" /
                                   "synthetic.py"))
    c.input.augment = {"enabled": False, "supervise_out_of_view": keep}
    it, _ = pipeline.make_train_iterator(c.input, process_batch=c.input.batch_size)
    b = next(it)
    covis, valid = np.asarray(b["covisibility"], bool), np.asarray(b["covis_valid"], bool)
    assert 0.02 < 1 - covis.mean() < 0.9    # the shifts move some pixels out of view
    if keep:
      assert valid.all()
    else:
      np.testing.assert_array_equal(valid, covis)
