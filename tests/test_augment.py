"""The official augmentation (ufm_jax.data.augment): its random parameters against the official
code's over many draws, its image operations against their definitions, and labels consistent
with the augmented images and geometry."""

import collections
import dataclasses

import cv2
import numpy as np
import pytest
from PIL import Image, ImageEnhance

from ufm_jax import geometry
from ufm_jax.data import augment, get_source, official_ops

# No colour change at all: factors 1, hue 0, no grayscale / blur / low light / identical views.
NO_COLOR = dict(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0, grayscale_prob=0.0,
                blur_prob=0.0, identical_view_prob=0.0)


def _sigma_ok(count, n, p, k=4.5):
  return abs(count - n * p) <= k * np.sqrt(n * p * (1 - p)) + 1


# ------------------------------------------------------------------------- random parameters

def test_official_shapes_are_drawn_uniformly_per_batch():
  # configs/dataset/resolution_options/default.yaml: 560_many_non_square_ar, 560_many_ar,
  # 980_many_opticalflow_ar, as (W, H) there.
  assert augment.SHAPES_560 == ((420, 560), (364, 560), (308, 560), (280, 560), (168, 560))
  assert augment.SHAPES_560_SQUARE == ((560, 560),) + augment.SHAPES_560
  assert augment.SHAPES_980 == ((644, 980), (560, 980), (490, 980), (308, 980))
  n = 6000
  for shapes in (augment.SHAPES_560, augment.SHAPES_980):
    picks = collections.Counter(augment.shape_for_step(shapes, 3, s) for s in range(n))
    assert set(picks) == set(shapes)
    for shape in shapes:
      assert _sigma_ok(picks[shape], n, 1 / len(shapes)), picks
  assert augment.shape_for_step(augment.SHAPES_560, 3, 17) == \
      augment.shape_for_step(augment.SHAPES_560, 3, 17)


def test_training_shapes_from_aspect_ratios():
  assert augment.training_shapes(560) == ((182, 560), (280, 560), (308, 560), (420, 560),
                                          (560, 560))
  with pytest.raises(ValueError, match="multiple of the patch"):
    augment.training_shapes(500)
  with pytest.raises(ValueError, match="multiples of 14"):
    augment.check_shapes([(420, 561)])


@pytest.mark.parametrize("hw,out_h,zoom_max", [
    ((560, 746), 420, 1 + (560 * 140 // 420) / 560),   # S (S - R) // R = 186 > 0.1 S
    ((560, 746), 168, 1 + (560 * 392 // 168) / 560),   # a thin shape: up to 3.3x
    ((440, 560), 420, 1.1),                             # S < 1.1 R: the 10 % floor
])
def test_static_per_view_zoom_and_crop_placement(hw, out_h, zoom_max):
  """gen_random_crops: one zoom per view, log-uniform in [1, 1 + max(0.1 S, S (S-R) // R) / S];
  boxes of the crop's aspect placed uniformly on the zoomed image."""
  assert augment.static_zoom_range(hw, out_h) == pytest.approx(zoom_max)
  crop_hw = (out_h, 560)
  rng = np.random.default_rng(0)
  size = np.array([hw[1], hw[0]], float)
  full = np.array([crop_hw[1], crop_hw[0]], float) * min(size / [crop_hw[1], crop_hw[0]])
  zooms, place = [], []
  for _ in range(3000):
    boxes = augment.random_crop_boxes(hw, 4, crop_hw, zoom_max, rng)
    wh = boxes[:, 2:] - boxes[:, :2]
    zoom = full / wh
    np.testing.assert_allclose(zoom, zoom[0, 0], rtol=1e-9)   # one zoom for the 4 boxes, both axes
    zooms.append(zoom[0, 0])
    room = np.floor(size * zoom[0, 0]) - full               # placement range on the zoomed image
    place.append((boxes[:, :2] * zoom[0, 0] / np.maximum(room, 1e-9)).ravel())
    assert (boxes[:, :2] >= 0).all() and (boxes[:, 2:] <= size + 1e-9).all()
  t = np.log(zooms) / np.log(zoom_max)
  assert t.min() >= 0 and t.max() <= 1
  assert abs(t.mean() - 0.5) < 0.02 and abs(np.median(t) - 0.5) < 0.03   # log-uniform
  place = np.concatenate(place)
  place = place[np.isfinite(place)]
  assert place.min() >= 0 and place.max() <= 1 and abs(place.mean() - 0.5) < 0.02


def test_flow_expansion_and_shared_crop_offset():
  """Short side x U(1, 1.2) (int truncation), the same offset in both views from
  randint(0, range): the largest offset is never drawn."""
  rng = np.random.default_rng(1)
  cfg = augment.AugmentConfig()
  hw, out = (540, 960), (420, 560)
  ratios, tops, expect = [], [], []
  for _ in range(4000):
    c = augment.random_flow_crop(hw, out, rng, cfg)
    assert c.crop0 == c.crop1
    rh, rw = c.resized_hw
    ratios.append(rh / out[0])
    assert 0 <= c.crop0[0] < rh - out[0] or c.crop0[0] == 0 == rh - out[0]
    assert 0 <= c.crop0[1] < rw - out[1]
    if rh > out[0]:
      tops.append(c.crop0[0])
      expect.append((rh - out[0] - 1) / 2)   # uniform on 0 .. range - 1
  ratios = np.array(ratios)
  assert ratios.min() >= 1.0 - 1e-9 and ratios.max() <= 1.2 + 1e-9
  assert abs(ratios.mean() - 1.1) < 0.005 and np.percentile(ratios, 90) > 1.17
  assert abs(np.mean(tops) - np.mean(expect)) < 0.03 * np.mean(expect)
  # Without augmentation: ResizeShortAxis + CenterCrop.
  c = official_ops.center_flow_crop(hw, out)
  assert c.resized_hw == (420, 746) and c.crop0 == (0, (746 - 560) // 2)


def test_color_jitter_parameters():
  """ColorJitter(0.5, 0.5, 0.5, 0.1).get_params: factors U(0.5, 1.5), hue U(-0.1, 0.1), the four
  operations in a uniformly random order."""
  rng = np.random.default_rng(2)
  cfg = augment.AugmentConfig()
  draws = [augment.draw_color(rng, cfg) for _ in range(12000)]
  f = np.array([d[1:4] for d in draws])
  h = np.array([d[4] for d in draws])
  assert f.min() >= 0.5 and f.max() <= 1.5 and np.abs(f.mean(0) - 1).max() < 0.01
  assert h.min() >= -0.1 and h.max() <= 0.1 and abs(h.mean()) < 0.002
  assert abs(np.std(f[:, 0]) - 1 / np.sqrt(12)) < 0.01                 # uniform, not centred
  orders = collections.Counter(d[0] for d in draws)
  assert len(orders) == 24 and all(_sigma_ok(c, 12000, 1 / 24) for c in orders.values())


def test_grayscale_blur_low_light_rates(monkeypatch):
  """Per image: jitter always, grayscale 5 %, blur 5 % with sigma U(0.1, 1.0), low light 1 % only
  for the datasets that enable it (static ones grey the image first)."""
  calls = collections.Counter()
  sigmas = []
  monkeypatch.setattr(augment, "color_jitter",
                      lambda im, p, fast=False: calls.update(["jitter"]) or im)
  monkeypatch.setattr(augment, "grayscale", lambda im: calls.update(["grey"]) or im)
  monkeypatch.setattr(augment, "gaussian_blur",
                      lambda im, s, k: calls.update(["blur"]) or sigmas.append(s) or im)
  monkeypatch.setattr(augment, "low_light", lambda im, rng: calls.update(["low"]) or im)
  rng = np.random.default_rng(3)
  cfg = augment.AugmentConfig()
  img = np.zeros((2, 2, 3), np.uint8)
  n = 20000
  for _ in range(n):
    augment.photometric(img, rng, cfg, low_light_on=True, static=False)
  assert calls["jitter"] == n
  assert _sigma_ok(calls["grey"], n, 0.05) and _sigma_ok(calls["blur"], n, 0.05)
  assert _sigma_ok(calls["low"], n, 0.01)
  assert min(sigmas) >= 0.1 and max(sigmas) <= 1.0 and abs(np.mean(sigmas) - 0.55) < 0.03
  calls.clear()
  for _ in range(2000):
    augment.photometric(img, rng, cfg, low_light_on=False, static=True)
  assert calls["low"] == 0


def test_identical_view_rate(monkeypatch):
  """aug_monocular 0.005: the static pair becomes two copies of the first (augmented) view."""
  monkeypatch.setattr(augment, "static_crop_pair", lambda v0, v1, out_hw, rng, cfg: (v0, v1))
  monkeypatch.setattr(augment, "photometric", lambda im, *a, **k: im)
  same = []
  monkeypatch.setattr(augment, "static_labels",
                      lambda a, b, p: same.append(a.image is b.image) or ({}, {}))
  rng = np.random.default_rng(4)
  v0 = official_ops.StaticView(np.zeros((2, 2, 3), np.uint8), np.ones((2, 2)), np.eye(3), np.eye(4))
  v1 = official_ops.StaticView(np.ones((2, 2, 3), np.uint8), np.ones((2, 2)), np.eye(3), np.eye(4))
  n = 40000
  for _ in range(n):
    augment.static_pair(v0, v1, (0.1, 0.1, 0.005), (2, 2), rng, augment.AugmentConfig())
  assert _sigma_ok(sum(same), n, 0.005)


def test_config_keys():
  cfg = augment.AugmentConfig.from_dict({"no_crop_datasets": ["habitat", "x"],
                                         "expansion": [1, 1.1]})
  assert cfg.no_crop_datasets == ("habitat", "x") and cfg.expansion == (1.0, 1.1)
  with pytest.raises(KeyError, match="unknown input.augment keys.*zoom"):
    augment.AugmentConfig.from_dict({"zoom": (1, 2)})
  with pytest.raises(ValueError, match="expansion"):
    augment.AugmentConfig.from_dict({"expansion": (0.8, 1.2)})


# ------------------------------------------------------------------------- image operations

def test_color_jitter_is_torchvision_pil_path():
  """brightness / contrast / saturation / hue in the drawn order, as torchvision applies them to
  a PIL image (ImageEnhance and the HSV hue shift of its functional_pil.adjust_hue)."""
  rng = np.random.default_rng(5)
  img = rng.integers(0, 256, (23, 31, 3)).astype(np.uint8)
  for _ in range(20):
    params = augment.draw_color(rng, augment.AugmentConfig())
    order, b, c, s, h = params
    ref = Image.fromarray(img)
    for op in order:
      if op == 0:
        ref = ImageEnhance.Brightness(ref).enhance(b)
      elif op == 1:
        ref = ImageEnhance.Contrast(ref).enhance(c)
      elif op == 2:
        ref = ImageEnhance.Color(ref).enhance(s)
      else:
        hh, ss, vv = ref.convert("HSV").split()
        hue = (np.asarray(hh).astype(np.int64) + int(np.int32(h * 255))) % 256
        hh = Image.fromarray(hue.astype(np.uint8), "L")
        ref = Image.merge("HSV", (hh, ss, vv)).convert("RGB")
    np.testing.assert_array_equal(augment.color_jitter(img, params), np.asarray(ref))
    fast = augment.color_jitter(img, params, fast=True)   # OpenCV's HSV: rounding differs
    assert np.abs(fast.astype(int) - np.asarray(ref)).mean() < 3


def test_gaussian_blur_grayscale_low_light_definitions():
  rng = np.random.default_rng(6)
  img = rng.integers(0, 256, (12, 17, 3)).astype(np.uint8)
  sigma = 0.7
  x = np.arange(5) - 2.0
  k = np.exp(-0.5 * (x / sigma) ** 2)
  k /= k.sum()
  pad = np.pad(img.astype(np.float64), ((2, 2), (2, 2), (0, 0)), mode="reflect")
  ref = sum(k[i] * k[j] * pad[i:i + 12, j:j + 17] for i in range(5) for j in range(5))
  got = augment.gaussian_blur(img, sigma)
  assert np.abs(got.astype(float) - np.round(ref)).max() <= 1
  grey = augment.grayscale(img)
  np.testing.assert_array_equal(grey[..., 0], np.asarray(Image.fromarray(img).convert("L")))
  assert (grey == grey[..., :1]).all()
  dark = augment.low_light(img, rng)
  assert dark.dtype == np.uint8 and dark.mean() < 0.6 * img.mean()


def test_antialiased_resize_and_nearest_index_match_torch():
  torch = pytest.importorskip("torch")
  F = torch.nn.functional
  rng = np.random.default_rng(7)
  # downsampling (PIL), upsampling (OpenCV), identity, mixed (PIL)
  for (h, w), (oh, ow) in [((60, 100), (47, 78)), ((64, 64), (84, 84)), ((60, 100), (71, 121)),
                           ((56, 133), (56, 133)), ((60, 100), (66, 97))]:
    img = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
    t = torch.from_numpy(img).permute(2, 0, 1)[None].float()
    ref = F.interpolate(t, size=(oh, ow), mode="bilinear", align_corners=False,
                        antialias=True).to(torch.uint8)[0].permute(1, 2, 0).numpy()
    got = official_ops.resize_bilinear_aa(img, (oh, ow))
    err = np.abs(got.astype(int) - ref)
    assert err.max() <= 1 and (err > 0).mean() < 0.05, ((h, w), (oh, ow), (err > 0).mean())
    # A window: the same pixels up to float rounding of the source box (one grey level, rarely).
    window = official_ops.resize_bilinear_aa(img, (oh, ow), (3, 5, oh - 7, ow - 9))
    diff = np.abs(window.astype(int) - got[3:oh - 4, 5:ow - 4])
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01
    for n_in, n_out in ((h, oh), (w, ow), (30, 60), (30, 59)):
      ref = F.interpolate(torch.arange(n_in, dtype=torch.float32)[None, None], size=n_out,
                          mode="nearest")[0, 0].long().numpy()
      np.testing.assert_array_equal(official_ops.nearest_index(n_in, n_out), ref)


# ------------------------------------------------------------------- labels after the crop

def _static_scenes(n=3, size=(72, 96)):
  """Synthetic static scenes (ray cast, z-depth, K, cam2world): textured views consistent with
  their depth and cameras."""
  src = get_source("synthetic", None, split="val", num_pairs=n, size=size, pair_type="wide",
                   moving_object_prob=0.0)
  for i in range(n):
    s = src[i]
    m = s["meta"]
    yield [official_ops.StaticView(s[f"image{k}"], m[f"depth{k}"], m[f"K{k}"], m[f"cam2world{k}"])
           for k in (0, 1)]


def _warp_error(row):
  """|image1(x + flow) - image0(x)| on covisible pixels (bilinear lookup)."""
  h, w = row["flow"].shape[:2]
  y, x = np.mgrid[0:h, 0:w].astype(np.float32)
  warped = cv2.remap(row["image1"].astype(np.float32), x + row["flow"][..., 0],
                     y + row["flow"][..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
  m = row["covisibility"]
  assert m.mean() > 0.05, "too few covisible pixels to check"
  return np.abs(warped - row["image0"]).mean(-1)[m]


@pytest.mark.parametrize("pil_sampling", [False, True])
def test_static_pair_labels_agree_with_the_augmented_images(pil_sampling):
  """Cropped, zoomed and labelled after the crop: image1 warped by the flow shows image0 on the
  covisible pixels; off by a whole pixel it does not. The official half-pixel sampling
  (static_pil_sampling) costs some of that agreement, never most of it."""
  cfg = augment.AugmentConfig(**NO_COLOR, static_pil_sampling=pil_sampling, fast_image_ops=False)
  rng = np.random.default_rng(8)
  good, bad = [], []
  for v0, v1 in _static_scenes():
    for _ in range(3):
      for row in augment.static_pair(v0, v1, (0.1, 0.1, 0.005), (42, 56), rng, cfg):
        good.append(np.median(_warp_error(row)))
        bad.append(np.median(_warp_error(dict(row, flow=row["flow"] + np.float32([1, 0])))))
  assert np.median(good) < 0.5 * np.median(bad), (good, bad)
  if not pil_sampling:
    assert np.median(good) < 4.0, good


def test_static_labels_equal_labelling_the_cropped_geometry():
  """The rows' labels are those of the cropped geometry: for an unzoomed integer crop they equal
  the full-size labels shifted by the crop offsets wherever the match stays clear of the other
  crop's border, and a pixel whose full-size match leaves the other crop is never covisible."""
  rng = np.random.default_rng(9)
  params = (0.1, 0.1, 0.005)
  turned_off = 0   # pixels covisible at full size whose match leaves the other crop
  for v0, v1 in _static_scenes(2, (80, 100)):
    full = geometry.official_labels(v0.depth, v0.K, v0.cam2world, v1.depth, v1.K, v1.cam2world,
                                     params)
    for _ in range(3):
      (t0, l0), (t1, l1) = rng.integers(0, 20, (2, 2))
      box0 = (l0, t0, l0 + 72, t0 + 56)
      box1 = (l1, t1, l1 + 72, t1 + 56)
      c0 = augment.crop_view_affine(v0, box0, (56, 72), pil_sampling=False)
      c1 = augment.crop_view_affine(v1, box1, (56, 72), pil_sampling=False)
      np.testing.assert_array_equal(c0.depth, v0.depth[t0:t0 + 56, l0:l0 + 72])
      fwd, _ = augment.static_labels(c0, c1, params)
      flow = full["flow"][t0:t0 + 56, l0:l0 + 72] + np.float32([l0 - l1, t0 - t1])
      y, x = np.mgrid[0:56, 0:72]
      tx, ty = x + flow[..., 0], y + flow[..., 1]
      inside = (tx >= -0.5) & (tx < 71.5) & (ty >= -0.5) & (ty < 55.5)
      clear = (tx >= 1) & (tx < 70) & (ty >= 1) & (ty < 54)   # bilinear taps inside the crop
      fov = full["flow_valid"][t0:t0 + 56, l0:l0 + 72]
      np.testing.assert_array_equal(fwd["flow_valid"], fov & inside)
      ok = fov & inside
      np.testing.assert_allclose(fwd["flow"][ok], flow[ok], atol=1e-3)
      covis = full["covisibility"][t0:t0 + 56, l0:l0 + 72]
      np.testing.assert_array_equal(fwd["covisibility"][clear], covis[clear])
      assert not fwd["covisibility"][~inside].any()
      turned_off += int((covis & ~inside).sum())
  assert turned_off > 0          # the case above happened, not only crops that keep every match


def test_rotating_a_portrait_view_rotates_its_labels():
  """rotate_to_landscape turns image, depth, K and pose together: the labels of the turned view
  are the turned labels (u' = v, v' = W - 1 - u), its targets unchanged."""
  (v0, v1), = _static_scenes(1, (64, 48))
  params = (0.1, 0.1, 0.005)
  a = geometry.official_labels(v0.depth, v0.K, v0.cam2world, v1.depth, v1.K, v1.cam2world, params)
  r = official_ops.rotate_to_landscape(v0)
  assert r.depth.shape == (48, 64) and r.image.shape == (48, 64, 3)
  b = geometry.official_labels(r.depth, r.K, r.cam2world, v1.depth, v1.K, v1.cam2world, params)
  np.testing.assert_array_equal(b["covisibility"], np.rot90(a["covisibility"]))
  target_a = np.rot90(a["flow"] + np.stack(np.meshgrid(np.arange(48), np.arange(64)), -1))
  target_b = b["flow"] + np.stack(np.meshgrid(np.arange(64), np.arange(48)), -1)
  m = b["flow_valid"]
  np.testing.assert_allclose(target_b[m], target_a[m], atol=1e-3)
  # And the other way: labels INTO a turned view land on the turned pixel.
  c = geometry.official_labels(v1.depth, v1.K, v1.cam2world, r.depth, r.K, r.cam2world, params)
  d = geometry.official_labels(v1.depth, v1.K, v1.cam2world, v0.depth, v0.K, v0.cam2world, params)
  u, v = (d["flow"] + np.stack(np.meshgrid(np.arange(48), np.arange(64)), -1)).transpose(2, 0, 1)
  m = c["flow_valid"] & d["flow_valid"]
  turned = np.stack([v, 47 - u], -1) - np.stack(np.meshgrid(np.arange(48), np.arange(64)), -1)
  np.testing.assert_allclose(c["flow"][m], turned[m], atol=1e-3)


def test_static_crop_pair_keeps_the_pair_of_boxes_sharing_most_matches(monkeypatch):
  points = (np.array([[5, 5], [6, 5], [30, 20], [31, 21]]),
            np.array([[50, 5], [51, 5], [2, 2], [3, 3]]))
  monkeypatch.setattr(augment, "crop_correspondences", lambda v0, v1, n, rng: points)
  boxes = {0: np.array([[0, 0, 20, 15], [25, 15, 45, 30.]]),
           1: np.array([[0, 0, 20, 15], [40, 0, 60, 15.]])}
  calls = []
  monkeypatch.setattr(augment, "random_crop_boxes",
                      lambda hw, n, crop_hw, zoom, rng: calls.append(1) or boxes[len(calls) - 1])
  picked = []
  monkeypatch.setattr(augment, "crop_view_affine",
                      lambda v, box, crop_hw, *a: picked.append(tuple(box)) or v)
  v = official_ops.StaticView(np.zeros((40, 60, 3), np.uint8), np.ones((40, 60)), np.eye(3),
                              np.eye(4))
  augment.static_crop_pair(v, v, (14, 28), np.random.default_rng(0), augment.AugmentConfig())
  # Shared matches: (box0 0, box1 1) holds 2, (box0 1, box1 0) holds 2; ties go to the first.
  assert picked == [tuple(boxes[0][0]), tuple(boxes[1][1])]


def test_sampled_correspondences_are_reciprocal_matches():
  """The reciprocal matches are found by testing random pixels; each one found passes the
  official whole-image test."""
  (v0, v1), = _static_scenes(1, (60, 80))
  xy0, xy1 = augment.crop_correspondences(v0, v1, 200, np.random.default_rng(10))
  assert len(xy0) == len(xy1) == 200
  c12 = augment._project_pixels(v0, v1)
  c21 = augment._project_pixels(v1, v0)
  flat0 = xy0[:, 0] + 80 * xy0[:, 1]
  assert len(set(flat0.tolist())) == 200
  np.testing.assert_array_equal(c12[flat0], xy1[:, 0] + 80 * xy1[:, 1])
  np.testing.assert_array_equal(c21[c12[flat0]], flat0)


def _flow_pairs(n=3, size=(60, 84)):
  src = get_source("synthetic", None, split="val", num_pairs=n, size=size, pair_type="flow")
  for i in range(n):
    yield src.both(i)


def test_flow_pathway_cuts_matches_leaving_the_crop_and_stays_consistent():
  """Resized and cropped with the same offset: flow scaled, covisibility and the supervision
  mask AND-ed with "the match stays in the crop"; image1 warped by the flow shows image0."""
  cfg = augment.AugmentConfig(**NO_COLOR)
  rng = np.random.default_rng(11)
  good, bad = [], []
  for fwd, bwd in _flow_pairs():
    for _ in range(3):
      for row in augment.flow_pair(fwd, bwd, (42, 56), rng, cfg):
        h, w = row["flow"].shape[:2]
        x = np.arange(w) + row["flow"][..., 0]
        y = np.arange(h)[:, None] + row["flow"][..., 1]
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        assert not (row["covisibility"] & ~inside).any()
        assert not (row["covis_valid"] & ~inside).any()
        good.append(np.median(_warp_error(row)))
        bad.append(np.median(_warp_error(dict(row, flow=row["flow"] + np.float32([1, 0])))))
  assert np.median(good) < 0.5 * np.median(bad), (good, bad)


def test_flow_pathway_labels_on_the_read_grid_equal_full_labels():
  """Labels given only at the stored pixels the crop reads (the pipeline's lazily labelled posed
  sources) give the same rows, bit for bit."""
  cfg = augment.AugmentConfig()
  for fwd, bwd in _flow_pairs(2):
    hw = fwd["image0"].shape[:2]
    for seed in range(3):
      crop = augment.flow_crop(hw, (28, 42), np.random.default_rng(seed), cfg)
      grids = [tuple(np.unique(g) for g in crop.source_grid(k)) for k in (0, 1)]
      on_grid = [dict(s, **{k: np.asarray(s[k])[np.ix_(*g)] for k in augment.LABEL_KEYS})
                 for s, g in ((fwd, grids[0]), (bwd, grids[1]))]
      full = augment.flow_pair_with_crop(fwd, bwd, crop, np.random.default_rng(0), cfg)
      lazy = augment.flow_pair_with_crop(*on_grid, crop, np.random.default_rng(0), cfg,
                                         grid=grids)
      for a, b in zip(full, lazy):
        for k in a:
          np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("quirk", [True, False])
def test_kubric_crops_maximise_the_official_score(quirk):
  """CovisibleGuidedCropManipulation: the pair of candidates with the best 2ab / (a + b) of the
  sampled covisible matches kept forward (a) and backward (b); officially b is read with the two
  candidate indices swapped (kubric_score_quirk)."""
  cfg = augment.AugmentConfig(kubric_score_quirk=quirk)
  (fwd, bwd), = _flow_pairs(1, (60, 84))
  out = (28, 42)
  for seed in range(4):
    crop = augment.covisible_guided_crops(fwd, bwd, (60, 84), out, np.random.default_rng(seed), cfg)
    # Replay the draws: expansion, the two samples, then the candidates of view 0 and view 1.
    rng = np.random.default_rng(seed)
    e = rng.uniform(*cfg.expansion)
    rh, rw = official_ops.resize_short_axis_size((60, 84), (int(out[0] * e), int(out[1] * e)))
    assert crop.resized_hw == (rh, rw)
    ri, ci = official_ops.nearest_index(60, rh), official_ops.nearest_index(84, rw)
    matches = []
    for lab in (fwd, bwd):
      covis = lab["covisibility"][np.ix_(ri, ci)]
      flat = np.flatnonzero(covis)
      flat = flat[rng.random(len(flat)) < 2048 / (len(flat) + 1e-8)]
      yy, xx = np.divmod(flat, rw)
      f = lab["flow"][ri[yy], ci[xx]] * np.float32([rw / 84, rh / 60])
      matches.append((xx, yy, xx + np.rint(f[:, 0]), yy + np.rint(f[:, 1])))
    draw = lambda n, o: rng.integers(0, n - o, 10) if n > o else np.zeros(10, np.int64)
    cands = [(draw(rh, out[0]), draw(rw, out[1])) for _ in (0, 1)]
    assert crop.crop0 in list(zip(*cands[0])) and crop.crop1 in list(zip(*cands[1]))

    def kept(m, own, other, i, j):
      (x, y, tx, ty), (t0, l0), (t1, l1) = m, (cands[own][0][i], cands[own][1][i]), \
          (cands[other][0][j], cands[other][1][j])
      return np.sum((l0 <= x) & (x < l0 + out[1]) & (t0 <= y) & (y < t0 + out[0])
                    & (l1 <= tx) & (tx < l1 + out[1]) & (t1 <= ty) & (ty < t1 + out[0]))

    a = np.array([[kept(matches[0], 0, 1, i, j) for j in range(10)] for i in range(10)], float)
    b = np.array([[kept(matches[1], 1, 0, i, j) for j in range(10)] for i in range(10)], float)
    if not quirk:
      b = b.T
    score = 2 * a * b / (a + b + 1e-8)
    i, j = np.unravel_index(np.argmax(score), score.shape)
    assert (crop.crop0, crop.crop1) == ((cands[0][0][i], cands[0][1][i]),
                                        (cands[1][0][j], cands[1][1][j]))


def test_kubric_pathway_independent_crops_stay_consistent():
  cfg = augment.AugmentConfig(**NO_COLOR)
  rng = np.random.default_rng(12)
  good, bad = [], []
  for fwd, bwd in _flow_pairs(3, (60, 84)):
    for _ in range(3):
      rows = augment.kubric_pair(fwd, bwd, (42, 56), rng, cfg)
      np.testing.assert_array_equal(rows[0]["image0"], rows[1]["image1"])
      for row in rows:
        good.append(np.median(_warp_error(row)))
        bad.append(np.median(_warp_error(dict(row, flow=row["flow"] + np.float32([1, 0])))))
  assert np.median(good) < 0.5 * np.median(bad), (good, bad)


def test_no_crop_static_views_are_resized_to_cover_and_centre_cropped():
  """Habitat at 560 (no_crop_datasets) and the no-augmentation path: Lanczos to cover, centre
  crop through the intrinsics; a portrait view is turned to landscape."""
  (v0, v1), = _static_scenes(1, (72, 96))
  out = official_ops.resize_cover_center_crop(v0, (28, 42))
  # Cover: scale max(42 / 96, 28 / 72) -> 42 x 31, crop rows round(1.5) = 2 (half to even).
  scale = max(42 / 96, 28 / 72) + 1e-8
  assert out.image.shape == (28, 42, 3)
  np.testing.assert_allclose(out.K[0, 0], v0.K[0, 0] * scale, rtol=1e-6)
  np.testing.assert_allclose(out.K[1, 2], (v0.K[1, 2] + 0.5) * scale - 0.5 * (72 * scale - 31)
                             - 0.5 - 2, rtol=1e-6)
  portrait = dataclasses.replace(v0, image=np.ascontiguousarray(v0.image[:, :40]),
                                 depth=np.ascontiguousarray(v0.depth[:, :40]))
  turned = official_ops.resize_cover_center_crop(portrait, (28, 42))
  assert turned.image.shape == (28, 42, 3)


def test_float_hue_step_is_mod_one_on_the_hue_plane():
  """Kubric's float jitter takes the hue mod 1 as x - floor(x) on the contiguous hue plane:
  equal to the strided np.mod formulation for every hue factor, negative sums included."""
  rng = np.random.default_rng(7)
  img = rng.integers(0, 256, (31, 45, 3)).astype(np.uint8)
  img[:4] = 0
  img[4:8] = 255
  x = np.clip(img.astype(np.float32) / np.float32(255), 0, 1)
  for h in (-0.1, -0.0999, -1e-7, 0.0, 1e-7, 0.05, 0.0999, 0.1):
    hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
    hue = hsv[..., 0]
    hue *= np.float32(1 / 360)
    hue += np.float32(h)
    np.mod(hue, 1, out=hue)
    hue *= np.float32(360)
    want = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    np.clip(want, 0, 1, out=want)
    want = (want * np.float32(255)).astype(np.uint8)
    np.testing.assert_array_equal(augment.color_jitter_float(img, ((3,), 1.0, 1.0, 1.0, h)),
                                  want, err_msg=str(h))
  vals = np.float32(rng.uniform(-1.5, 1.5, 100000))
  vals[:3] = (-0.0, -1.0, np.nextafter(np.float32(-1), np.float32(0)))
  np.testing.assert_array_equal(vals - np.floor(vals), np.mod(vals, 1))


def test_kubric_float_jitter_is_torchvisions_tensor_path():
  """Kubric's jitter (on the float image, kubric4d.py:171-178) against a hand copy of
  torchvision's tensor formulas run in torch (`color_reference.torchvision_tensor_jitter`;
  torchvision itself is not installed): brightness, contrast and saturation exact; the hue
  through OpenCV's float HSV within one grey level on at most 0.2% of the values (measured at
  most 0.021% of the pixels in these draws; benchmarks/kubric_hue.py, docs/host_input.md)."""
  pytest.importorskip("torch")
  from ufm_jax.testing import color_reference
  rng = np.random.default_rng(8)
  img = cv2.GaussianBlur(rng.integers(0, 256, (60, 80, 3)).astype(np.uint8), (0, 0), 1.5)
  cfg = augment.AugmentConfig()
  for k in range(10):
    params = augment.draw_color(rng, cfg)
    if k < 3:
      params = ((k,),) + params[1:]
    d = np.abs(augment.color_jitter_float(img, params).astype(int)
               - color_reference.torchvision_tensor_jitter(img, params))
    if 3 not in params[0]:
      assert d.max() == 0, params
    assert d.max() <= 1 and (d > 0).mean() <= 0.002, (params, d.max(), (d > 0).mean())


def test_static_crop_warp_is_pils_bicubic_transform():
  """The static crop's image: the bytes of PIL's bicubic `Image.transform` (the official warp),
  computed by data/pil_warp.py, for zooms in and out, integer positions, crops reaching past the
  image (filled with 0), flat patches (exact integers) and PIL's half-pixel frame or not."""
  from ufm_jax.data import pil_warp
  rng = np.random.default_rng(12)
  img = cv2.GaussianBlur(rng.integers(0, 256, (70, 90, 3)).astype(np.uint8), (0, 0), 1.2)
  img[10:30, 20:50] = 77
  img[40:50] = 255
  for trial in range(40):
    a0, a4 = rng.uniform(0.25, 2.5, 2)
    a2, a5 = rng.uniform(-20, 60), rng.uniform(-20, 40)
    if trial % 4 == 0:
      a0, a2 = 1.0, float(rng.integers(-3, 30))     # integer positions: fraction 0
    if trial % 5 == 0:
      a4, a5 = 0.5, 0.25
    data = (a0, 0.0, a2, 0.0, a4, a5, 0.0, 0.0)
    size = (int(rng.integers(20, 80)), int(rng.integers(14, 60)))
    want = np.asarray(Image.fromarray(img).transform(size, Image.PERSPECTIVE, data,
                                                     resample=Image.BICUBIC))
    np.testing.assert_array_equal(pil_warp.bicubic_transform(img, data, size), want,
                                  err_msg=str((data, size)))
  with pytest.raises(ValueError, match="not a scale"):
    pil_warp.bicubic_transform(img, (1.0, 0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), (10, 10))
  # Through the static crop, with PIL's frame and without: the same bytes as PIL's own call.
  v = augment.StaticView(img, np.ones(img.shape[:2], np.float32),
                         np.array([[60.0, 0, 45], [0, 60.0, 35], [0, 0, 1]]), np.eye(4))
  calls = []
  pil = lambda im, data, size: calls.append(data) or np.asarray(  # noqa: E731
      Image.fromarray(im).transform(size, Image.PERSPECTIVE, data, resample=Image.BICUBIC))
  for pil_sampling in (True, False):
    for box in ((5.3, 4.1, 61.7, 46.9), (-8.0, -3.0, 100.0, 80.0), (20.0, 10.0, 40.0, 25.0)):
      got = augment.crop_view_affine(v, box, (42, 56), pil_sampling).image
      with pytest.MonkeyPatch.context() as m:
        m.setattr(pil_warp, "bicubic_transform", pil)
        want = augment.crop_view_affine(v, box, (42, 56), pil_sampling).image
      np.testing.assert_array_equal(got, want, err_msg=str((box, pil_sampling)))
  assert len(calls) == 6   # every crop took the scale + shift path
