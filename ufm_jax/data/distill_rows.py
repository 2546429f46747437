"""Training rows for distillation (configs/distill.py; the teacher side: ufm_jax.training.distill).

`DistillPair` is the pipeline's per-record transform when the input block names a
`teacher_shape`: each pair's two images (a source's labels are not read unless `keep_labels`)
become
  image0, image1                     the student's input: the official flow pathway's resize and
                                     shared random crop (`augment.flow_crop`), then the official
                                     colour augmentation per image (unless
                                     `input.augment.photometric` is False)
  teacher_image0, teacher_image1     the same pair un-augmented, resized to teacher_shape
                                     (antialiased bilinear, as the training resize), as
                                     `ufm_jax.predict` shows a pair to a model: stretched to the
                                     resolution, not cropped
  teacher_to_crop0, teacher_to_crop1 [2, 3] float32 affines from teacher pixels of the row's
                                     source / target view to crop pixels (`crop_map`)
and, with `keep_labels`, the crop's labels as the flow pathway makes them (flow_pair_with_crop).
Symmetrized, the (b, a) row swaps the images, the teacher's images and the maps.

Every source takes the flow pathway here: its crop needs no labels, while the static and Kubric
pathways choose their crops by the labels' correspondences. Images are read through the cheapest
door a source has: `images(i)` (unlabelled sources: `frames`, image-only `pairs_folder` pairs),
else `lazy_pair(i)` (posed sources, labelled only on request), else the sample itself. Both views
must have the same size (the flow pathway's crop is shared).
"""

from __future__ import annotations

import numpy as np

from ufm_jax.data import augment as augment_lib
from ufm_jax.data import official_ops
from ufm_jax.data.load_pair import ARRAY_KEYS, LoadPair, check_images

TEACHER_KEYS = ("teacher_image0", "teacher_image1", "teacher_to_crop0", "teacher_to_crop1")


def row_shapes(teacher_hw) -> dict:
  """{key: (per-row shape, numpy dtype)} of the teacher's part of a distillation row."""
  th, tw = teacher_hw
  return {"teacher_image0": ((th, tw, 3), np.uint8), "teacher_image1": ((th, tw, 3), np.uint8),
          "teacher_to_crop0": ((2, 3), np.float32), "teacher_to_crop1": ((2, 3), np.float32)}


def crop_map(resized_hw, crop_top_left, teacher_hw) -> np.ndarray:
  """[2, 3] float32 affine from teacher pixels to crop pixels of one view (pixel centres at
  integers, the half-pixel convention of the resizes): the view is seen by the teacher resized
  to `teacher_hw`, by the student resized to `resized_hw` and cropped at (top, left). Per axis
  crop = (t + 0.5) * resized / teacher - 0.5 - offset; the stored size cancels."""
  (th, tw), (rh, rw), (top, left) = teacher_hw, resized_hw, crop_top_left
  ax, ay = rw / tw, rh / th
  return np.array([[ax, 0.0, 0.5 * ax - 0.5 - left],
                   [0.0, ay, 0.5 * ay - 0.5 - top]], np.float32)


def read_images(src, i: int, where: str):
  """(image0, image1) of pair i through the cheapest door the source has: `images(i)`, else
  `lazy_pair(i)`, else the sample (its labels unused)."""
  if callable(getattr(src, "images", None)):
    image0, image1 = src.images(i)
  elif callable(getattr(src, "lazy_pair", None)):
    pair = src.lazy_pair(i)
    image0, image1 = pair.image0, pair.image1
  else:
    sample = src[i]
    image0, image1 = sample["image0"], sample["image1"]
  return check_images(image0, image1, where)


def teacher_view(image, teacher_hw) -> np.ndarray:
  image = np.asarray(image)
  if image.shape[:2] == tuple(teacher_hw):
    return np.ascontiguousarray(image)
  return official_ops.resize_bilinear_aa(image, teacher_hw)


class DistillPair(LoadPair):
  """grain map: index record -> the distillation rows of one pair (1, or 2 when symmetrized)."""

  def __init__(self, *args, teacher_hw, keep_labels: bool = False, **kwargs):
    super().__init__(*args, **kwargs)
    self.teacher_hw = tuple(int(v) for v in teacher_hw)
    self.keep_labels = bool(keep_labels)
    self.row_keys = ("image0", "image1") + TEACHER_KEYS + (ARRAY_KEYS[2:] if keep_labels else ())

  def _augmented(self, d: int, i: int, out_hw, rng):
    where = f"{self.names[d]}[{i}]"
    cfg = self.cfg
    low_light = self.names[d].lower() in cfg.low_light_datasets
    if self.keep_labels:
      sample, backward = self._load(d, i)
      image0, image1 = sample["image0"], sample["image1"]
    else:
      image0, image1 = read_images(self.sources[d], i, where)
    if image0.shape != image1.shape:
      raise ValueError(f"{where}: image shapes {image0.shape} and {image1.shape} differ; "
                       "distillation crops both views alike and needs equal sizes")
    crop = augment_lib.flow_crop(image0.shape[:2], out_hw, rng, cfg)
    if self.keep_labels:
      rows = augment_lib.flow_pair_with_crop(sample, backward, crop, rng, cfg,
                                             low_light_on=low_light)
    else:
      s0, s1 = official_ops.flow_crop_images(image0, image1, crop)
      if cfg.enabled:
        s0 = augment_lib.photometric(s0, rng, cfg, low_light, static=False)
        s1 = augment_lib.photometric(s1, rng, cfg, low_light, static=False)
      rows = [{"image0": s0, "image1": s1}]
      if self.symmetrize:
        rows.append({"image0": s1, "image1": s0})
    t0, t1 = (teacher_view(im, self.teacher_hw) for im in (image0, image1))
    m0 = crop_map(crop.resized_hw, crop.crop0, self.teacher_hw)
    m1 = crop_map(crop.resized_hw, crop.crop1, self.teacher_hw)
    rows[0].update(teacher_image0=t0, teacher_image1=t1, teacher_to_crop0=m0, teacher_to_crop1=m1)
    if len(rows) > 1:
      rows[1].update(teacher_image0=t1, teacher_image1=t0, teacher_to_crop0=m1,
                     teacher_to_crop1=m0)
    return rows
