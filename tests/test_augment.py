"""Augmentation keeps labels consistent with the pixels (analytic pairs with known flow)."""

import cv2
import numpy as np
import pytest

from ufm_jax.data import augment


def _texture(x, y):
  """Smooth RGB texture (wavelengths >= ~25 px, so bilinear sampling error stays small)."""
  chans = [127.5 + 55 * np.sin(0.21 * x + 0.13 * y + p) + 45 * np.cos(0.17 * y - 0.09 * x + 2 * p)
           for p in (0.0, 1.3, 2.6)]
  return np.clip(np.stack(chans, -1), 0, 255)


def _affine_pair(hw0=(60, 90), hw1=(70, 104)):
  """image1(A x) = image0(x) for a similarity A; flow = A x - x; covisible where A x is inside image1."""
  h0, w0 = hw0
  h1, w1 = hw1
  ang, s, t = 0.08, 1.1, np.array([6.0, -3.0])
  a = s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
  y, x = np.mgrid[0:h0, 0:w0].astype(np.float64)
  image0 = _texture(x, y).round().astype(np.uint8)
  tx = a[0, 0] * x + a[0, 1] * y + t[0]
  ty = a[1, 0] * x + a[1, 1] * y + t[1]
  flow = np.stack([tx - x, ty - y], -1).astype(np.float32)
  # image1 at pixel q shows the texture at A^-1 q.
  yq, xq = np.mgrid[0:h1, 0:w1].astype(np.float64)
  ainv = np.linalg.inv(a)
  sx = ainv[0, 0] * (xq - t[0]) + ainv[0, 1] * (yq - t[1])
  sy = ainv[1, 0] * (xq - t[0]) + ainv[1, 1] * (yq - t[1])
  image1 = _texture(sx, sy).round().astype(np.uint8)
  inside = (tx >= 0) & (tx <= w1 - 1) & (ty >= 0) & (ty <= h1 - 1)
  return {"image0": image0, "image1": image1, "flow": flow, "covisibility": inside,
          "flow_valid": np.ones((h0, w0), bool), "covis_valid": np.ones((h0, w0), bool), "meta": {}}


def _bilinear(img, x, y):
  return cv2.remap(img.astype(np.float32), x.astype(np.float32), y.astype(np.float32),
                   cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _photo_error(out, min_frac=0.3):
  """Mean |image1(x + flow) - image0(x)| over covisible, valid pixels whose target is inside."""
  h, w = out["flow"].shape[:2]
  y, x = np.mgrid[0:h, 0:w].astype(np.float32)
  tx, ty = x + out["flow"][..., 0], y + out["flow"][..., 1]
  warped = _bilinear(out["image1"], tx, ty)
  m = (out["covisibility"] & out["flow_valid"] & (tx >= 0) & (tx <= w - 1) & (ty >= 0)
       & (ty <= h - 1))
  assert m.mean() > min_frac, "too few checkable pixels; test setup broken"
  err = np.abs(warped - out["image0"].astype(np.float32))[m]
  return err.mean(), np.percentile(err, 99)


@pytest.mark.parametrize("hflip", [0.0, 1.0])
@pytest.mark.parametrize("out_hw", [(28, 84), (42, 56), (56, 56)])
def test_warp_by_flow_reproduces_source(out_hw, hflip):
  sample = _affine_pair()
  cfg = augment.AugmentConfig(zoom=(1.0, 1.6), view_scale_jitter=0.15, crop_shift=0.1,
                              hflip_prob=hflip, color_prob=0.0)
  for seed in range(4):
    out, = augment.augment(sample, np.random.default_rng(seed), out_hw, cfg)
    assert out["image0"].shape == out_hw + (3,) and out["flow"].shape == out_hw + (2,)
    mean, p99 = _photo_error(out)
    assert mean < 2.0 and p99 < 8.0, (seed, mean, p99)


def test_photo_error_detects_wrong_flow():
  """The consistency check above can fail: a flow 10% too short is caught."""
  sample = _affine_pair()
  p = augment.Params(augment.View(0.9, 0.9, 3, 2, (54, 81)), augment.View(1.2, 1.2, 10, 9, (84, 125)),
                     False, None, None)
  out, = augment.apply(sample, p, (42, 56))
  assert _photo_error(out)[0] < 2.0
  h, w = out["flow"].shape[:2]
  bad = dict(out, flow=out["flow"] * 0.9)
  assert _photo_error(bad)[0] > 4.0


def test_constant_flow_hand_computed():
  """Both views 2x, crops (4, 2) and (6, 1): u' = 2*3 + (4 - 6) = 4, v' = 2*(-2) + (2 - 1) = -3."""
  h, w = 20, 30
  sample = {"image0": np.zeros((h, w, 3), np.uint8), "image1": np.zeros((h, w, 3), np.uint8),
            "flow": np.tile(np.float32([3, -2]), (h, w, 1)), "covisibility": np.ones((h, w), bool),
            "flow_valid": np.ones((h, w), bool), "covis_valid": np.ones((h, w), bool)}
  p = augment.Params(augment.View(2.0, 2.0, 4, 2, (40, 60)), augment.View(2.0, 2.0, 6, 1, (40, 60)),
                     False, None, None)
  out, = augment.apply(sample, p, (14, 28))
  np.testing.assert_allclose(out["flow"][..., 0], 4.0, atol=1e-5)
  np.testing.assert_allclose(out["flow"][..., 1], -3.0, atol=1e-5)
  p = augment.Params(p.view0, p.view1, True, None, None)
  out, = augment.apply(sample, p, (14, 28))
  np.testing.assert_allclose(out["flow"][..., 0], -4.0, atol=1e-5)


def test_masks_nearest_and_invalid_flow_not_blended():
  h, w = 30, 40
  y, x = np.mgrid[0:h, 0:w]
  flow = np.zeros((h, w, 2), np.float32)
  flow_valid = x != 17
  flow[~flow_valid] = np.nan   # garbage where invalid must never leak
  sample = {"image0": np.zeros((h, w, 3), np.uint8), "image1": np.zeros((h, w, 3), np.uint8),
            "flow": flow, "covisibility": x < 20, "flow_valid": flow_valid,
            "covis_valid": y >= 10}
  v = augment.View(1.5, 1.5, 5, 4, (45, 60))
  out, = augment.apply(sample, augment.Params(v, v, False, None, None), (28, 42))
  assert np.isfinite(out["flow"]).all()
  xo = (np.arange(42) + 5 + 0.5) / 1.5 - 0.5   # original x of each output column
  yo = (np.arange(28) + 4 + 0.5) / 1.5 - 0.5
  np.testing.assert_array_equal(out["covisibility"][0], np.round(xo) < 20)
  np.testing.assert_array_equal(out["covis_valid"][:, 0], np.round(yo) >= 10)
  # Flow valid only where both bilinear neighbours in x avoid column 17.
  expect = (np.floor(xo) != 17) & (np.ceil(xo) != 17)  # ceil == floor when exact
  np.testing.assert_array_equal(out["flow_valid"][0], expect)


def test_symmetric_output_swaps_images_and_uses_reverse_labels():
  fwd = _affine_pair(hw0=(60, 90), hw1=(60, 90))
  # Reverse of a similarity pair: image0 <-> image1, flow from the inverse map (analytic).
  rev = _affine_pair(hw0=(60, 90), hw1=(60, 90))
  h, w = 60, 90
  y, x = np.mgrid[0:h, 0:w].astype(np.float64)
  ang, s, t = 0.08, 1.1, np.array([6.0, -3.0])
  a = s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
  ainv = np.linalg.inv(a)
  sx = ainv[0, 0] * (x - t[0]) + ainv[0, 1] * (y - t[1])
  sy = ainv[1, 0] * (x - t[0]) + ainv[1, 1] * (y - t[1])
  rev = {"image0": fwd["image1"], "image1": fwd["image0"],
         "flow": np.stack([sx - x, sy - y], -1).astype(np.float32),
         "covisibility": (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1),
         "flow_valid": np.ones((h, w), bool), "covis_valid": np.ones((h, w), bool)}
  cfg = augment.AugmentConfig(view_scale_jitter=0.1, hflip_prob=0.5, asymmetric_color_prob=1.0)
  f, b = augment.augment(fwd, np.random.default_rng(3), (42, 70), cfg, backward=rev)
  np.testing.assert_array_equal(f["image0"], b["image1"])
  np.testing.assert_array_equal(f["image1"], b["image0"])
  cfg_nocolor = dataclasses_replace(cfg, color_prob=0.0)
  f, b = augment.augment(fwd, np.random.default_rng(3), (42, 70), cfg_nocolor, backward=rev)
  assert _photo_error(f)[0] < 2.0 and _photo_error(b)[0] < 2.0


def dataclasses_replace(cfg, **kw):
  import dataclasses
  return dataclasses.replace(cfg, **kw)


def test_color_jitter_touches_images_only():
  sample = _affine_pair()
  p = augment.sample_params(np.random.default_rng(0), (60, 90), (70, 104), (28, 56),
                            augment.AugmentConfig(color_prob=1.0))
  plain = augment.Params(p.view0, p.view1, p.hflip, None, None)
  a, = augment.apply(sample, p, (28, 56))
  b, = augment.apply(sample, plain, (28, 56))
  for k in augment.LABEL_KEYS:
    np.testing.assert_array_equal(a[k], b[k])
  assert np.abs(a["image0"].astype(int) - b["image0"]).mean() > 1


def test_training_shapes():
  assert augment.training_shapes(560) == ((182, 560), (280, 560), (308, 560), (420, 560), (560, 560))
  for h, w in augment.training_shapes(980):
    assert w == 980 and h % 14 == 0 and 980 / 3 - 14 <= h <= 980
  shapes = augment.training_shapes(560)
  picks = [augment.shape_for_step(shapes, 0, s) for s in range(200)]
  assert picks == [augment.shape_for_step(shapes, 0, s) for s in range(200)]
  assert set(picks) == set(shapes)
  with pytest.raises(ValueError, match="multiple of the patch"):
    augment.training_shapes(500)


def test_synthetic_pairs_stay_consistent_after_augmentation():
  """On rendered synthetic pairs (both directions) the augmented flow still warps image1 onto image0:
  the error is interpolation-sized and far below that of a flow off by 2 px."""
  from ufm_jax.data import get_source
  src = get_source("synthetic", None, split="val", num_pairs=6, size=(56, 84))
  cfg = augment.AugmentConfig(view_scale_jitter=0.1, hflip_prob=0.5, color_prob=0.0)
  good, bad = [], []
  for i in range(6):
    fwd, bwd = src.both(i)
    for out in augment.augment(fwd, np.random.default_rng(i), (42, 84), cfg, backward=bwd):
      good.append(_photo_error(out, 0.1)[0])
      bad.append(_photo_error(dict(out, flow=out["flow"] + np.float32([2, 0])), 0.1)[0])
  assert np.median(good) < 4.0 and np.mean(good) < 0.4 * np.mean(bad), (good, bad)


def test_color_jitter_matches_sequential_definition():
  """One fused blend == brightness, then contrast around the mean grey, then saturation around each
  pixel's grey (torchvision order), computed step by step in float here."""
  rng = np.random.default_rng(0)
  img = rng.integers(0, 256, (20, 30, 3)).astype(np.uint8)
  w = np.array([0.299, 0.587, 0.114])
  for b, c, s in [(1.2, 0.8, 1.1), (0.85, 1.15, 0.8), (1.0, 1.0, 0.0)]:
    x = img.astype(np.float64) * b
    m = (x @ w).mean()
    x = (x - m) * c + m
    g = x @ w
    x = (x - g[..., None]) * s + g[..., None]
    want = np.clip(np.round(x), 0, 255)
    got = augment.color_jitter(img, (b, c, s, 0.0)).astype(np.float64)
    assert np.abs(got - want).max() <= 2.0, (b, c, s)


@pytest.mark.parametrize("out_hw", [(28, 84), (42, 56), (84, 112)])
def test_labels_on_the_label_grid_give_the_full_labels_output(out_hw):
  """warp_labels reads only label_grid's pixels: labels given on that grid alone (the pipeline's
  lazy posed pairs) produce the same output, bit for bit, also around NaN and invalid taps."""
  rng = np.random.default_rng(1)
  sample = _affine_pair()
  sample["flow"][10:14, 20:25] = np.nan
  sample["flow_valid"] = rng.uniform(size=sample["flow_valid"].shape) > 0.1
  sample["covis_valid"] = rng.uniform(size=sample["flow_valid"].shape) > 0.2
  cfg = augment.AugmentConfig(zoom=(0.6, 1.4), view_scale_jitter=0.2, crop_shift=0.1)
  hw = sample["flow"].shape[:2]
  for _ in range(10):
    params = augment.sample_params(rng, hw, sample["image1"].shape[:2], out_hw, cfg)
    grid = augment.label_grid(params.view0, hw, out_hw)
    assert len(grid.rows) * len(grid.cols) < hw[0] * hw[1]
    on_grid = {k: sample[k][np.ix_(grid.rows, grid.cols)] for k in augment.LABEL_KEYS}
    full = augment.warp_labels(sample, params.view0, params.view1, out_hw)
    lazy = augment.warp_labels(on_grid, params.view0, params.view1, out_hw, grid)
    for k in augment.LABEL_KEYS:
      assert np.array_equal(np.ascontiguousarray(full[k]).view(np.uint8),
                            np.ascontiguousarray(lazy[k]).view(np.uint8)), k
