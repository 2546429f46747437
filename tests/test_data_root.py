"""One data root (`input.data_root` = the official `root_data_dir`): each dataset is found in its
official layout, else its raw one, the reason is logged; absent datasets are dropped with one
warning naming both folders, malformed folders stop the start-up; the official recipes' epoch
quantities; damaged files of the official layouts are skipped, counted and logged."""

import logging
import os
import shutil

import numpy as np
import pytest

from ufm_jax.data import mixture, pipeline
from ufm_jax.testing import official_trees as ot
from ufm_jax.testing import wide_trees as wide


@pytest.fixture(scope="module")
def official_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("official_root")
  ot.write_official_root(str(root), hw=(24, 32))
  return root


def _block(datasets, root, **kw):
  kw = {"batch_size": 4, "longest_side": 28, "num_workers": 0, **kw}
  return pipeline.input_config(datasets, data_root=str(root), **kw)


def test_recipes_are_the_official_quantity_options():
  # configs/dataset/quantity_options/train/old_setting_100k.yaml (dataset=ufm_560_all).
  assert {n: q for n, (q, _) in mixture.RECIPES["ufm560"].items()} == {
      "blendedmvs": 100_000, "megadepth": 100_000, "scannetpp": 100_000,
      "tartanair_v2": 100_000, "kubric4d": 100_000, "staticthings": 10_000,
      "flyingthings": 50_000, "habitat": 25_000, "flyingchairs": 25_000, "spring": 25_000,
      "hd1k": 5_000, "monkaa": 5_000}
  # train/default.yaml's *_pairs through opticalflow_100k.yaml (ufm_980_highres).
  for r in ("ufm980", "refine980"):
    assert {n: q for n, (q, _) in mixture.RECIPES[r].items()} == {
        "flyingthings": 50_000, "flyingchairs": 25_000, "spring": 25_000, "hd1k": 5_000,
        "monkaa": 5_000}
  # static_pinhole_100k.yaml (dataset=static_pinhole).
  assert {n: q for n, (q, _) in mixture.RECIPES["refine560"].items()} == {
      "blendedmvs": 100_000, "megadepth": 100_000, "scannetpp": 100_000,
      "staticthings": 10_000, "habitat": 25_000}
  for table in mixture.RECIPES.values():
    assert all(src.startswith("configs/dataset/quantity_options/") for _, src in table.values())
  ds = mixture.recipe("ufm560")
  assert ds.kubric4d.quota == 100_000 and ds.kubric4d.root is None
  assert list(mixture.recipe("ufm560", ["hd1k"])) == ["hd1k"]
  with pytest.raises(KeyError, match="no quota for.*kubric4d"):
    mixture.recipe("ufm980", ["kubric4d"])


def test_whole_official_root_through_the_pipeline(official_root, caplog):
  cfg = _block(mixture.recipe("ufm560"), official_root)
  with caplog.at_level(logging.INFO, logger="ufm_jax.data.pipeline"):
    pipe = pipeline.create(cfg, seed=3, num_epochs=1, process_index=0, process_count=1)
  assert set(pipe.names) == set(mixture.RECIPES["ufm560"]) and not pipe.dropped
  assert "dataset kubric4d: official layout at" in caplog.text
  assert "read by 'tartanair_assembled'" in caplog.text
  it = iter(pipe)
  batches = [next(it) for _ in range(6)]
  seen = {pipe.names[d] for b in batches for d in b["dataset_id"]}
  assert all(b["image0"].shape[0] == 4 and b["flow"].dtype == np.float32 for b in batches)
  assert it.skipped == 0 and len(seen) >= 3
  # The plan comes from the seed alone: a second pipeline yields the same rows.
  again = next(iter(pipeline.create(cfg, seed=3, num_epochs=1, process_index=0, process_count=1)))
  np.testing.assert_array_equal(again["image0"], batches[0]["image0"])
  np.testing.assert_array_equal(again["dataset_id"], batches[0]["dataset_id"])


def test_official_layout_first_raw_as_fallback(tmp_path, caplog):
  scene = wide.PlaneScene()
  wide.write_blendedmvs(str(tmp_path / "blendedmvs"), scene)           # raw
  layout, folder, why = mixture.find_layout("blendedmvs", str(tmp_path))
  assert (layout.kind, layout.source, folder) == ("raw", "blendedmvs", str(tmp_path / "blendedmvs"))
  assert f"{tmp_path / 'blendedmvs_processed'} absent" in why
  ot.write_blendedmvs(str(tmp_path), scene)                            # + official
  layout, folder, why = mixture.find_layout("blendedmvs", str(tmp_path))
  assert (layout.kind, layout.source) == ("official", "blendedmvs_official")
  assert folder == str(tmp_path / "blendedmvs_processed")
  # A root given for the dataset is the one folder read, in whichever layout it holds.
  cfg = _block(mixture.mixture(["blendedmvs"]), tmp_path)
  cfg.datasets.blendedmvs.root = "blendedmvs"
  with caplog.at_level(logging.INFO, logger="ufm_jax.data.pipeline"):
    pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  assert pipe.sizes == (2,) and "raw layout at" in caplog.text
  assert "given as its root" in caplog.text


def test_official_layout_in_a_folder_of_another_name(tmp_path):
  ot.write_hd1k(str(tmp_path))
  shutil.move(str(tmp_path / "hd1k_processed"), str(tmp_path / "my_hd1k"))
  layout, folder, _ = mixture.find_layout("hd1k", "/nonexistent", str(tmp_path / "my_hd1k"))
  assert (layout.kind, folder) == ("official", str(tmp_path / "my_hd1k"))


def test_absent_dataset_dropped_with_one_warning_naming_both_folders(official_root, caplog):
  ds = mixture.mixture(["hd1k"])
  ds.update(mixture.mixture(["megadepth"]))   # present in the official root
  cfg = _block(ds, official_root)
  os.rename(official_root / "hd1k_processed", official_root / "hd1k_away")
  try:
    with caplog.at_level(logging.WARNING):
      pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  finally:
    os.rename(official_root / "hd1k_away", official_root / "hd1k_processed")
  assert pipe.names == ("megadepth",) and pipe.dropped == ("hd1k",)
  warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
  assert len(warnings) == 1
  assert str(official_root / "hd1k_processed") in warnings[0]
  assert str(official_root / "hd1k") in warnings[0]


def test_folder_with_neither_layout_fails_at_start_up(tmp_path):
  (tmp_path / "spring_processed" / "train").mkdir(parents=True)
  cfg = _block(mixture.mixture(["spring"]), tmp_path)
  with pytest.raises(mixture.LayoutError) as e:
    pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  msg = str(e.value)
  assert str(tmp_path / "spring_processed") in msg
  assert "train/*/*/flow/*.npz" in msg and "train/*/frame_left" in msg   # both layouts named


# --------------------------------------------------------------------------------------- bad data

def test_damaged_official_files_are_skipped_counted_and_logged(tmp_path, caplog):
  ot.write_tawb(str(tmp_path))
  ot.write_hd1k(str(tmp_path), n=3)
  ot.write_spring(str(tmp_path), seqs=("0001", "0002"))
  ot.write_habitat(str(tmp_path))
  shard = tmp_path / ot.TAWB_FOLDER / "train" / "shard_2_2.h5"
  shard.write_bytes(shard.read_bytes()[:4000])                              # truncated h5
  npz = tmp_path / "hd1k_processed" / "0001.npz"
  npz.write_bytes(npz.read_bytes()[:3000])                                  # truncated npz
  spring = tmp_path / "spring_processed" / "train" / "0002" / "left" / "flow" / "0001_0002.npz"
  z = dict(np.load(spring))
  del z["fov_mask_1"]
  np.savez(spring, **z)                                                     # missing key
  habitat = tmp_path / "habitat_processed" / "replica_cad_baked_lighting"
  with open(habitat / "Habitat_35000_scenes_train.txt", "a") as f:
    f.write("apt_9/000777\n")                                               # missing files
  ds = {n: {"quota": q, "root": None, "options": {"split": "train"}}
        for n, q in (("tartanair_v2", 3), ("hd1k", 3), ("spring", 4), ("habitat", 8))}
  cfg = _block(ds, tmp_path, max_skip_fraction=1.0, max_retries=50)
  pipe = pipeline.create(cfg, seed=0, num_epochs=1, process_index=0, process_count=1)
  it = iter(pipe)
  with caplog.at_level(logging.WARNING):
    batches = list(it)
  assert len(batches) == 9 and it.skipped >= 1 + 1 + 1 + 4 and it.attempted > it.skipped
  for path in (shard, npz, habitat / "apt_9" / "000777_1_camera_params.json"):
    assert str(path) in caplog.text, path
  assert f"{spring}: no key 'fov_mask_1'" in caplog.text
