"""The training pipeline labels posed pairs only at the pixels its crop reads (the sources'
lazy_pair + augment.label_grid): the rows must equal those made from the full-size labels of the
same readers, bit for bit, in both directions."""

import numpy as np
import pytest

from ufm_jax.data import get_source, pipeline, register
from ufm_jax.data.sources import kubric4d, posed
from ufm_jax.testing import wide_trees

STATIC = ("blendedmvs", "megadepth", "tartanair_v2", "scannetpp", "habitat", "staticthings")
TREES = {name: (writer, kwargs) for name, writer, kwargs in wide_trees.timing_trees((60, 80))}


def _eager_source(name):
  """The same reader without lazy_pair: full-size labels, then backward labels from meta's depth
  + poses (given here at the views' own float64 precision, which lazy_pair uses)."""
  def make(root, **kw):
    src = get_source(name, root, **kw)
    reader = type(src)

    class Eager(reader):
      lazy_pair = None

      def both(self, i):   # Kubric-4D: the two directions read separately
        return self[i], self.backward(i)

      def __getitem__(self, i):   # PosedPairSource.__getitem__, float64 meta
        if name == "kubric4d":
          return super().__getitem__(i)
        scene, f0, f1 = self.pairs[i][:3]
        pair = reader.lazy_pair(self, i)
        sample = posed.pair_sample(self.name, scene, (f0, f1), pair.v0, pair.v1, pair.thresholds)
        meta = dict(sample["meta"], K0=pair.v0.K, K1=pair.v1.K, cam2world0=pair.v0.cam2world,
                    cam2world1=pair.v1.cam2world)
        return dict(sample, meta=meta)

    src.__class__ = Eager
    return src
  return make


for _name in STATIC + ("kubric4d",):
  register(f"_eager_{_name}")(_eager_source(_name))


@pytest.mark.parametrize("name", STATIC + ("kubric4d",))
@pytest.mark.parametrize("longest_side,symmetrize", [(112, True), (56, True), (56, False)])
def test_lazy_labels_equal_full_labels(tmp_path, monkeypatch, name, longest_side, symmetrize):
  writer, kwargs = TREES[name]
  writer(str(tmp_path))
  grids = []   # (labelled pixels, image pixels) of every label call on a grid
  for cls in (posed.PosedPair, kubric4d.KubricPair):
    def spy(self, backward=False, rows=None, cols=None, labels=cls.labels):
      if rows is not None:
        grids.append((len(rows) * len(cols), self.v0.depth.size))
      return labels(self, backward, rows, cols)
    monkeypatch.setattr(cls, "labels", spy)
  aug = {"hflip_prob": 0.5, "crop_shift": 0.1, "zoom": (1.0, 1.5), "view_scale_jitter": 0.1}
  out = []
  for prefix in ("", "_eager_"):
    cfg = pipeline.input_config(
        {prefix + name: {"quota": 8, "root": str(tmp_path), "options": kwargs}},
        batch_size=4, symmetrize=symmetrize, longest_side=longest_side, augment=aug,
        read_threads=0, prefetch_buffer_size=0, num_workers=0)
    it = iter(pipeline.create(cfg, seed=3, num_epochs=1, process_index=0, process_count=1))
    out.append([next(it) for _ in range(2)])
    if not prefix:   # the lazy run labelled grids, not whole images
      assert len(grids) == 8   # 2 batches x 4 rows, each row labelled once
      assert sum(g for g, _ in grids) < sum(n for _, n in grids)
  for lazy, eager in zip(*out):
    assert eager["flow_valid"].any() and eager["covisibility"].any()
    for k in pipeline._ARRAY_KEYS:
      a, b = np.ascontiguousarray(lazy[k]), np.ascontiguousarray(eager[k])
      assert a.dtype == b.dtype and a.shape == b.shape, k
      assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), k
