"""Optical-flow sources on tiny trees written here in each dataset's real on-disk layout.

The file writers used here (ufm_jax.data.io.write_*) are checked byte-for-byte against the format
spec in test_io_formats.py; the expected labels below are worked out by hand.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax import data
from ufm_jax.data import io

F = 1050.0  # FlyingThings3D / Monkaa: depth = 1050 / disparity


def _img(h, w, seed):
  return np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)


def _mk(path):
  os.makedirs(os.path.dirname(path), exist_ok=True)
  return path


def _check_sample(s, h, w):
  assert set(s) - {"fov_mask"} == set(data.SAMPLE_KEYS)   # fov_mask: official layouts only
  assert s["image0"].shape == s["image1"].shape == (h, w, 3) and s["image0"].dtype == np.uint8
  assert s["flow"].shape == (h, w, 2) and s["flow"].dtype == np.float32
  for k in ("covisibility", "flow_valid", "covis_valid"):
    assert s[k].shape == (h, w) and s[k].dtype == bool, k
  assert not (s["covisibility"] & ~s["flow_valid"]).any()  # covisible implies GT flow
  for k in ("dataset", "scene", "frame0", "frame1", "gt_relpath"):
    assert k in s["meta"], k


# -- FlyingChairs ---------------------------------------------------------------------------------

def _chairs_tree(root, n=3, h=6, w=8):
  images = {}
  for i in range(1, n + 1):
    for j in (1, 2):
      img = _img(h, w, 10 * i + j)
      # PPM as shipped: binary P6 with RGB samples.
      with open(_mk(os.path.join(root, "data", f"{i:05d}_img{j}.ppm")), "wb") as f:
        f.write(f"P6\n{w} {h}\n255\n".encode() + img.tobytes())
      images[i, j] = img
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0] = 3.0 * i
    flow[0, 0] = [1e10, 1e10]  # Middlebury "unknown"
    io.write_flo(os.path.join(root, "data", f"{i:05d}_flow.flo"), flow)
  return images


def test_flyingchairs_split_and_labels(tmp_path):
  images = _chairs_tree(tmp_path)
  (tmp_path / "chairs_split.txt").write_text("1\n2\n1\n")
  train = data.get_source("flyingchairs", tmp_path, split="train")
  assert len(train) == 2 and [train.ids[0], train.ids[1]] == [1, 3]
  assert len(data.get_source("flyingchairs", tmp_path, split="val")) == 1
  s = train[0]
  _check_sample(s, 6, 8)
  np.testing.assert_array_equal(s["image0"], images[1, 1])
  np.testing.assert_array_equal(s["image1"], images[1, 2])
  assert s["flow"][1, 1, 0] == 3.0 and not s["flow_valid"][0, 0] and s["flow_valid"].sum() == 47
  # FoV proxy: u + 3 must stay below W - 0.5 = 7.5 -> columns 0..4 covisible (except (0,0)).
  expected = np.zeros((6, 8), bool)
  expected[:, :5] = True
  expected[0, 0] = False
  np.testing.assert_array_equal(s["covisibility"], expected)
  assert not s["covis_valid"].any()  # FlyingChairs never supervises covisibility
  assert s["meta"]["gt_relpath"] == "00001_flow.flo"
  assert train.has_backward and not train.static_scene
  fwd, bwd = train.both(0)
  assert set(fwd) == set(bwd) == set(data.SAMPLE_KEYS) | {"fov_mask"}
  np.testing.assert_array_equal(bwd["image0"], images[1, 2])
  np.testing.assert_array_equal(bwd["image1"], images[1, 1])
  assert not bwd["flow"].any() and bwd["flow_valid"].all()   # the official zero flow, read
  for k in ("covisibility", "covis_valid", "fov_mask"):      # by the "all" range only
    assert not bwd[k].any(), k
  off = data.get_source("flyingchairs", tmp_path, split="train", backward_zero_flow=False)
  assert not off.both(0)[1]["flow_valid"].any()


def test_flyingchairs_errors(tmp_path):
  with pytest.raises(FileNotFoundError, match="nowhere.*data/"):
    data.get_source("flyingchairs", tmp_path / "nowhere")
  _chairs_tree(tmp_path)
  with pytest.raises(FileNotFoundError, match="chairs_split.txt"):
    data.get_source("flyingchairs", tmp_path, split="train")
  (tmp_path / "chairs_split.txt").write_text("1\n2\n")
  with pytest.raises(ValueError, match="chairs_split.txt.*expected 3 lines"):
    data.get_source("flyingchairs", tmp_path, split="train")
  src = data.get_source("flyingchairs", tmp_path, split="all")
  (tmp_path / "data" / "00002_flow.flo").write_bytes(b"garbage!" * 3)
  with pytest.raises(ValueError, match="00002_flow.flo"):
    src[1]


# -- FlyingThings3D / Monkaa ----------------------------------------------------------------------

H, W = 6, 12


def _scene_disparities():
  """Static background z=10; a square at z=2 on cols 2..4 in frame a, cols 5..7 in frame b."""
  da = np.full((H, W), F / 10.0, np.float32)
  da[1:5, 2:5] = F / 2.0
  db = np.full((H, W), F / 10.0, np.float32)
  db[1:5, 5:8] = F / 2.0
  fwd = np.zeros((H, W, 3), np.float32)
  fwd[1:5, 2:5, 0] = 3.0
  bwd = np.zeros((H, W, 3), np.float32)
  bwd[1:5, 5:8, 0] = -3.0
  return da, db, fwd, bwd


def _sceneflow_tree(root, scene, frames, passes=("clean",)):
  """Writes frames (a, b, c): the square moves a->b, then stays still b->c."""
  a, b, c = frames
  da, db, fwd, bwd = _scene_disparities()
  disp = {a: da, b: db, c: db}
  zero3 = np.zeros((H, W, 3), np.float32)
  fut = {a: fwd, b: zero3, c: zero3}
  past = {a: zero3, b: bwd, c: zero3}
  for fr in frames:
    for p in passes:
      io.write_image(_mk(f"{root}/frames_{p}pass/{scene}/left/{fr:04d}.png"), _img(H, W, fr))
    io.write_pfm(_mk(f"{root}/disparity/{scene}/left/{fr:04d}.pfm"), disp[fr])
    io.write_pfm(_mk(f"{root}/optical_flow/{scene}/into_future/left/"
                     f"OpticalFlowIntoFuture_{fr:04d}_L.pfm"), fut[fr])
    io.write_pfm(_mk(f"{root}/optical_flow/{scene}/into_past/left/"
                     f"OpticalFlowIntoPast_{fr:04d}_L.pfm"), past[fr], little_endian=False)
    for into in ("into_future", "into_past"):
      io.write_pfm(_mk(f"{root}/disparity_change/{scene}/{into}/left/{fr:04d}.pfm"),
                   np.zeros((H, W), np.float32))


def test_flyingthings_sceneflow_covisibility(tmp_path):
  _sceneflow_tree(tmp_path, "TRAIN/A/0000", (6, 7, 8), passes=("clean", "final"))
  src = data.get_source("flyingthings", tmp_path, split="train")
  assert len(src) == 2 and src.has_backward and not src.static_scene
  s = src[0]
  _check_sample(s, H, W)
  np.testing.assert_array_equal(s["image0"], _img(H, W, 6))
  np.testing.assert_array_equal(s["flow"][2, 3], [3.0, 0.0])
  expected = np.ones((H, W), bool)
  expected[1:5, 5:8] = False  # background covered by the square in frame 7
  np.testing.assert_array_equal(s["covisibility"], expected)
  assert s["covis_valid"].all() and s["flow_valid"].all()
  m = s["meta"]
  assert m["gt_relpath"] == "TRAIN/A/0000/into_future/left/OpticalFlowIntoFuture_0006_L.pfm"
  assert (m["dataset"], m["scene"], m["frame0"], m["frame1"]) == ("flyingthings", "TRAIN/A/0000",
                                                                  "0006", "0007")
  np.testing.assert_allclose(m["depth0"][2, 3], 2.0, rtol=1e-6)
  np.testing.assert_allclose(m["K0"], [[F, 0, 5.5], [0, F, 2.5], [0, 0, 1]])

  r = src.backward(0)  # frame 7 -> 6 with the into_past flow of frame 7
  np.testing.assert_array_equal(r["image0"], _img(H, W, 7))
  np.testing.assert_array_equal(r["flow"][2, 6], [-3.0, 0.0])
  expected = np.ones((H, W), bool)
  expected[1:5, 2:5] = False  # background behind where the square was in frame 6
  np.testing.assert_array_equal(r["covisibility"], expected)
  assert r["meta"]["gt_relpath"].endswith("into_past/left/OpticalFlowIntoPast_0007_L.pfm")

  both = data.get_source("flyingthings", tmp_path, split="train", directions="both", dstype="both")
  assert len(both) == 8
  np.testing.assert_array_equal(both[1]["flow"], r["flow"])
  assert both[1]["meta"]["direction"] == "backward" and both.backward(1)["meta"]["frame0"] == "0006"
  assert both[4]["meta"]["dstype"] == "final"
  fwd, bwd = src.both(0)  # what the pipeline calls to symmetrise batches
  np.testing.assert_array_equal(fwd["covisibility"], s["covisibility"])
  np.testing.assert_array_equal(bwd["covisibility"], r["covisibility"])
  np.testing.assert_array_equal(bwd["image0"], r["image0"])
  np.testing.assert_array_equal(bwd["image1"], r["image1"])
  b1, f1 = both.both(1)
  assert b1["meta"]["direction"] == "backward" and f1["meta"]["direction"] == "forward"


def test_flyingthings_errors(tmp_path):
  with pytest.raises(FileNotFoundError, match="frames_cleanpass"):
    data.get_source("flyingthings", tmp_path)
  _sceneflow_tree(tmp_path, "TRAIN/A/0000", (6, 7, 8))
  with pytest.raises(FileNotFoundError, match="TEST"):
    data.get_source("flyingthings", tmp_path, split="test")
  src = data.get_source("flyingthings", tmp_path)
  os.remove(tmp_path / "disparity_change/TRAIN/A/0000/into_future/left/0006.pfm")
  with pytest.raises(FileNotFoundError, match="disparity_change/TRAIN/A/0000/into_future/left/0006"):
    src[0]
  (tmp_path / "disparity/TRAIN/A/0000/left/0007.pfm").write_bytes(b"Pf\n3 3\n-1\n")
  with pytest.raises(ValueError, match="0007.pfm"):
    src[1]
  io.write_pfm(tmp_path / "disparity/TRAIN/A/0000/left/0007.pfm", np.ones((3, 3), np.float32))
  with pytest.raises(ValueError, match="disparity/TRAIN/A/0000/left/0007.pfm: shape \\(3, 3\\)"):
    src[1]


def test_monkaa_layout_and_invalid_flow(tmp_path):
  _sceneflow_tree(tmp_path, "a_rain_of_stones_x2", (0, 1, 2))
  fut = io.read_pfm(tmp_path / "optical_flow/a_rain_of_stones_x2/into_future/left/"
                    "OpticalFlowIntoFuture_0000_L.pfm")
  fut[0, 0, 0] = 5000.0  # beyond the |flow| < 1000 validity bound
  io.write_pfm(tmp_path / "optical_flow/a_rain_of_stones_x2/into_future/left/"
               "OpticalFlowIntoFuture_0000_L.pfm", fut)
  src = data.get_source("monkaa", tmp_path)
  assert len(src) == 2
  s = src[0]
  _check_sample(s, H, W)
  assert s["meta"]["scene"] == "a_rain_of_stones_x2" and s["meta"]["dataset"] == "monkaa"
  assert not s["flow_valid"][0, 0] and not s["covisibility"][0, 0]
  assert s["covisibility"][0, 1] and not s["covisibility"][2, 6]


# -- Spring ---------------------------------------------------------------------------------------

def _spring_tree(root, h=4, w=6):
  seq = f"{root}/train/0001"
  for k in (1, 2, 3):
    io.write_image(_mk(f"{seq}/frame_left/frame_left_{k:04d}.png"), _img(h, w, k))
  # 2x-resolution GT: samples on even rows/cols carry the 1K flow, odd positions a decoy.
  full = np.full((2 * h, 2 * w, 2), 99.0, np.float32)
  full[::2, ::2] = [1.0, 0.5]
  full[0, 2 * (w - 1)] = [1.0, 0.5]  # last column + 1 px leaves the view
  full[2, 2] = np.nan                  # sample (1, 1) has no GT
  for k in (1, 2):
    io.write_flo5(_mk(f"{seq}/flow_FW_left/flow_FW_left_{k:04d}.flo5"), full)
    io.write_flo5(_mk(f"{seq}/flow_BW_left/flow_BW_left_{k + 1:04d}.flo5"), -full)
    for fb, fr in (("FW", k), ("BW", k + 1)):
      mm = np.zeros((2 * h, 2 * w, 3), np.uint8)
      mm[4, 4, 0] = 255   # sample (2, 2) occluded (red)
      mm[4, 6, 1] = 255   # sample (2, 3) out of view (green)
      io.write_image(_mk(f"{seq}/maps/matchmap_flow_{fb}_left/matchmap_flow_{fb}_left_{fr:04d}.png"),
                     mm)
  os.makedirs(f"{seq}/cam_data")
  with open(f"{seq}/cam_data/intrinsics.txt", "w") as f:
    f.write("1000 1001 959.5 539.5\n1100 1101 960 540\n1200 1201 961 541\n")
  ext = [np.eye(4), np.eye(4), np.eye(4)]
  ext[1][:3, 3] = [1.0, 2.0, 3.0]
  with open(f"{seq}/cam_data/extrinsics.txt", "w") as f:
    f.write("".join(" ".join(str(x) for x in e.ravel()) + "\n" for e in ext))


def test_spring_half_resolution_gt_and_matchmap(tmp_path):
  _spring_tree(tmp_path)
  src = data.get_source("spring", tmp_path, split="train", cameras=("left",))
  assert len(src) == 2
  s = src[0]
  _check_sample(s, 4, 6)
  np.testing.assert_array_equal(s["flow"][0, 0], [1.0, 0.5])  # values not rescaled
  assert not (s["flow"] == 99.0).any()
  expected_valid = np.ones((4, 6), bool)
  expected_valid[1, 1] = False
  np.testing.assert_array_equal(s["flow_valid"], expected_valid)
  np.testing.assert_array_equal(s["covis_valid"], expected_valid)
  expected = expected_valid.copy()
  expected[:, 5] = False  # u + 1 = 6 > W - 0.5
  expected[3, :] = False  # v + 0.5 = 3.5 = H - 0.5: out of view
  expected[2, 2] = expected[2, 3] = False
  np.testing.assert_array_equal(s["covisibility"], expected)
  m = s["meta"]
  assert m["gt_relpath"] == "0001/flow_FW_left/flow_FW_left_0001.flo5"
  np.testing.assert_allclose(m["K0"], [[1000, 0, 959.5], [0, 1001, 539.5], [0, 0, 1]])
  np.testing.assert_allclose(m["K1"][0, 0], 1100)
  np.testing.assert_allclose(m["cam2world1"][:3, 3], [-1.0, -2.0, -3.0])  # inverse of w2c
  r = src.backward(0)
  assert r["meta"]["gt_relpath"] == "0001/flow_BW_left/flow_BW_left_0002.flo5"
  np.testing.assert_array_equal(r["flow"][0, 0], [-1.0, -0.5])
  np.testing.assert_array_equal(r["image0"], _img(4, 6, 2))
  f2, r2 = src.both(0)
  np.testing.assert_array_equal(r2["flow"], r["flow"])
  np.testing.assert_array_equal(r2["image1"], s["image0"])
  assert f2["meta"]["gt_relpath"] == s["meta"]["gt_relpath"]
  full = data.get_source("spring", tmp_path, cameras=("left",), full_gt=True)[0]
  assert full["meta"]["flow_full"].shape == (8, 12, 2)


def test_spring_right_camera_pose_and_depth(tmp_path):
  _spring_tree(tmp_path)
  seq = tmp_path / "train/0001"
  for k in (1, 2):
    io.write_image(_mk(f"{seq}/frame_right/frame_right_{k:04d}.png"), _img(4, 6, k))
    io.write_flo5(_mk(f"{seq}/flow_FW_right/flow_FW_right_{k:04d}.flo5"),
                  np.zeros((8, 12, 2), np.float32))
    io.write_image(_mk(f"{seq}/maps/matchmap_flow_FW_right/matchmap_flow_FW_right_{k:04d}.png"),
                   np.zeros((8, 12, 3), np.uint8))
    disp = np.full((8, 12), 13.0, np.float32)
    disp[0, 0] = np.nan
    disp[2, 2] = 0.0
    io.write_dsp5(_mk(f"{seq}/disp1_right/disp1_right_{k:04d}.dsp5"), disp)
  src = data.get_source("spring", tmp_path, cameras=("right",), with_depth=True)
  assert len(src) == 1
  m = src[0]["meta"]
  # Right camera: world-to-camera is the left one shifted by -0.065 in x, so its centre is at
  # x = +0.065 for the identity left pose of frame 1.
  np.testing.assert_allclose(m["cam2world0"], [[1, 0, 0, 0.065], [0, 1, 0, 0], [0, 0, 1, 0],
                                               [0, 0, 0, 1]])
  np.testing.assert_allclose(m["depth0"][1, 0], 1000 * 0.065 / 13.0, rtol=1e-6)
  np.testing.assert_allclose(m["depth1"][0, 1], 1100 * 0.065 / 13.0, rtol=1e-6)
  assert m["depth0"][0, 0] == 0 and m["depth0"][1, 1] == 0


def test_spring_errors(tmp_path):
  with pytest.raises(FileNotFoundError, match="train.*frame_<cam>"):
    data.get_source("spring", tmp_path)
  _spring_tree(tmp_path)
  io.write_flo5(tmp_path / "train/0001/flow_FW_left/flow_FW_left_0001.flo5",
                np.zeros((4, 6, 2), np.float32))  # 1x resolution: not what Spring ships
  src = data.get_source("spring", tmp_path, cameras=("left",))
  with pytest.raises(ValueError, match="flow_FW_left_0001.flo5.*2x resolution 8x12"):
    src[0]
  os.remove(tmp_path / "train/0001/maps/matchmap_flow_FW_left/matchmap_flow_FW_left_0002.png")
  with pytest.raises(FileNotFoundError, match="matchmap_flow_FW_left_0002.png"):
    src[1]


def test_spring_test_split_has_no_gt(tmp_path):
  for k in (1, 2):
    io.write_image(_mk(f"{tmp_path}/test/0003/frame_right/frame_right_{k:04d}.png"), _img(4, 6, k))
  src = data.get_source("spring", tmp_path, split="test", directions="both")
  assert len(src) == 2
  s = src[1]
  assert s["meta"]["has_gt"] is False and not s["flow_valid"].any()
  assert s["meta"]["gt_relpath"] == "0003/flow_BW_right/flow_BW_right_0002.flo5"


# -- HD1K -----------------------------------------------------------------------------------------

def test_hd1k(tmp_path):
  h, w = 5, 7
  for fr in (0, 1, 2):
    io.write_image(_mk(f"{tmp_path}/hd1k_input/image_2/000000_{fr:04d}.png"), _img(h, w, fr))
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = -2.25
  valid = np.ones((h, w), bool)
  valid[3, 3] = False
  for fr in (0, 1, 2):  # the last flow has no next image: no pair
    io.write_kitti_flow(_mk(f"{tmp_path}/hd1k_flow_gt/flow_occ/000000_{fr:04d}.png"), flow, valid)
  src = data.get_source("hd1k", tmp_path)
  assert len(src) == 2
  s = src[1]
  _check_sample(s, h, w)
  np.testing.assert_array_equal(s["image1"], _img(h, w, 2))
  assert s["flow"][0, 4, 0] == -2.25 and s["flow"][3, 3, 0] == 0.0
  np.testing.assert_array_equal(s["flow_valid"], valid)
  expected = valid.copy()
  expected[:, :2] = False  # u - 2.25 < -0.5 for columns 0 and 1
  np.testing.assert_array_equal(s["covisibility"], expected)
  assert not s["covis_valid"].any()
  assert s["meta"]["gt_relpath"] == "000000_0001.png"
  with pytest.raises(FileNotFoundError, match="hd1k_flow_gt"):
    data.get_source("hd1k", tmp_path / "hd1k_input")


# -- Sintel ---------------------------------------------------------------------------------------

def _sintel_tree(root, h=4, w=6):
  for p in ("clean", "final"):
    for k in (1, 2, 3):
      io.write_image(_mk(f"{root}/training/{p}/alley_1/frame_{k:04d}.png"), _img(h, w, k + 10 * (p == "final")))
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = 1.0
  flow[0, 0] = [1e10, 1e10]
  occ = np.zeros((h, w), bool)
  occ[2, 2] = True
  inv = np.zeros((h, w), bool)
  inv[3, 0] = True
  for k in (1, 2):
    io.write_flo(_mk(f"{root}/training/flow/alley_1/frame_{k:04d}.flo"), flow)
    io.write_mask(_mk(f"{root}/training/occlusions/alley_1/frame_{k:04d}.png"), occ)
    io.write_mask(_mk(f"{root}/training/invalid/alley_1/frame_{k:04d}.png"), inv)


def test_sintel(tmp_path):
  _sintel_tree(tmp_path)
  clean = data.get_source("sintel_clean", tmp_path)
  final = data.get_source("sintel_final", tmp_path, split="train")
  assert len(clean) == len(final) == 2
  s, f = clean[0], final[0]
  _check_sample(s, 4, 6)
  np.testing.assert_array_equal(f["image0"], _img(4, 6, 11))
  assert s["meta"]["gt_relpath"] == "clean/alley_1/frame_0001.flo"
  assert f["meta"]["gt_relpath"] == "final/alley_1/frame_0001.flo"
  assert (s["meta"]["scene"], s["meta"]["frame0"]) == ("alley_1", "0001")
  expected_valid = np.ones((4, 6), bool)
  expected_valid[0, 0] = False
  np.testing.assert_array_equal(s["flow_valid"], expected_valid)
  expected = expected_valid.copy()
  expected[:, 5] = False   # leaves the view
  expected[2, 2] = False   # occluded
  np.testing.assert_array_equal(s["covisibility"], expected)
  np.testing.assert_array_equal(s["meta"]["matched"], expected)  # here both rules agree
  assert s["meta"]["occlusion"][2, 2] and s["meta"]["invalid"][3, 0]
  assert not s["covis_valid"][3, 0] and s["covis_valid"].sum() == 22


def test_sintel_matched_uses_inclusive_bounds(tmp_path):
  _sintel_tree(tmp_path)
  flow = np.zeros((4, 6, 2), np.float32)
  flow[0, 0] = [-0.4, 0.0]   # lands at -0.4: in view (covisible) but outside [0, W-1] (unmatched)
  flow[0, 1] = [4.0, 0.0]    # lands at 5.0 = W - 1: matched
  io.write_flo(tmp_path / "training/flow/alley_1/frame_0001.flo", flow)
  s = data.get_source("sintel_clean", tmp_path)[0]
  assert s["covisibility"][0, 0] and not s["meta"]["matched"][0, 0]
  assert s["meta"]["matched"][0, 1]


def test_sintel_errors_and_test_split(tmp_path):
  with pytest.raises(FileNotFoundError, match="training/clean"):
    data.get_source("sintel_clean", tmp_path)
  _sintel_tree(tmp_path)
  os.remove(tmp_path / "training/occlusions/alley_1/frame_0002.png")
  with pytest.raises(FileNotFoundError, match="occlusions/alley_1/frame_0002.png"):
    data.get_source("sintel_clean", tmp_path)[1]
  with pytest.raises(FileNotFoundError, match="scenes \\['cave_2'\\]"):
    data.get_source("sintel_clean", tmp_path, scenes=["cave_2"])
  for k in (1, 2):
    io.write_image(_mk(f"{tmp_path}/test/final/wall/frame_{k:04d}.png"), _img(4, 6, k))
  t = data.get_source("sintel_final", tmp_path, split="test")
  assert len(t) == 1 and t[0]["meta"]["has_gt"] is False
  assert t[0]["meta"]["gt_relpath"] == "final/wall/frame_0001.flo"


# -- KITTI-2015 -----------------------------------------------------------------------------------

def test_kitti2015(tmp_path):
  h, w = 5, 8
  t = f"{tmp_path}/training"
  for pid in (0, 1):
    io.write_image(_mk(f"{t}/image_2/{pid:06d}_10.png"), _img(h, w, pid))
    io.write_image(_mk(f"{t}/image_2/{pid:06d}_11.png"), _img(h, w, pid + 5))
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0] = 2.5
    flow[..., 1] = -1.0
    occ = np.zeros((h, w), bool)
    occ[2:, :] = True             # LiDAR GT only on the lower rows
    noc = occ.copy()
    noc[2:, 6:] = False           # these leave the image or are occluded
    io.write_kitti_flow(_mk(f"{t}/flow_occ/{pid:06d}_10.png"), flow, occ)
    io.write_kitti_flow(_mk(f"{t}/flow_noc/{pid:06d}_10.png"), flow, noc)
  obj = np.zeros((h, w), np.uint8)
  obj[3, 1:3] = 2
  import cv2
  cv2.imwrite(_mk(f"{t}/obj_map/000000_10.png"), obj)
  src = data.get_source("kitti2015", tmp_path)
  assert len(src) == 2
  s = src[0]
  _check_sample(s, h, w)
  np.testing.assert_array_equal(s["flow"][3, 3], [2.5, -1.0])
  np.testing.assert_array_equal(s["flow_valid"], occ)
  np.testing.assert_array_equal(s["covisibility"], noc)
  np.testing.assert_array_equal(s["covis_valid"], occ)
  np.testing.assert_array_equal(s["meta"]["foreground"], obj > 0)
  assert s["meta"]["gt_relpath"] == "flow/000000_10.png"
  assert "obj_map" not in src[1]["meta"] and "foreground" not in src[1]["meta"]
  np.testing.assert_array_equal(s["meta"]["obj_map"], obj)
  s_noc = data.get_source("kitti2015", tmp_path, gt="noc")[0]
  np.testing.assert_array_equal(s_noc["flow_valid"], noc)
  os.remove(f"{t}/flow_noc/000001_10.png")
  with pytest.raises(FileNotFoundError, match="flow_noc/000001_10.png"):
    src[1]
  with pytest.raises(FileNotFoundError, match="testing/image_2"):
    data.get_source("kitti2015", tmp_path, split="testing")


# -- the training pipeline's view of these sources ------------------------------------------------

def test_pipeline_interface(tmp_path):
  from ufm_jax.data import backward_labels, load_pair
  _chairs_tree(tmp_path / "chairs")
  _sceneflow_tree(tmp_path / "things", "TRAIN/A/0000", (6, 7, 8))
  _spring_tree(tmp_path / "spring")
  _sintel_tree(tmp_path / "sintel")
  srcs = {"flyingchairs": data.get_source("flyingchairs", tmp_path / "chairs", split="all"),
          "flyingthings": data.get_source("flyingthings", tmp_path / "things"),
          "spring": data.get_source("spring", tmp_path / "spring", cameras=("left",)),
          "sintel_clean": data.get_source("sintel_clean", tmp_path / "sintel")}
  modes = {n: backward_labels.backward_mode(s, n) for n, s in srcs.items()}
  assert modes == {"flyingchairs": "source", "flyingthings": "source", "spring": "source",
                   "sintel_clean": "unsupervised"}
  for name, src in srcs.items():
    load_pair.check_sample(src[0], name)
    if modes[name] == "source":
      for s in src.both(0):
        load_pair.check_sample(s, name)


def _hd1k_tree(root, h, w):
  flow = np.zeros((h, w, 2), np.float32)
  flow[..., 0] = -2.25
  valid = np.ones((h, w), bool)
  valid[3, 3] = False
  for fr in (0, 1, 2):
    io.write_image(_mk(f"{root}/hd1k_input/image_2/000000_{fr:04d}.png"), _img(h, w, fr))
    io.write_kitti_flow(_mk(f"{root}/hd1k_flow_gt/flow_occ/000000_{fr:04d}.png"), flow, valid)


@pytest.mark.parametrize("zero_flow", [True, False])
def test_flyingchairs_backward_rows_in_the_980_all_range(tmp_path, zero_flow):
  """The official FlyingChairs second view (zero flow, every mask False) in symmetrized 980
  batches: the "all" range (loss/epe.py:63-69 reads no mask) supervises every pixel of those
  rows towards zero flow; `backward_zero_flow=False` drops them. HD1K's backward rows (official:
  4000 px flow, outside the range) supervise nothing either way."""
  from ufm_jax.training import config_lib, losses
  from ufm_jax.data import pipeline
  h, w = 28, 42
  _chairs_tree(tmp_path / "chairs", n=4, h=h, w=w)
  (tmp_path / "chairs" / "chairs_split.txt").write_text("1\n1\n1\n1\n")
  _hd1k_tree(tmp_path / "hd1k", h, w)
  recipe = config_lib.load_config("configs/ufm980.py")
  assert recipe.input.datasets.flyingchairs.options.backward_zero_flow   # the official quirk
  term = dict(losses.recipe_from_config(recipe.loss).terms)["epe_all"]
  cfg = pipeline.input_config(
      {"flyingchairs": {"quota": 4, "root": str(tmp_path / "chairs"),
                        "options": {"split": "train", "backward_zero_flow": zero_flow}},
       "hd1k": {"quota": 2, "root": str(tmp_path / "hd1k"), "options": {}}},
      batch_size=12, shapes=((14, 28),), num_workers=0, augment=dict(recipe.input.augment))
  batch = next(iter(pipeline.create(cfg, seed=0, num_epochs=1, process_index=0,
                                    process_count=1)))
  names = ("flyingchairs", "hd1k")
  mask, _ = term.mask({k: np.asarray(v) for k, v in batch.items()}, np.asarray(batch["flow"]))
  mask = np.asarray(mask)
  seen = set()
  for r in range(12):
    name, backward = names[batch["dataset_id"][r]], r % 2 == 1
    seen.add((name, backward))
    assert not batch["covisibility"][r].any() or not backward
    if name == "flyingchairs" and backward:
      assert not batch["flow"][r].any() and not batch["covis_valid"][r].any()
      assert mask[r].sum() == (14 * 28 if zero_flow else 0), r
    elif backward:
      assert mask[r].sum() == 0, r
    else:
      assert mask[r].sum() > 0, r
  assert seen == {(n, b) for n in names for b in (False, True)}
  # The rows pull a prediction towards zero flow on every pixel (the official gradient).
  pred = jnp.ones(batch["flow"].shape, jnp.float32)
  grads = jax.grad(lambda p: losses.Recipe((("epe_all", term),))(
      {"flow": p}, {k: jnp.asarray(v) for k, v in batch.items()})[0])(pred)
  rows = [r for r in range(12) if names[batch["dataset_id"][r]] == "flyingchairs" and r % 2]
  g = np.asarray(grads)[rows]
  assert (g > 0).all() if zero_flow else not g.any()


# -- Non-finite ground truth ----------------------------------------------------------------------
# NaN/Inf flow where a format has no such marker is a damaged file: the reader raises (naming it)
# and the pipeline skips and counts the sample. Formats' own markers stay "no ground truth" (the
# 1e10 .flo marker here; Spring's NaN in test_spring_half_resolution_gt_and_matchmap).

def test_nonfinite_flow_is_a_corrupt_sample_where_the_format_has_no_such_marker(tmp_path):
  _chairs_tree(tmp_path / "chairs")
  flow = io.read_flo(tmp_path / "chairs/data/00002_flow.flo")
  flow[2, 3] = np.nan
  io.write_flo(tmp_path / "chairs/data/00002_flow.flo", flow)
  chairs = data.get_source("flyingchairs", tmp_path / "chairs", split="all")
  assert not chairs[0]["flow_valid"][0, 0]  # the 1e10 unknown marker is still just invalid
  with pytest.raises(ValueError, match=r"00002_flow\.flo: non-finite flow .* at 1 of 48 pixels"):
    chairs[1]

  _sintel_tree(tmp_path / "sintel")
  flow = io.read_flo(tmp_path / "sintel/training/flow/alley_1/frame_0002.flo")
  flow[1, 1] = [np.inf, 0.0]
  io.write_flo(tmp_path / "sintel/training/flow/alley_1/frame_0002.flo", flow)
  sintel = data.get_source("sintel_clean", tmp_path / "sintel")
  assert not sintel[0]["flow_valid"][0, 0] and sintel[0]["flow_valid"].sum() == 23
  with pytest.raises(ValueError, match=r"flow/alley_1/frame_0002\.flo: non-finite flow"):
    sintel[1]

  _sceneflow_tree(tmp_path / "things", "TRAIN/A/0000", (6, 7, 8))
  path = tmp_path / "things/optical_flow/TRAIN/A/0000/into_future/left/OpticalFlowIntoFuture_0007_L.pfm"
  fut = io.read_pfm(path)
  fut[:] = np.nan
  io.write_pfm(path, fut)
  things = data.get_source("flyingthings", tmp_path / "things")
  _check_sample(things[0], H, W)
  with pytest.raises(ValueError, match=r"OpticalFlowIntoFuture_0007_L\.pfm: non-finite flow"):
    things[1]

