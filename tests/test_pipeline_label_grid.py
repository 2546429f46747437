"""The training pipeline on the wide-baseline readers' tiny trees: each dataset takes its official
pathway (static scenes labelled after the crop, Kubric-4D, TartanAir read as a flow set), the
rows' labels agree with their images, and a lazily labelled source (labels only at the stored
pixels its crop reads) gives the rows of its full-size labels, bit for bit."""

import cv2
import numpy as np
import pytest

from ufm_jax.data import augment, get_source, pipeline, register
from ufm_jax.testing import wide_trees

STATIC = ("blendedmvs", "megadepth", "scannetpp", "habitat", "staticthings")
TREES = {name: (writer, kwargs) for name, writer, kwargs in wide_trees.timing_trees((60, 80))}
NO_COLOR = dict(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0, grayscale_prob=0.0,
                blur_prob=0.0, identical_view_prob=0.0)


def _batches(root, name, kwargs, n=2, symmetrize=True, augment_keys=None, shapes=((42, 56),)):
  cfg = pipeline.input_config(
      {name: {"quota": 8, "root": str(root), "options": kwargs}}, batch_size=4,
      symmetrize=symmetrize, shapes=shapes, augment=augment_keys or {}, read_threads=0,
      prefetch_buffer_size=0, num_workers=0)
  pipe = pipeline.create(cfg, seed=3, num_epochs=1, process_index=0, process_count=1)
  it = iter(pipe)
  return pipe, [next(it) for _ in range(n)]


def test_each_dataset_takes_its_official_pathway(tmp_path):
  cfg = augment.AugmentConfig()
  want = {**{n: "static" for n in STATIC}, "kubric4d": "kubric", "tartanair_v2": "flow"}
  for name, path in want.items():
    writer, kwargs = TREES[name]
    writer(str(tmp_path / name))
    assert pipeline.pathway(get_source(name, str(tmp_path / name), **kwargs), name, cfg) == path


@pytest.mark.parametrize("name", STATIC + ("kubric4d", "tartanair_v2"))
def test_rows_follow_the_crop(tmp_path, name):
  """Symmetrized rows show the same images swapped; a covisible pixel's match lies in the other
  crop; covisibility implies defined flow; image1 warped by the flow shows image0."""
  writer, kwargs = TREES[name]
  writer(str(tmp_path))
  _, batches = _batches(tmp_path, name, kwargs, augment_keys=NO_COLOR)
  # Static labels: the match projects into [-0.5, W - 0.5); flow sets and Kubric: the stored
  # match stays in [0, W) of the crop (CovisibleGuided / RandomEqualCrop).
  lo, hi = (-0.5, 0.5) if name in STATIC else (0.0, 0.0)
  errors, shifted = [], []
  for b in batches:
    np.testing.assert_array_equal(b["image0"][::2], b["image1"][1::2])
    for r in range(b["flow"].shape[0]):
      covis, flow = b["covisibility"][r], b["flow"][r]
      assert covis.any(), (name, r)
      assert not (covis & ~b["flow_valid"][r]).any()
      h, w = covis.shape
      x, y = np.arange(w) + flow[..., 0], np.arange(h)[:, None] + flow[..., 1]
      assert ((x >= lo) & (x < w - hi) & (y >= lo) & (y < h - hi))[covis].all()
      yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
      for f, out in ((flow, errors), (flow + np.float32([1.5, 0]), shifted)):
        warped = cv2.remap(b["image1"][r].astype(np.float32), xx + f[..., 0], yy + f[..., 1],
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out.append(np.median(np.abs(warped - b["image0"][r]).mean(-1)[covis]))
  assert np.median(errors) < 0.6 * np.median(shifted), (name, errors, shifted)


def _eager_tartanair(root, **kwargs):
  """TartanAir V2 without lazy_pair: full-size official labels in both directions (`both`)."""
  src = get_source("tartanair_v2", root, **kwargs)
  reader = type(src)
  params = pipeline.label_parameters(src, "tartanair_v2")

  class Eager(reader):
    lazy_pair = None
    has_backward = True
    pathway = "flow"

    def both(self, i):
      pair = reader.lazy_pair(self, i)
      return tuple({"image0": a.image, "image1": b.image, "meta": {"dataset": "tartanair_v2"},
                    **pair.training_labels(backward, params)}
                   for a, b, backward in ((pair.v0, pair.v1, False), (pair.v1, pair.v0, True)))

    def __getitem__(self, i):
      return self.both(i)[0]

  src.__class__ = Eager
  return src


register("_eager_tartanair_v2")(_eager_tartanair)


@pytest.mark.parametrize("shapes,symmetrize", [(((42, 56),), True), (((28, 84),), True),
                                               (((56, 56),), False)])
def test_lazy_labels_equal_full_labels(tmp_path, monkeypatch, shapes, symmetrize):
  writer, kwargs = TREES["tartanair_v2"]
  writer(str(tmp_path))
  grids = []
  from ufm_jax.data.sources import posed
  labels = posed.PosedPair.training_labels

  def spy(self, backward, params, rows=None, cols=None):
    if rows is not None:
      grids.append((len(rows) * len(cols), self.v0.depth.size))
    return labels(self, backward, params, rows, cols)

  monkeypatch.setattr(posed.PosedPair, "training_labels", spy)
  _, lazy = _batches(tmp_path, "tartanair_v2", kwargs, symmetrize=symmetrize, shapes=shapes)
  assert len(grids) == 8   # 2 batches x 4 rows, each labelled once
  assert sum(g for g, _ in grids) < sum(n for _, n in grids)
  _, eager = _batches(tmp_path, "_eager_tartanair_v2", kwargs, symmetrize=symmetrize,
                      shapes=shapes)
  for a, b in zip(lazy, eager):
    assert b["flow_valid"].any() and b["covisibility"].any()
    for k in pipeline._ARRAY_KEYS:
      x, y = np.ascontiguousarray(a[k]), np.ascontiguousarray(b[k])
      assert x.dtype == y.dtype and x.shape == y.shape, k
      assert np.array_equal(x.view(np.uint8), y.view(np.uint8)), k


def test_habitat_is_not_crop_augmented_by_default(tmp_path):
  """The 560 recipe's Habitat: resize to cover + centre crop (no_crop_datasets), so its rows
  equal the no-augmentation path's labels (colours aside)."""
  writer, kwargs = TREES["habitat"]
  writer(str(tmp_path))
  src = get_source("habitat", str(tmp_path), **kwargs)
  pair = src.lazy_pair(0)
  views = [augment.StaticView(v.image, v.depth, v.K, v.cam2world) for v in (pair.v0, pair.v1)]
  want = augment.static_pair(*views, pipeline.label_parameters(src, "habitat"), (42, 56), None,
                             augment.AugmentConfig(enabled=False))
  _, batches = _batches(tmp_path, "habitat", kwargs, n=1, augment_keys=NO_COLOR)
  b = batches[0]
  for r in range(2):
    for k in augment.LABEL_KEYS:
      np.testing.assert_array_equal(b[k][r], want[r][k], err_msg=k)
