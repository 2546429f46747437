"""The quota-mixture grain pipeline, on tiny in-test sources whose pixels encode (dataset, index)."""

import collections
import subprocess
import sys
import json
import logging

import numpy as np
import pytest

from ufm_jax.data import pipeline, register, sampling_plan

HW = (20, 30)


class FakeSource:
  """Sample i of dataset `code`: uniform images encoding (code, i), constant flow (1, 2) and its
  exact reverse. Indices in `corrupt` raise like a broken file would; `nan` ones carry NaN flow."""
  has_backward = False
  static_scene = False

  def __init__(self, root, n=10, code=1, corrupt=(), nan=(), reversible=True, split=None,
               variants=None):
    self.root, self.n, self.code = root, n, code
    self.corrupt, self.nan, self.reversible = set(corrupt), set(nan), reversible
    if variants is not None:   # consecutive indices rendering one official sample
      self.variants = variants

  def __len__(self):
    return self.n

  def _pair(self, i, backward):
    if i in self.corrupt:
      raise ValueError(f"{self.root}/{i:05d}.png: truncated PNG")
    im_a = np.empty(HW + (3,), np.uint8)
    im_a[...] = (self.code, i % 256, i // 256)
    im_b = np.full(HW + (3,), 200, np.uint8)
    flow = np.tile(np.float32([-1, -2] if backward else [1, 2]), HW + (1,))
    if i in self.nan:
      flow[3, 4] = np.nan
    ones = np.ones(HW, bool)
    return {"image0": im_b if backward else im_a, "image1": im_a if backward else im_b,
            "flow": flow, "covisibility": ones, "flow_valid": ones, "covis_valid": ones,
            "meta": {"dataset": f"fake{self.code}", "index": i}}

  def __getitem__(self, i):
    return self._pair(i, False)


class ReversibleFake(FakeSource):
  has_backward = True

  def backward(self, i):
    return self._pair(i, True)

  def both(self, i):
    return self[i], self.backward(i)


def decode(batch, symmetrize):
  """(dataset code, index) of every unique pair in a batch, read back from the pixels."""
  im = batch["image0"][::2] if symmetrize else batch["image0"]
  px = im[:, 0, 0].astype(int)
  return [(int(c), int(lo) + 256 * int(hi)) for c, lo, hi in px]


def make_config(tmp_path, datasets, **kw):
  cfg = {"datasets": {}, "batch_size": 8, "symmetrize": True, "longest_side": 28,
         "augment": {"enabled": False},
         "read_threads": 1, "prefetch_buffer_size": 2, "max_skip_fraction": 0.05,
         "skip_check_min_samples": 1}
  for i, (quota, opts) in enumerate(datasets):
    root = tmp_path / f"d{i}"
    root.mkdir(exist_ok=True)
    cfg["datasets"][f"_tp_d{i}"] = {"quota": quota, "root": str(root), "options": opts}
  cfg.update(kw)
  return cfg


# Test-only dataset names, so the mixture can hold several fake datasets.
for _i in range(4):
  register(f"_tp_d{_i}")(lambda root, reversible=True, **kw:
                     (ReversibleFake if reversible else FakeSource)(root, **kw))


def batches(pipe_or_it, n):
  it = iter(pipe_or_it) if isinstance(pipe_or_it, pipeline.Pipeline) else pipe_or_it
  return [next(it) for _ in range(n)]


def assert_batches_equal(a, b):
  assert len(a) == len(b)
  for x, y in zip(a, b):
    assert x.keys() == y.keys()
    for k in x:
      np.testing.assert_array_equal(x[k], y[k], err_msg=k)


def test_draw_quota_with_and_without_replacement():
  rng = np.random.default_rng(0)
  a = sampling_plan.draw_quota(50, 30, rng)
  assert len(a) == 30 and len(set(a.tolist())) == 30 and a.min() >= 0 and a.max() < 50
  b = sampling_plan.draw_quota(7, 20, rng)   # 7 * 2 + 6
  counts = collections.Counter(b.tolist())
  assert len(b) == 20 and set(counts) == set(range(7))
  assert sorted(counts.values()) == [2] + [3] * 6


def test_epoch_plan_counts_equal_quotas_and_depend_on_seed_epoch():
  names, sizes, quotas = ("a", "b", "c"), (50, 7, 100), (30, 20, 5)
  ids, idx = sampling_plan.epoch_plan(names, sizes, quotas, seed=3, epoch=0)
  assert np.bincount(ids).tolist() == list(quotas)
  for d, size in enumerate(sizes):
    assert idx[ids == d].max() < size
  same = sampling_plan.epoch_plan(names, sizes, quotas, seed=3, epoch=0)
  np.testing.assert_array_equal(ids, same[0])
  np.testing.assert_array_equal(idx, same[1])
  other = sampling_plan.epoch_plan(names, sizes, quotas, seed=3, epoch=1)
  assert not np.array_equal(idx, other[1])
  # Dropping dataset "a" leaves the draws of "b" untouched (draws keyed by name).
  ids2, idx2 = sampling_plan.epoch_plan(("b", "c"), (7, 100), (20, 5), seed=3, epoch=0)
  assert sorted(idx2[ids2 == 0].tolist()) == sorted(idx[ids == 1].tolist())


def test_per_epoch_counts_in_batches_equal_quotas(tmp_path):
  # 3 epochs of 60 unique pairs, 4 unique pairs per batch; d1 is smaller than its quota.
  cfg = make_config(tmp_path, [(30, {"n": 40, "code": 1}), (25, {"n": 9, "code": 2}),
                               (5, {"n": 100, "code": 3})])
  pipe = pipeline.create(cfg, seed=1, num_epochs=3, process_index=0, process_count=1)
  assert pipe.names == ("_tp_d0", "_tp_d1", "_tp_d2") and pipe.epoch_size == 60 and pipe.num_steps == 45
  counts = collections.defaultdict(collections.Counter)
  seen = collections.defaultdict(list)
  n = 0
  for batch in pipe:
    n += 1
    assert batch["image0"].shape[0] == 8 and batch["flow"].dtype == np.float32
    for (code, i), d, e in zip(decode(batch, True), batch["dataset_id"][::2], batch["epoch"][::2]):
      assert code == d + 1
      counts[int(e)][int(d)] += 1
      seen[(int(e), int(d))].append(i)
  assert n == 45
  for e in range(3):
    assert [counts[e][d] for d in range(3)] == [30, 25, 5]
    assert len(set(seen[(e, 0)])) == 30            # without replacement
    assert set(seen[(e, 1)]) == set(range(9))      # every item of the small dataset


def test_batch_layout_symmetric_and_shapes(tmp_path):
  cfg = make_config(tmp_path, [(16, {"n": 20})], batch_size=6)
  pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  for step, b in enumerate(batches(pipe, 5)):
    from ufm_jax.data import augment
    assert b["image0"].shape[1:3] == augment.shape_for_step(pipe.shapes, 0, step)
    assert set(b) == {"image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid",
                      "dataset_id", "epoch"}
    np.testing.assert_array_equal(b["image0"][::2], b["image1"][1::2])
    np.testing.assert_array_equal(b["image1"][::2], b["image0"][1::2])
    np.testing.assert_allclose(b["flow"][::2], -b["flow"][1::2])
    assert b["covisibility"].dtype == bool


def test_same_seed_same_batches_other_seed_differs(tmp_path):
  cfg = make_config(tmp_path, [(12, {"n": 30, "code": 1}), (8, {"n": 30, "code": 2})],
                    augment={})
  a = batches(pipeline.create(cfg, seed=5, process_index=0, process_count=1), 6)
  b = batches(pipeline.create(cfg, seed=5, process_index=0, process_count=1), 6)
  assert_batches_equal(a, b)
  c = batches(pipeline.create(cfg, seed=6, process_index=0, process_count=1), 6)
  assert any(not np.array_equal(x["image0"], y["image0"]) for x, y in zip(a, c))


def test_resume_mid_epoch_from_checkpoint(tmp_path):
  from etils import epath
  import grain
  cfg = make_config(tmp_path, [(12, {"n": 30, "code": 1}), (9, {"n": 5, "code": 2})],
                    augment={})
  pipe = pipeline.create(cfg, seed=2, num_epochs=2, process_index=0, process_count=1)
  it = iter(pipe)
  batches(it, 3)  # 12 unique pairs: mid first epoch of 21
  ckpt = epath.Path(tmp_path / "ckpt")
  ckpt.mkdir()
  grain.checkpoint.CheckpointHandler().save(ckpt, item=it)
  rest = batches(it, 7)   # runs into the second epoch
  it2 = iter(pipeline.create(cfg, seed=2, num_epochs=2, process_index=0, process_count=1))
  grain.checkpoint.CheckpointHandler().restore(ckpt, item=it2)
  assert_batches_equal(rest, batches(it2, 7))
  # The remaining batches are also those of an uninterrupted run.
  assert_batches_equal(rest, batches(pipeline.create(cfg, seed=2, num_epochs=2, process_index=0,
                                                     process_count=1), 10)[3:])


def test_sharding_disjoint_complete_and_same_shapes(tmp_path):
  cfg = make_config(tmp_path, [(20, {"n": 50, "code": 1}), (28, {"n": 60, "code": 2})],
                    batch_size=12)   # 6 unique per step, 48 per epoch -> 8 steps
  per_host = {}
  for p in range(3):
    pipe = pipeline.create(cfg, seed=4, num_epochs=1, process_index=p, process_count=3)
    assert pipe.batch_size == 4 and pipe.num_steps == 8
    per_host[p] = list(pipe)
    assert len(per_host[p]) == 8
  items = [x for p in range(3) for b in per_host[p] for x in decode(b, True)]
  assert len(items) == len(set(items)) == 48   # disjoint; epoch draws without replacement here
  ids, idx = sampling_plan.epoch_plan(("_tp_d0", "_tp_d1"), (50, 60), (20, 28), seed=4, epoch=0)
  assert set(items) == {(int(d) + 1, int(i)) for d, i in zip(ids, idx)}   # complete
  for step in range(8):
    assert len({per_host[p][step]["image0"].shape for p in range(3)}) == 1
  # Global batch k = host blocks in process order = plan positions [6k, 6k+6).
  for step in range(8):
    got = [x for p in range(3) for x in decode(per_host[p][step], True)]
    assert got == [(int(d) + 1, int(i)) for d, i in zip(ids[6 * step:6 * step + 6],
                                                       idx[6 * step:6 * step + 6])]


def test_default_sharding_uses_jax_process(tmp_path):
  cfg = make_config(tmp_path, [(8, {"n": 10})])
  pipe = pipeline.create(cfg, seed=0, num_epochs=1)
  assert pipe.batch_size == 8   # one process: the whole global batch


def test_corrupt_samples_skipped_counted_and_logged(tmp_path, caplog):
  cfg = make_config(tmp_path, [(20, {"n": 20, "code": 1, "corrupt": [3], "nan": [7]})],
                    max_skip_fraction=0.5, batch_size=8)
  pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  it = iter(pipe)
  with caplog.at_level(logging.WARNING, logger="ufm_jax.data.load_pair"):
    got = [x for b in it for x in decode(b, True)]
  assert len(got) == 20
  assert not {i for _, i in got} & {3, 7}   # never trained on
  assert it.skipped >= 2 and it.attempted == 20 + it.skipped
  text = caplog.text
  assert "d0/00003.png: truncated PNG" in text and "non-finite flow" in text
  state = it.get_state()
  assert state["skipped"] == it.skipped and json.loads(json.dumps(state)) == state


def test_skipped_fraction_above_limit_fails(tmp_path):
  cfg = make_config(tmp_path, [(20, {"n": 20, "corrupt": range(0, 20, 2)})],
                    max_skip_fraction=0.1)
  it = iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1))
  with pytest.raises(pipeline.SkipLimitExceeded, match="unreadable"):
    for _ in it:
      pass


def test_absent_dataset_dropped_with_one_warning(tmp_path, caplog):
  cfg = make_config(tmp_path, [(8, {"n": 10, "code": 1}), (4, {"n": 10, "code": 2})])
  cfg["datasets"]["_tp_d2"] = {"quota": 100, "root": str(tmp_path / "nowhere")}
  cfg["datasets"]["_tp_d3"] = {"quota": 100, "root": str(tmp_path / "nowhere_either")}
  with caplog.at_level(logging.WARNING, logger="ufm_jax.data.pipeline"):
    pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  warnings = [r for r in caplog.records if "absent" in r.getMessage()]
  msg = warnings[0].getMessage()
  assert len(warnings) == 1 and "_tp_d2" in msg and "_tp_d3" in msg
  assert pipe.names == ("_tp_d0", "_tp_d1") and pipe.quotas == (8, 4)
  assert pipe.dropped == ("_tp_d2", "_tp_d3")
  cfg["datasets"] = {"_tp_d2": cfg["datasets"]["_tp_d2"]}
  with pytest.raises(FileNotFoundError, match="no dataset of the mixture"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=1)


def test_symmetrize_without_backward_labels(tmp_path):
  cfg = make_config(tmp_path, [(8, {"n": 10, "reversible": False})], backward_fallback="error")
  with pytest.raises(ValueError, match="'_tp_d0' cannot be symmetrized"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=1)
  cfg["backward_fallback"] = "unsupervised"   # the default: (b, a) rows carry no supervision
  b = next(iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)))
  np.testing.assert_array_equal(b["image0"][1::2], b["image1"][::2])
  for k in ("flow_valid", "covis_valid", "covisibility"):
    assert b[k][::2].any() and not b[k][1::2].any()
  assert b["flow_valid"][::2].all() and b["covis_valid"][::2].all()
  # Covisible unless the (constant) flow leaves the crop (the official CenterCrop's update).
  h, w = b["flow"].shape[1:3]
  u, v = b["flow"][::2, ..., 0], b["flow"][::2, ..., 1]
  inside = (np.arange(w) + u < w) & (np.arange(h)[:, None] + v < h)
  np.testing.assert_array_equal(b["covisibility"][::2], inside)
  cfg["symmetrize"] = False
  pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  b = next(iter(pipe))
  assert b["image0"].shape[0] == 8 and len(set(decode(b, False))) == 8


class BothFake(FakeSource):
  """Backward labels through `both(i)`, which gives None for odd indices (as pairs_folder does for
  a pair without reverse/)."""
  has_backward = True

  def both(self, i):
    return self._pair(i, False), self._pair(i, True) if i % 2 == 0 else None


register("_tp_both")(BothFake)


def test_symmetrize_via_both_and_per_sample_fallback(tmp_path):
  cfg = make_config(tmp_path, [])
  (tmp_path / "b").mkdir()
  cfg["datasets"] = {"_tp_both": {"quota": 12, "root": str(tmp_path / "b"), "options": {"n": 12}}}
  pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  n = 0
  for b in pipe:
    for row, (_, i) in enumerate(decode(b, True)):
      n += 1
      bwd = {k: b[k][2 * row + 1] for k in ("flow", "flow_valid")}
      if i % 2 == 0:
        np.testing.assert_allclose(bwd["flow"], -b["flow"][2 * row])
        assert bwd["flow_valid"].all()
      else:
        assert not bwd["flow_valid"].any()
  assert n == 12


def test_bad_batch_sizes(tmp_path):
  cfg = make_config(tmp_path, [(8, {"n": 10})], batch_size=6)
  with pytest.raises(ValueError, match="not divisible by 4 processes"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=4)
  with pytest.raises(ValueError, match="even per-host batch"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=2)


@pytest.mark.slow
@pytest.mark.multiprocess
def test_worker_processes_same_batches_and_resume(tmp_path):
  cfg = make_config(tmp_path, [(12, {"n": 30, "code": 1}), (9, {"n": 5, "code": 2, "corrupt": [4]})],
                    augment={}, max_skip_fraction=0.5)
  ref = batches(pipeline.create(cfg, seed=2, num_epochs=2, process_index=0, process_count=1), 8)
  cfg_mp = dict(cfg, num_workers=2)
  it = iter(pipeline.create(cfg_mp, seed=2, num_epochs=2, process_index=0, process_count=1))
  try:
    got = batches(it, 5)
    state = json.loads(json.dumps(it.get_state()))   # what grain's orbax handler stores
    assert it.skipped > 0
  finally:
    it.close()
  assert_batches_equal(ref[:5], got)
  it2 = iter(pipeline.create(cfg_mp, seed=2, num_epochs=2, process_index=0, process_count=1))
  try:
    it2.set_state(state)
    assert_batches_equal(ref[5:], batches(it2, 3))
  finally:
    it2.close()


class PlaneFake(FakeSource):
  """Fronto-parallel plane at depth 4 seen by two cameras 0.2 apart along x (f = 20): the forward
  flow is u = -f * tx / Z = -1 px everywhere; no backward accessor, depth + poses in meta."""
  static_scene = True
  dataset = "habitat"

  def __getitem__(self, i):
    sample = self._pair(i, False)
    h, w = HW
    k = np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1]])
    c2w1 = np.eye(4)
    c2w1[0, 3] = 0.2
    sample["flow"] = np.tile(np.float32([-1, 0]), HW + (1,))
    sample["meta"] = {"dataset": self.dataset, "K0": k, "K1": k, "cam2world0": np.eye(4),
                      "cam2world1": c2w1, "depth0": np.full(HW, 4.0, np.float32),
                      "depth1": np.full(HW, 4.0, np.float32)}
    return sample


class OwnStaticFake(PlaneFake):
  """A static scene under a name no table lists, with its own covisibility thresholds: the source's
  declaration, not its dataset name, lets the pipeline compute backward labels from geometry."""
  dataset = "_tp_own_static"
  thresholds = (0.1, 0.005)


register("_tp_plane")(PlaneFake)
register("_tp_own_static")(OwnStaticFake)


@pytest.mark.parametrize("name", ["_tp_plane", "_tp_own_static"])
def test_symmetrize_backward_from_depth_and_poses(tmp_path, name):
  cfg = make_config(tmp_path, [], backward_fallback="error")
  (tmp_path / "p").mkdir()
  cfg["datasets"] = {name: {"quota": 4, "root": str(tmp_path / "p"), "options": {"n": 4}}}
  cfg["augment"] = {"enabled": False}
  b = next(iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)))
  for row in range(4):
    fwd, bwd = 2 * row, 2 * row + 1
    m = b["flow_valid"][bwd] & b["covisibility"][bwd]
    assert m.mean() > 0.5   # all but the column leaving the view
    # Both views are scaled alike, so the backward flow is the negated forward one: +s px.
    both = m & b["flow_valid"][fwd]
    np.testing.assert_allclose(b["flow"][bwd][both], -b["flow"][fwd][both], atol=1e-4)
    assert b["flow"][fwd][0, -1, 0] < -0.9
    # The official labels are made after the crop: the left column's match leaves the view, its
    # flow is 0 and it is a supervised negative.
    assert (b["flow"][fwd][:, 0] == 0).all() and not b["flow_valid"][fwd][:, 0].any()
    assert b["covis_valid"][fwd][:, 0].all() and not b["covisibility"][fwd][:, 0].any()


class DynamicPlaneFake(PlaneFake):
  """Same geometry and dataset name, but the source declares a dynamic scene: depth + poses alone
  do not give its backward labels."""
  static_scene = False


register("_tp_dynamic")(DynamicPlaneFake)


def test_no_static_geometry_backward_for_dynamic_scenes(tmp_path):
  cfg = make_config(tmp_path, [])
  (tmp_path / "k").mkdir()
  cfg["datasets"] = {"_tp_dynamic": {"quota": 4, "root": str(tmp_path / "k"), "options": {"n": 4}}}
  b = next(iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)))
  assert b["flow_valid"][::2].all() and not b["flow_valid"][1::2].any()
  cfg["backward_fallback"] = "error"
  with pytest.raises(ValueError, match="not static-scene pairs"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=1)


class UndeclaredFake:
  """Readable pairs, but the class says nothing about backward labels or static scenes."""

  def __init__(self, root, n=4, split=None):
    self.inner = FakeSource(root, n=n)

  def __len__(self):
    return len(self.inner)

  def __getitem__(self, i):
    return self.inner[i]


register("_tp_undeclared")(UndeclaredFake)


def test_source_without_declarations_is_refused_when_symmetrizing(tmp_path):
  cfg = make_config(tmp_path, [])
  (tmp_path / "u").mkdir()
  cfg["datasets"] = {"_tp_undeclared": {"quota": 8, "root": str(tmp_path / "u"),
                                        "options": {"n": 8}}}
  with pytest.raises(TypeError, match="UndeclaredFake does not declare has_backward and "
                                      "static_scene.*registry.py"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=1)
  cfg["symmetrize"] = False   # only symmetrized batches need backward labels
  b = next(iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)))
  assert b["image0"].shape[0] == 8


def test_keep_heap_serves_samples_from_memory_already_touched():
  """keep_heap (in every process that makes samples) stops glibc from mapping and trimming a
  sample's 1-24 MB temporaries anew each time: far fewer page faults per repeated allocation.
  (All below glibc's 32 MiB mmap ceiling: a larger one is mapped afresh either way, and its
  faults then depend on whether the kernel finds huge pages, i.e. on the machine's memory
  pressure: 210 faults idle, 5320 beside a 10 GB compile, for a 40 MB array.)"""
  code = """if True:
    import resource, sys
    import numpy as np
    from ufm_jax.data import input_block
    if sys.argv[1] == "1":
      assert input_block.keep_heap()
    def sample():  # temporaries alive together, as in one sample's labelling
      arrays = [np.ones(n << 20, np.uint8) for n in (1, 3, 8, 2, 24, 5)]
      return sum(int(a[::4096].sum()) for a in arrays)
    sample()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
      sample()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
  """
  faults = {k: int(subprocess.run([sys.executable, "-c", code, k], check=True, text=True,
                                  capture_output=True).stdout) for k in "01"}
  assert faults["0"] > 1000, faults
  assert faults["1"] * 10 < faults["0"], faults


@pytest.mark.parametrize("draw", [True, False])
def test_variants_are_drawn_per_official_sample(tmp_path, draw):
  """A source with 4 renderings (camera x pass) of each of 6 official samples, quota 12 per
  epoch. draw_variants (official: the dataset class draws the rendering per sample): every
  official sample exactly twice per epoch (floor(12 / 6)), each time a random rendering;
  without it, 12 of the 24 renderings without replacement (a sample 0..4 times)."""
  cfg = make_config(tmp_path, [(12, {"n": 24, "variants": 4})], draw_variants=draw)
  pipe = pipeline.create(cfg, seed=3, num_epochs=8, process_index=0, process_count=1)
  assert pipe.sizes == ((6,) if draw else (24,))
  per_epoch = [collections.Counter() for _ in range(8)]
  renderings = collections.Counter()
  for e, b in enumerate(batches(pipe, 8 * 12 // 4)):
    for _, i in decode(b, True):
      per_epoch[e * 4 // 12][i // 4] += 1
      renderings[i] += 1
  spreads = {tuple(sorted(c.values())) for c in per_epoch}
  if draw:
    assert spreads == {(2,) * 6}
    assert set(renderings) == set(range(24))   # every rendering drawn at some point
  else:
    assert all(sum(s) == 12 for s in spreads) and any(s != (2,) * 6 for s in spreads)
