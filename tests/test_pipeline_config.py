"""The Table 1 quotas (ufm_jax.data.mixture), the input block the pipeline reads, config args."""

import logging
import pathlib

import ml_collections
import numpy as np
import pytest

from ufm_jax.training import config_lib
from ufm_jax.data import mixture, pipeline, register

SYNTHETIC = pathlib.Path(__file__).resolve().parents[1] / "configs" / "synthetic.py"


def _synthetic_config(arg):
  return config_lib.load_config(f"{SYNTHETIC}:{arg}" if arg else str(SYNTHETIC))


class _Tiny:
  has_backward = True
  static_scene = False

  def __init__(self, root, n=12, split=None):
    self.n, self.split = n, split

  def __len__(self):
    return self.n

  def _pair(self, i, sign):
    ones = np.ones((16, 24), bool)
    return {"image0": np.full((16, 24, 3), i, np.uint8), "image1": np.zeros((16, 24, 3), np.uint8),
            "flow": np.full((16, 24, 2), sign, np.float32), "covisibility": ones,
            "flow_valid": ones, "covis_valid": ones, "meta": {}}

  def __getitem__(self, i):
    return self._pair(i, 1.0)

  def backward(self, i):
    return self._pair(i, -1.0)

  def both(self, i):
    return self[i], self.backward(i)


register("_tpc_a", "_tpc_b")(_Tiny)


def test_quota_table_is_paper_table1():
  # Paper Table 1, "Pairs in Epoch" column, in the table's order.
  assert list(mixture.QUOTAS.items()) == [
      ("blendedmvs", 100_000), ("megadepth", 100_000), ("tartanair_v2", 100_000),
      ("scannetpp", 100_000), ("habitat", 25_000), ("staticthings", 10_000),
      ("kubric4d", 50_000), ("flyingthings", 50_000), ("flyingchairs", 25_000),
      ("spring", 25_000), ("monkaa", 5_000), ("hd1k", 5_000)]
  assert sum(mixture.QUOTAS.values()) == 595_000
  assert set(mixture.WIDE_BASELINE) | set(mixture.OPTICAL_FLOW) == set(mixture.ALL)
  assert not set(mixture.WIDE_BASELINE) & set(mixture.OPTICAL_FLOW)


def test_input_block_drives_the_pipeline(tmp_path, caplog):
  (tmp_path / "_tpc_a").mkdir()
  (tmp_path / "_tpc_b").mkdir()
  names = ("_tpc_a", "_tpc_b", "blendedmvs")   # blendedmvs absent under tmp_path
  ds = mixture.mixture(names, quotas={"_tpc_a": 10, "_tpc_b": 6})
  cfg = pipeline.input_config(ds, batch_size=4, longest_side=28, data_root=str(tmp_path),
                            num_workers=0, augment={})
  assert isinstance(cfg, ml_collections.ConfigDict) and cfg.datasets.blendedmvs.quota == 100_000
  with caplog.at_level(logging.WARNING):
    pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  assert "blendedmvs" in caplog.text
  assert pipe.names == ("_tpc_a", "_tpc_b") and pipe.quotas == (10, 6) and pipe.num_steps == 8
  counts = np.zeros(2, int)
  for b in pipe:
    counts += np.bincount(b["dataset_id"][::2], minlength=2)
  assert counts.tolist() == [10, 6]


def test_all_absent_lists_them(tmp_path):
  cfg = pipeline.input_config(mixture.mixture(), data_root=str(tmp_path / "empty"))
  with pytest.raises(FileNotFoundError, match="hd1k"):
    pipeline.create(cfg, seed=0, process_index=0, process_count=1)


def test_parse_arg():
  c = config_lib.parse_arg("data=of,res=980,sym=false", data="both", res=560, sym=True)
  assert (c.data, c.res, c.sym) == ("of", 980, False)
  assert config_lib.parse_arg(None, data="both").data == "both"
  with pytest.raises(config_lib.ConfigArgError, match="unknown config arg 'x'; valid keys: data$"):
    config_lib.parse_arg("x=1", data="both")
  with pytest.raises(config_lib.ConfigArgError, match="valid values: true, false, 1, 0"):
    config_lib.parse_arg("sym=maybe", sym=True)
  with pytest.raises(config_lib.ConfigArgError, match="'many' is not int"):
    config_lib.parse_arg("res=many", res=560)


def test_synthetic_mixture_through_train_entry_point():
  cfg = pipeline.input_config(mixture.synthetic_mixture(num_pairs=6, size=(28, 42)), batch_size=4,
                            longest_side=28, num_workers=0)
  it, info = pipeline.make_train_iterator(cfg, process_batch=4, seed=0)
  assert info["pairs_per_epoch"] == 12 and info["unique_pairs_per_epoch"] == 6
  assert info["datasets"] == {"synthetic": 6} and info["image_shape"] in ((14, 28), (28, 28))
  b = next(it)
  assert b["image0"].shape[0] == 4 and b["image0"].shape[1:3] in info["shapes"]
  assert b["flow_valid"].any() and b["covis_valid"].any()
  with pytest.raises(ValueError, match="expects 2 pairs per process"):
    pipeline.make_train_iterator(cfg, process_batch=2, seed=0)


def test_pairs_folder_on_disk_with_a_truncated_png(tmp_path, caplog):
  """A real reader in the mixture: synthetic pairs written in the pairs_folder format, one with its
  image0.png truncated (skipped, logged with its path), one without reverse/ labels."""
  import shutil
  from ufm_jax.data import get_source, synthetic
  root = tmp_path / "pairs"
  src = get_source("synthetic", None, split="val", num_pairs=6, size=(28, 42))
  for i in range(6):
    fwd, bwd = src.both(i)
    synthetic.write_pair(str(root / f"{i:03d}"), fwd, bwd)
  shutil.rmtree(root / "004" / "reverse")
  png = root / "002" / "image0.png"
  png.write_bytes(png.read_bytes()[:40])
  ds = {"pairs_folder": {"quota": 6, "root": str(root), "options": {}}}
  cfg = pipeline.input_config(ds, batch_size=4, longest_side=28, num_workers=0,
                            max_skip_fraction=0.5, augment={})
  pipe = pipeline.create(cfg, seed=1, num_epochs=1, process_index=0, process_count=1)
  it = iter(pipe)
  with caplog.at_level(logging.WARNING):
    batches = list(it)
  assert len(batches) == 3 and it.skipped >= 1
  assert f"{png}: missing or unreadable image" in caplog.text
  # Rows without supervision: only the backward row of pair 004 (no reverse/, no static geometry).
  unsupervised = sum(int(not b["flow_valid"][r].any()) for b in batches for r in range(4))
  assert 1 <= unsupervised <= 2 and all(b["flow_valid"][::2].any(axis=(1, 2)).all()
                                        for b in batches)


def test_synthetic_config_shift_args_reach_the_pipeline():
  c = _synthetic_config("pairs=shift,loss=l1,steps=4,batch=4,size=28,max_shift=3,aligned=0.0")
  assert c.loss.robust_epe.alpha == 1.0 and c.loss.robust_epe.c == 0.01
  assert c.evals.heldout.kwargs.pair_type == "shift" and c.evals.heldout.kwargs.max_shift == 3
  # The curriculum (patch-aligned shifts) is for training only; the held-out pairs have none.
  assert c.input.datasets.synthetic.options.aligned_shift_frac == 0.0
  assert "aligned_shift_frac" not in c.evals.heldout.kwargs
  it, _ = pipeline.make_train_iterator(c.input, process_batch=4, seed=0)
  b = next(it)
  # No augmentation: every row is an untouched shift pair (constant flow, at most 3 px).
  for k in range(4):
    flow = b["flow"][k]
    assert (flow == flow[0, 0]).all() and np.abs(flow).max() <= 3
  np.testing.assert_array_equal(b["flow"][1], -b["flow"][0])  # symmetrized (a, b), (b, a)
  assert _synthetic_config(None).loss.robust_epe.alpha == 1.0  # the README run's
  assert _synthetic_config("loss=paper").loss.robust_epe.alpha == 0.5
  with pytest.raises(ValueError, match="loss must be"):
    _synthetic_config("loss=huber")
