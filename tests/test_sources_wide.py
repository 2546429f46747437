"""Static wide-baseline readers on tiny trees in each dataset's real layout (see
test_sources_wide_trees.py for the plane scene whose flow is a closed-form homography)."""

import os

import numpy as np
import pytest

from ufm_jax import data
import test_sources_wide_trees as trees


def test_blendedmvs_plane(tmp_path):
  scene = trees.PlaneScene()
  trees.write_blendedmvs(str(tmp_path), scene)
  src = data.get_source("blendedmvs", str(tmp_path), split="train")
  assert len(src) == 2  # both directions from cams/pair.txt
  trees.check_plane_sample(src[0], scene)
  assert data.get_source("blendedmvs", str(tmp_path), split="val").scenes() == []


def _only_pair(src, pair):
  idx = [tuple(p) for p in src.pairs].index(tuple(pair))
  return src[idx]


def test_megadepth_plane(tmp_path):
  scene = trees.megadepth_scene()
  pair = trees.write_megadepth(str(tmp_path), scene)
  trees_pairs = tmp_path / "pairs_train.txt"
  trees_pairs.write_text(" ".join(pair) + "\n")
  src = data.get_source("megadepth", str(tmp_path))
  trees.check_plane_sample(src[0], scene)
  assert src.scenes() == ["0001/0"] and src.frames("0001/0") == ["img0.jpg", "img1.jpg"]


def test_megadepth_without_pairs_names_the_tool(tmp_path):
  trees.write_megadepth(str(tmp_path), trees.megadepth_scene())
  with pytest.raises(FileNotFoundError, match="pairs_train.txt.*mine_pairs.py"):
    len(data.get_source("megadepth", str(tmp_path)))


def test_tartanair_v2_plane(tmp_path):
  scene = trees.tartanair_scene()
  pair = trees.write_tartanair_v2(str(tmp_path), scene)
  src = data.get_source("tartanair_v2", str(tmp_path), strides=(1,))
  assert [tuple(p) for p in src.pairs] == [pair]
  trees.check_plane_sample(src[0], scene)


def test_scannetpp_plane(tmp_path):
  scene = trees.PlaneScene()
  pair = trees.write_scannetpp(str(tmp_path), scene)
  (tmp_path / "pairs_train.txt").write_text("# mined\n" + " ".join(pair) + " 0.61\n")
  src = data.get_source("scannetpp", str(tmp_path))
  trees.check_plane_sample(src[0], scene)


def test_habitat_plane_half_float_exr(tmp_path):
  scene = trees.PlaneScene()
  pair = trees.write_habitat(str(tmp_path), scene)
  src = data.get_source("habitat", str(tmp_path))
  assert [tuple(p) for p in src.pairs] == [pair]
  # float16 depth: ~1e-3 relative error, hence the looser tolerances
  trees.check_plane_sample(src[0], scene, tol=0.05, depth_tol=3e-3)


def test_staticthings_plane(tmp_path):
  scene = trees.PlaneScene()
  pair = trees.write_staticthings(str(tmp_path), scene)
  src = data.get_source("staticthings", str(tmp_path))
  assert [tuple(p) for p in src.pairs] == [pair]
  trees.check_plane_sample(src[0], scene)


@pytest.mark.parametrize("name", ["blendedmvs", "megadepth", "tartanair_v2", "scannetpp",
                                  "habitat", "staticthings"])
def test_missing_root_names_path(tmp_path, name):
  missing = str(tmp_path / "nope")
  with pytest.raises(FileNotFoundError, match="nope"):
    data.get_source(name, missing)


def test_malformed_files_name_path(tmp_path):
  scene = trees.PlaneScene()
  trees.write_blendedmvs(str(tmp_path), scene)
  bad = tmp_path / trees.BLENDED_SCENE / "rendered_depth_maps" / "00000000.pfm"
  bad.write_bytes(b"P6\n1 1\n255\n\0\0\0")
  src = data.get_source("blendedmvs", str(tmp_path))
  with pytest.raises(ValueError, match="00000000.pfm.*not a PFM"):
    src[0]
  os.remove(tmp_path / trees.BLENDED_SCENE / "cams" / "00000001_cam.txt")
  with pytest.raises(FileNotFoundError, match="00000001_cam.txt"):
    src[1]
