"""Wide-baseline benchmark readers (ETH3D, DTU, TA-WB, ScanNet-1500) on tiny trees."""

import os

import numpy as np
import pytest

from ufm_jax import data
from ufm_jax.testing import wide_trees as trees


def test_dtu_plane_millimetres_to_metres(tmp_path):
  scene = trees.PlaneScene()
  pair = trees.write_dtu(str(tmp_path), scene)
  src = data.get_source("dtu", str(tmp_path))  # split 'test' = the evaluation scans (scan1 is one)
  assert [tuple(p) for p in src.pairs] == [pair, (pair[0], pair[2], pair[1])]
  trees.check_plane_sample(src[0], scene)
  assert data.get_source("dtu", str(tmp_path), split="val").scenes() == []


def test_eth3d_prepared_plane(tmp_path):
  scene = trees.PlaneScene()
  pair = trees.write_eth3d_prepared(str(tmp_path), scene)
  with pytest.raises(FileNotFoundError, match="pairs_test.txt.*prepare.py"):
    len(data.get_source("eth3d", str(tmp_path)))
  (tmp_path / "pairs_test.txt").write_text(" ".join(pair) + "\n")
  trees.check_plane_sample(data.get_source("eth3d", str(tmp_path))[0], scene)


def test_tawb_plane(tmp_path):
  scene = trees.tartanair_scene()
  pair = trees.write_tawb(str(tmp_path), scene)
  src = data.get_source("tawb", str(tmp_path), split="test")
  assert [tuple(p) for p in src.pairs] == [pair]
  trees.check_plane_sample(src[0], scene)


def test_tawb_malformed_pose_names_file(tmp_path):
  env, f0, _ = trees.write_tawb(str(tmp_path), trees.tartanair_scene())
  np.save(tmp_path / "test" / env / "poses" / f"{f0}.npy", np.eye(3))
  with pytest.raises(ValueError, match=f"{f0}.npy.*4, 4"):
    data.get_source("tawb", str(tmp_path))[0]


def test_scannet1500_pose_only(tmp_path):
  scene = trees.PlaneScene(hw0=(48, 64))
  trees.write_scannet1500(str(tmp_path), scene, (48, 64))
  src = data.get_source("scannet1500", str(tmp_path))
  assert len(src) == 1
  s = src[0]
  assert s["image0"].shape == (48, 64, 3) and s["flow"].shape == (48, 64, 2)
  assert not s["flow_valid"].any() and not s["covis_valid"].any() and not s["covisibility"].any()
  m = s["meta"]
  np.testing.assert_allclose(m["K0"], scene.K[0], atol=1e-4)
  np.testing.assert_allclose(m["K1"], scene.K[1], atol=1e-4)
  rel = np.linalg.inv(m["cam2world1"]) @ m["cam2world0"]
  np.testing.assert_allclose(rel, np.linalg.inv(scene.c2w[1]) @ scene.c2w[0], atol=1e-5)
  assert (m["scene"], m["frame0"], m["frame1"]) == ("scene0707_00", "15", "585")


def test_scannet1500_missing_image_lists_candidates(tmp_path):
  scene = trees.PlaneScene(hw0=(48, 64))
  trees.write_scannet1500(str(tmp_path), scene, (48, 64))
  os.remove(tmp_path / "scannet_test_1500" / "scene0707_00" / "color" / "585.jpg")
  with pytest.raises(FileNotFoundError, match="scans_test/scene0707_00/color/585.jpg"):
    data.get_source("scannet1500", str(tmp_path))[0]
  with pytest.raises(FileNotFoundError, match="scannet_test_pairs_with_gt.txt"):
    data.get_source("scannet1500", str(tmp_path), pairs=str(tmp_path / "nope" /
                                                             "scannet_test_pairs_with_gt.txt"))
