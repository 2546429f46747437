"""The teacher's outputs warped into the student's crop (ufm_jax.training.distill.warp_to_crop) agree with
the crop's own labels, the way the label-consistency tests check the pipeline's rows
(tests/test_augment.py, tests/test_pipeline_label_grid.py): a stand-in teacher that predicts the
true flow of the un-augmented pair gives the labels the flow pathway makes for the same crop, at
any teacher resolution and for crops that differ between the views; the warped flow carries
image1's crop onto image0's; the maps follow the images' own resize and crop; covariances turn
with the map."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.training import distill
from ufm_jax.models import sampling
from ufm_jax.data import augment, distill_rows, get_source, official_ops, pipeline
from ufm_jax.data.official_ops import FlowCrop

NO_COLOR = dict(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0, grayscale_prob=0.0,
                blur_prob=0.0, identical_view_prob=0.0)


def _teacher_outputs(samples, teacher_hw):
  """A stand-in teacher at `teacher_hw` that predicts the true labels of constant-flow pairs
  (flow scaled to its pixels; covisibility resized by nearest neighbour)."""
  flows, covis = [], []
  for s in samples:
    h, w = s["flow"].shape[:2]
    f = s["flow"][0, 0] * np.float32([teacher_hw[1] / w, teacher_hw[0] / h])
    assert np.all(s["flow"] == s["flow"][0, 0])   # constant: resampling it is exact
    flows.append(np.broadcast_to(f, tuple(teacher_hw) + (2,)))
    covis.append(cv2.resize(s["covisibility"].astype(np.float32), teacher_hw[::-1],
                            interpolation=cv2.INTER_NEAREST))
  return {"flow": jnp.asarray(np.stack(flows)), "covisibility": jnp.asarray(np.stack(covis))}


def _warp(rows, outputs, interpolation="bilinear"):
  m0 = jnp.asarray(np.stack([r["teacher_to_crop0"] for r in rows]))
  m1 = jnp.asarray(np.stack([r["teacher_to_crop1"] for r in rows]))
  out = distill.warp_to_crop(outputs, m0, m1, rows[0]["image0"].shape[:2], interpolation)
  return {k: np.asarray(v) for k, v in out.items()}


def _distill_rows(sample, backward, teacher_hw, seed, out_hw=(42, 56), cfg=None):
  """The rows DistillPair makes of one pair, with the crop's labels (keep_labels)."""
  cfg = cfg or augment.AugmentConfig(**NO_COLOR)
  pair = distill_rows.DistillPair.__new__(distill_rows.DistillPair)
  pair.cfg, pair.symmetrize, pair.teacher_hw, pair.keep_labels = cfg, True, teacher_hw, True
  pair.names = ("synthetic",)
  pair._load = lambda d, i: (sample, backward)   # noqa: SLF001 - the source's labelled sample
  return pair._augmented(0, 0, out_hw, np.random.default_rng(seed))


def _shift_pairs(n, size=(56, 72)):
  src = get_source("synthetic", None, split="val", num_pairs=n, size=size, pair_type="shift",
                   max_shift=10)
  return [src.both(i) for i in range(n)]


@pytest.mark.parametrize("teacher_hw", [(56, 72), (112, 140), (28, 42)])
def test_warped_true_flow_equals_the_crop_labels(teacher_hw):
  """Both rows of symmetrized pairs, the teacher at the stored size, larger, and smaller with
  another aspect ratio: the warped flow is the crop's label flow; the match stays in the crop
  exactly where the label says covisible (the pairs leave the view only by their shift)."""
  agree, total = 0, 0
  for k, (fwd, bwd) in enumerate(_shift_pairs(4)):
    for seed in range(3):
      rows = _distill_rows(fwd, bwd, teacher_hw, seed=10 * k + seed)
      assert len(rows) == 2
      got = _warp(rows, _teacher_outputs([fwd, bwd], teacher_hw))
      for r, row in enumerate(rows):
        np.testing.assert_allclose(got["teacher_flow"][r], row["flow"], atol=2e-4)
        assert got["teacher_in_view"][r].all()
        covis = got["teacher_covisibility"][r] > 0.5
        np.testing.assert_array_equal(covis, covis & got["teacher_in_crop"][r])
        agree += np.count_nonzero(covis == row["covisibility"])
        total += covis.size
  # Nearest-neighbour covisibility at another resolution moves its edge by up to a pixel.
  assert agree / total > 0.97, agree / total


def test_views_cropped_apart_warp_like_the_labels():
  """Independent crops of the two views (as Kubric's): the label rule shifts the flow by the
  offset difference; so does the warp."""
  for fwd, bwd in _shift_pairs(3, (60, 84)):
    crop = FlowCrop((60, 84), (66, 92), (42, 56), (3, 11), (17, 30))
    labels = official_ops.flow_crop_labels(fwd, crop, 0, "in_crop")
    rows = [{"image0": np.zeros((42, 56, 3), np.uint8),
             "teacher_to_crop0": distill_rows.crop_map(crop.resized_hw, crop.crop0, (60, 84)),
             "teacher_to_crop1": distill_rows.crop_map(crop.resized_hw, crop.crop1, (60, 84))}]
    got = _warp(rows, _teacher_outputs([fwd], (60, 84)))
    np.testing.assert_allclose(got["teacher_flow"][0], labels["flow"], atol=2e-4)
    inside = official_ops.in_frame(got["teacher_flow"][0])
    np.testing.assert_array_equal(got["teacher_in_crop"][0], inside)


def _warp_error(image0, image1, flow, mask):
  h, w = flow.shape[:2]
  yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
  warped = cv2.remap(image1.astype(np.float32), xx + flow[..., 0], yy + flow[..., 1],
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
  return np.median(np.abs(warped - image0.astype(np.float32)).mean(-1)[mask])


def test_warped_flow_carries_the_target_crop_onto_the_source_crop():
  """Scene pairs with varying flow, the teacher predicting their true flow and covisibility:
  image1's crop warped by the teacher's flow shows image0's crop, clearly better than with the
  flow one pixel off (the label-consistency test of tests/test_augment.py)."""
  src = get_source("synthetic", None, split="val", num_pairs=4, size=(60, 84), pair_type="flow")
  good, bad, labels = [], [], []
  for i in range(4):
    fwd, bwd = src.both(i)
    rows = _distill_rows(fwd, bwd, (60, 84), seed=i)
    outputs = {"flow": jnp.asarray(np.stack([fwd["flow"], bwd["flow"]])),
               "covisibility": jnp.asarray(np.stack([fwd["covisibility"], bwd["covisibility"]])
                                           .astype(np.float32))}
    got = _warp(rows, outputs)
    for r, row in enumerate(rows):
      mask = (got["teacher_covisibility"][r] > 0.5) & got["teacher_in_crop"][r]
      assert mask.mean() > 0.3
      flow = got["teacher_flow"][r]
      good.append(_warp_error(row["image0"], row["image1"], flow, mask))
      bad.append(_warp_error(row["image0"], row["image1"], flow + np.float32([1, 0]), mask))
      # The labels' flow, read at the nearest stored pixel, is a fraction of a pixel off
      # where the flow varies; the warp reads the teacher where the crop pixel lies.
      both = mask & row["covisibility"] & row["flow_valid"]
      assert np.median(np.linalg.norm(flow - row["flow"], axis=-1)[both]) < 0.3
      labels.append(_warp_error(row["image0"], row["image1"], row["flow"], both))
  print("warp error: teacher", np.median(good), "labels", np.median(labels), "1 px off",
        np.median(bad))
  assert np.median(good) < 0.5 * np.median(bad), (good, bad)
  assert np.median(good) <= 1.05 * np.median(labels), (good, labels)


def test_crop_map_follows_the_images_resize_and_crop():
  """Linear ramps (R = 4 x + 8, G = 3 y + 20 in stored pixels) survive the antialiased resizes
  exactly away from the borders, so each pixel of the teacher's view and of the crop says which
  stored position it shows; crop_map must send the one to the other (within the uint8
  truncation, a quarter pixel; a half-pixel convention error would be 0.5 x the scale)."""
  h, w = 60, 56
  ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
  image = np.stack([4 * xs + 8, 3 * ys + 20, np.full_like(xs, 128)], -1).astype(np.uint8)
  cfg = augment.AugmentConfig(**NO_COLOR, expansion=(1.1, 1.3))
  for seed, teacher_hw in ((0, (60, 56)), (1, (84, 70)), (2, (42, 42))):
    crop = augment.flow_crop((h, w), (28, 42), np.random.default_rng(seed), cfg)
    crop_img, _ = official_ops.flow_crop_images(image, image, crop)
    teacher_img = distill_rows.teacher_view(image, teacher_hw)
    m = distill_rows.crop_map(crop.resized_hw, crop.crop0, teacher_hw)
    # stored position shown by each teacher pixel, mapped into the crop
    ty, tx = np.mgrid[0:teacher_hw[0], 0:teacher_hw[1]].astype(np.float32)
    sx = (teacher_img[..., 0].astype(np.float32) - 8 + 0.5) / 4
    sy = (teacher_img[..., 1].astype(np.float32) - 20 + 0.5) / 3
    cx, cy = m[0, 0] * tx + m[0, 2], m[1, 1] * ty + m[1, 2]
    inner = (cx >= 2) & (cx <= 28 - 3) & (cy >= 2) & (cy <= 28 - 3) & (sx > 3) & (sy > 3) & \
        (sx < w - 4) & (sy < h - 4)
    assert inner.sum() > 50
    # what the crop shows at (cx, cy), bilinearly
    shown = cv2.remap(crop_img.astype(np.float32), cx, cy, cv2.INTER_LINEAR)
    csx = (shown[..., 0] - 8 + 0.5) / 4
    csy = (shown[..., 1] - 20 + 0.5) / 3
    assert np.abs(csx - sx)[inner].max() < 0.35, (seed, np.abs(csx - sx)[inner].max())
    assert np.abs(csy - sy)[inner].max() < 0.45, (seed, np.abs(csy - sy)[inner].max())


def test_covariance_turns_with_the_target_map():
  """A C A^T with A the target view's linear part, for a scaled and for a rotated map."""
  cov = np.float32([4.0, 1.0, 0.5])   # var_x, var_y, cov_xy
  outputs = {"flow": jnp.zeros((1, 8, 8, 2)),
             "flow_covariance": jnp.asarray(np.broadcast_to(cov, (1, 8, 8, 3)).copy())}
  c = np.float32([[4.0, 0.5], [0.5, 1.0]])
  for a in (np.float32([[1.5, 0.0], [0.0, 0.5]]),
            np.float32([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]) * 2):
    m1 = np.concatenate([a, np.zeros((2, 1), np.float32)], 1)[None]
    m0 = np.float32([[[1, 0, 0], [0, 1, 0]]])
    got = np.asarray(distill.warp_to_crop(outputs, jnp.asarray(m0), jnp.asarray(m1), (8, 8))[
        "teacher_flow_covariance"])[0, 3, 3]
    want = a @ c @ a.T
    np.testing.assert_allclose(got, [want[0, 0], want[1, 1], want[0, 1]], rtol=1e-5)


def test_sampling_is_opencv_bilinear_with_replicated_borders():
  rng = np.random.default_rng(0)
  values = rng.normal(size=(1, 9, 11, 2)).astype(np.float32)
  xy = rng.uniform(-2, 12, size=(1, 5, 6, 2)).astype(np.float32)
  got = np.asarray(sampling.sample(jnp.asarray(values), jnp.asarray(xy)))[0]
  for c in range(2):
    want = cv2.remap(values[0, ..., c], xy[0, ..., 0], xy[0, ..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(got[..., c], want, atol=2e-3)   # OpenCV: 1/32 px weights
  near = np.asarray(sampling.sample(jnp.asarray(values), jnp.asarray(xy), "nearest"))[0]
  ix = np.clip(np.floor(xy[0, ..., 0] + 0.5), 0, 10).astype(int)
  iy = np.clip(np.floor(xy[0, ..., 1] + 0.5), 0, 8).astype(int)
  np.testing.assert_array_equal(near, values[0][iy, ix])


def test_pipeline_rows_swap_for_the_backward_direction(tmp_path):
  """Symmetrized distillation rows from the pipeline: (b, a) swaps the student's images, the
  teacher's images and the two maps; the teacher's images are the stored pair, un-augmented."""
  cfg = pipeline.input_config(
      {"synthetic": {"quota": 8, "root": None,
                     "options": {"split": "val", "num_pairs": 8, "size": (56, 56),
                                 "pair_type": "shift"}}},
      batch_size=4, shapes=((28, 42),), teacher_shape=(56, 56), read_threads=0,
      prefetch_buffer_size=0, num_workers=0)
  pipe = pipeline.create(cfg, seed=1, num_epochs=1, process_index=0, process_count=1)
  b = next(iter(pipe))
  assert set(b) == {"image0", "image1", "teacher_image0", "teacher_image1", "teacher_to_crop0",
                    "teacher_to_crop1", "dataset_id", "epoch"}   # no label of the source
  for k0, k1 in (("image0", "image1"), ("teacher_image0", "teacher_image1"),
                 ("teacher_to_crop0", "teacher_to_crop1")):
    np.testing.assert_array_equal(b[k0][::2], b[k1][1::2])
    np.testing.assert_array_equal(b[k1][::2], b[k0][1::2])
  src = get_source("synthetic", None, split="val", num_pairs=8, size=(56, 56), pair_type="shift")
  stored = [src[i]["image0"] for i in range(8)]
  assert all(any(np.array_equal(t, s) for s in stored) for t in b["teacher_image0"][::2])
  assert b["image0"].shape == (4, 28, 42, 3) and b["teacher_to_crop0"].dtype == np.float32


def test_photometric_off_keeps_the_geometric_crop_only():
  """input.augment.photometric=False (configs/distill.py colour=false): the
  student's images are the resize-and-crop of the pair, no colour; with it on they differ."""
  fwd, bwd = _shift_pairs(1)[0]
  for photometric in (False, True):
    cfg = augment.AugmentConfig(photometric=photometric, identical_view_prob=0.0)
    rows = _distill_rows(fwd, bwd, (56, 72), seed=3, cfg=cfg)
    # The same draws of the crop: flow_crop is the first use of the generator.
    crop = augment.flow_crop(fwd["image0"].shape[:2], (42, 56), np.random.default_rng(3), cfg)
    s0, s1 = official_ops.flow_crop_images(fwd["image0"], fwd["image1"], crop)
    same = np.array_equal(rows[0]["image0"], s0) and np.array_equal(rows[0]["image1"], s1)
    assert same == (not photometric)


def test_distill_config_colour_defaults_and_a_fresh_student(tmp_path, monkeypatch):
  """The 560 recipe takes the official colour augmentation unless colour=false, the synthetic
  recipe drops it unless colour=true; both start the student from its own init (no model_init)
  unless init=teacher, for every kind of teacher."""
  import pathlib
  from ufm_jax.training import config_lib
  config = pathlib.Path(__file__).resolve().parents[1] / "configs" / "distill.py"
  get = lambda a: config_lib.load_config(f"{config}:{a}")   # noqa: E731
  synth = "teacher=variant:synth,student=synth_small,data=synthetic"
  assert get(synth).input.augment["photometric"] is False
  assert get(synth + ",colour=true").input.augment["photometric"] is True
  frames = "teacher=variant:ufm_base,student=ufm_small,data=frames,data_root=/data/frames"
  assert get(frames).input.augment["photometric"] is True
  assert get(frames + ",colour=false").input.augment["photometric"] is False
  # The recipe, not the source, picks the default.
  assert get(frames + ",recipe=synthetic").input.augment["photometric"] is False
  # A teacher workdir that exists (a missing path that looks like org/name reads as a Hub ID).
  monkeypatch.chdir(tmp_path)
  (tmp_path / "workdirs" / "synthetic").mkdir(parents=True)
  workdir = "teacher=workdirs/synthetic,student=synth_small,data=synthetic"
  hub = "teacher=infinity1096/UFM-Base,student=ufm_small,data=frames,data_root=/data/frames"
  for arg in (synth, frames, workdir, hub):
    assert not get(arg).model_init, arg
  assert get(workdir + ",init=teacher").model_init == "teacher:workdirs/synthetic"
  assert get(hub + ",init=teacher").model_init == "teacher:snapshot:infinity1096/UFM-Base"
  with pytest.raises(ValueError, match="init"):
    get(synth + ",init=both")
  with pytest.raises(ValueError, match="colour"):
    get(synth + ",colour=maybe")
