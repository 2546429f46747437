"""Static wide-baseline readers on tiny trees in each dataset's real layout (see
ufm_jax/testing/wide_trees.py for the plane scene whose flow is a closed-form homography)."""

import os

import pytest

from ufm_jax import data
from ufm_jax.data import load_pair
from ufm_jax.testing import wide_trees as trees


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


def test_every_reader_loads_at_the_training_shape(tmp_path):
  """Each reader on its tree of `timing_trees` at 560x420 (the trees whose load times
  `python -m ufm_jax.testing.wide_trees` prints; figures, not asserted here) gives a 560x420
  sample that passes the training pipeline's checks, with covisible pixels (a third or more of
  each scene's source view) that have flow."""
  names = []
  for name, writer, kwargs in trees.timing_trees((420, 560)):
    root = tmp_path / name
    writer(str(root))
    s = load_pair.check_sample(data.get_source(name, str(root), **kwargs)[0], name)
    assert s["image0"].shape == s["image1"].shape == (420, 560, 3), name
    assert s["covisibility"].mean() > 0.3, (name, s["covisibility"].mean())
    assert not (s["covisibility"] & ~s["flow_valid"]).any(), name
    names.append(name)
  assert sorted(names) == sorted(["blendedmvs", "megadepth", "tartanair_v2", "scannetpp", "habitat",
                                  "staticthings", "kubric4d", "eth3d", "dtu", "tawb"])


def test_malformed_depth_formats_name_the_file(tmp_path):
  import cv2
  import numpy as np
  scene = trees.PlaneScene()
  name, f0, _ = trees.write_scannetpp(str(tmp_path / "spp"), scene)
  (tmp_path / "spp" / "pairs_train.txt").write_text(f"{name} {f0} DSC00001\n")
  exr = tmp_path / "spp" / name / "rendered_depth" / f"{f0}.exr"
  exr.write_bytes(b"not an exr file")
  with pytest.raises(ValueError, match=f"{f0}.exr.*not an OpenEXR"):
    data.get_source("scannetpp", str(tmp_path / "spp"))[0]
  scene_id, t0, _ = trees.write_tartanair_v2(str(tmp_path / "ta"), trees.tartanair_scene())
  cam, idx = t0.split("/")
  png = tmp_path / "ta" / scene_id / f"depth_{cam}" / f"{idx}_{cam}_depth.png"
  cv2.imwrite(str(png), np.zeros((4, 4, 3), np.uint8))
  with pytest.raises(ValueError, match=f"{idx}_{cam}_depth.png.*4-channel"):
    data.get_source("tartanair_v2", str(tmp_path / "ta"), strides=(1,))[0]
  trees.write_tartanair_v2(str(tmp_path / "ta2"), trees.tartanair_scene())
  (tmp_path / "ta2" / scene_id / f"pose_{cam}.txt").write_text("1 2 3\n")
  with pytest.raises(ValueError, match=f"pose_{cam}.txt.*7 numbers"):
    data.get_source("tartanair_v2", str(tmp_path / "ta2"), strides=(1,))[0]
