"""Preparation tools of the benchmark sets: ETH3D (distorted GT depth -> undistorted geometry),
TA-WB (Hugging Face shards -> extracted layout)."""

import json

import h5py
import numpy as np
import pytest

from ufm_jax import data
from ufm_jax import testing
from ufm_jax.testing import wide_trees as trees


def _fisheye_k1_unproject(xd, yd, k1):
  """Inverse of x_d = theta (1 + k1 theta^2) x / r, theta = atan(r) (test-local Newton solve)."""
  rd = np.hypot(xd, yd)
  th = rd.copy()
  for _ in range(30):
    th -= (th * (1 + k1 * th * th) - rd) / (1 + 3 * k1 * th * th)
  r = np.tan(th)
  s = np.where(rd > 1e-12, r / np.maximum(rd, 1e-12), 1.0)
  return xd * s, yd * s


def test_eth3d_prepare_undistorts_depth(tmp_path):
  raw, out = tmp_path / "raw", tmp_path / "out"
  full_hw, k1 = (72, 96), 0.05
  full = trees.PlaneScene(hw0=full_hw, inv0=(), inv1=())
  scene_dir = raw / "courtyard"
  for sub in ("images/dslr_images_undistorted", "dslr_calibration_undistorted",
              "dslr_calibration_jpg", "ground_truth_depth/dslr_images"):
    (scene_dir / sub).mkdir(parents=True)
  cams_u, cams_d, images = [], [], []
  for i in (0, 1):
    name = f"DSC_{100 + i}.JPG"
    K = full.K[i]
    # COLMAP text files use the +0.5 pixel-centre convention
    cams_u.append(f"{i + 1} PINHOLE {full_hw[1]} {full_hw[0]} {K[0, 0]} {K[1, 1]} "
                  f"{K[0, 2] + 0.5} {K[1, 2] + 0.5}")
    fd, cd = 0.8 * K[0, 0], (K[0, 2] + 0.5 + 1.0, K[1, 2] + 0.5 - 0.7)
    cams_d.append(f"{i + 1} THIN_PRISM_FISHEYE {full_hw[1]} {full_hw[0]} {fd} {fd} {cd[0]} {cd[1]} "
                  f"{k1} 0 0 0 0 0 0 0")
    w2c = np.linalg.inv(full.c2w[i])
    q = trees.rotmat_to_qvec(w2c[:3, :3])
    images.append(f"{i + 1} {' '.join(map(str, q))} {' '.join(map(str, w2c[:3, 3]))} {i + 1} "
                  f"dslr_images_undistorted/{name}\n")
    trees.write_image(str(scene_dir / "images/dslr_images_undistorted" / name), full.image(i))
    # distorted GT depth: the ray of every distorted pixel, intersected with the plane
    v, u = np.mgrid[0:full_hw[0], 0:full_hw[1]].astype(np.float64)
    x, y = _fisheye_k1_unproject((u + 0.5 - cd[0]) / fd, (v + 0.5 - cd[1]) / fd, k1)
    rc = np.stack([x, y, np.ones_like(x)], -1)
    rw = rc @ full.c2w[i][:3, :3].T
    z = (full.d - full.n @ full.c2w[i][:3, 3]) / (rw @ full.n)
    z[34:40, 44:52] = np.inf  # ETH3D marks missing depth with inf
    z.astype("<f4").tofile(str(scene_dir / "ground_truth_depth/dslr_images" / name))
  (scene_dir / "dslr_calibration_undistorted/cameras.txt").write_text("# c\n" + "\n".join(cams_u))
  (scene_dir / "dslr_calibration_undistorted/images.txt").write_text(
      "# i\n" + "".join(l + "\n" for l in images))
  (scene_dir / "dslr_calibration_jpg/cameras.txt").write_text("# c\n" + "\n".join(cams_d))
  tool = testing.load_script("data/eth3d/prepare.py")
  pairs_path = tool.main(["--raw", str(raw), "--out", str(out), "--scale", "0.5",
                          "--no_progress"])
  lines = [l.split() for l in open(pairs_path) if not l.startswith("#")]
  assert [l[:3] for l in lines] == [["courtyard", "DSC_100", "DSC_101"]]
  src = data.get_source("eth3d", str(out))
  s = src[0]
  # the output geometry: half size, pixel centres kept consistent
  Ks = []
  for K in full.K:
    Kh = K.copy()
    Kh[:2, :2] *= 0.5
    Kh[0, 2], Kh[1, 2] = (K[0, 2] + 0.5) * 0.5 - 0.5, (K[1, 2] + 0.5) * 0.5 - 0.5
    Ks.append(Kh)
  half = trees.PlaneScene(hw0=(36, 48), K0=Ks[0], K1=Ks[1], c2w0=full.c2w[0], c2w1=full.c2w[1],
                          inv0=(), inv1=())
  np.testing.assert_allclose(s["meta"]["K0"], Ks[0], atol=1e-4)
  d0, z0 = s["meta"]["depth0"], half.z_depth(0)
  ok = d0 > 0
  assert 0.9 < ok.mean() < 0.995  # the inf patch became invalid
  assert np.median(np.abs(d0[ok] - z0[ok]) / z0[ok]) < 2e-3  # nearest lookup of a smooth map
  e = half.expected()
  m = e["inside"] & ok & s["covisibility"]
  err = np.abs(s["flow"] - e["flow"]).max(-1)[m]
  assert (e["inside"] & ok & ~s["covisibility"]).mean() < 0.05
  assert m.mean() > 0.3 and np.median(err) < 0.02 and err.max() < 0.3, (np.median(err), err.max())


def test_eth3d_prepare_missing_raw_names_path(tmp_path):
  tool = testing.load_script("data/eth3d/prepare.py")
  with pytest.raises(FileNotFoundError, match="nope"):
    tool.main(["--raw", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--no_progress"])


@pytest.mark.parametrize("grouped", [False, True])
def test_tawb_prepare_from_release_shards(tmp_path, grouped):
  dl, out = tmp_path / "dl", tmp_path / "out"
  (dl / "test").mkdir(parents=True)
  (dl / "test_camera_data").mkdir()
  scenes = [trees.tartanair_scene(), trees.tartanair_scene(
      c2w1=trees.look_at((-0.8, 0.3, 1.0), (0.1, 0.0, 5.0)))]
  depth_sky = []
  for s in scenes:
    d1 = s.z_depth(1).copy()
    d1[-3:] = 500.0  # sky: beyond the 200 m default cut
    depth_sky.append(d1)
  with h5py.File(dl / "test" / "shard_000.h5", "w") as f:
    if grouped:
      for i, s in enumerate(scenes):
        g = f.create_group(str(i))
        g["img0"], g["img1"] = s.image(0), s.image(1)
        g["depth0"], g["depth1"] = s.z_depth(0), depth_sky[i]
    else:
      f["img0"] = np.stack([s.image(0) for s in scenes]).astype(np.float32)
      f["img1"] = np.stack([s.image(1) for s in scenes]).astype(np.float32)
      f["depth0"] = np.stack([s.z_depth(0) for s in scenes])
      f["depth1"] = np.stack(depth_sky)
  # pairs 5 and 9 of the release live at indices 0 and 1 of the shard
  (dl / "test" / "index_000.json").write_text(json.dumps(
      {"5": ["shard_000.h5", 0], "9": {"file_name": "shard_000.h5", "file_index": 1}}))
  (dl / "test" / "stats.json").write_text(json.dumps({"forward_match_errors": [1.0]}))
  n = 10
  for cam, k in (("cam1", 0), ("cam2", 1)):
    ext = np.tile(np.eye(4), (n, 1, 1))
    intr = np.tile(np.eye(3), (n, 1, 1))
    for pair, s in zip((5, 9), scenes):
      ext[pair], intr[pair] = s.c2w[k], s.K[k]
    np.savez(dl / "test_camera_data" / f"{cam}_extrinsics.npz", ext)
    np.savez(dl / "test_camera_data" / f"{cam}_intrinsics.npz", intr)
  envs = ["x"] * n
  envs[5], envs[9] = "SewerageWinter", "Sewerage"
  (dl / "test_camera_data" / "metadata.json").write_text(json.dumps(
      {"columns": ["img1_env", "img2_env"], "index": list(range(n)),
       "data": [[e, e] for e in envs]}))
  tool = testing.load_script("data/tawb/prepare.py")
  assert tool.main(["--download", str(dl), "--out", str(out), "--no_progress"]) == 2
  src = data.get_source("tawb", str(out))
  assert [tuple(p) for p in src.pairs] == [("Sewerage", "00000005_0", "00000005_1"),
                                           ("Sewerage", "00000009_0", "00000009_1")]
  for i, s in enumerate(scenes):
    sample = src[i]
    assert (sample["meta"]["depth1"][-3:] == 0).all()  # sky masked
    s.invalid[1][-3:] = True  # the masked rows now behave as holes of view 1
    trees.check_plane_sample(sample, s)


def test_tawb_prepare_missing_camera_data(tmp_path):
  (tmp_path / "test").mkdir()
  tool = testing.load_script("data/tawb/prepare.py")
  with pytest.raises(FileNotFoundError, match="test_camera_data"):
    tool.main(["--download", str(tmp_path), "--out", str(tmp_path / "o"), "--no_progress"])


def test_dtu_prepare_mines_covisible_pairs(tmp_path):
  scene = trees.PlaneScene()
  trees.write_dtu(str(tmp_path), scene, views=(0, 1))
  trees.write_dtu(str(tmp_path), trees.PlaneScene(
      c2w1=trees.look_at((0, 0, 0), (0, 0, -5.0))), scan="scan4", views=(2, 3))  # shared Cameras/
  out = testing.load_script("data/dtu/prepare.py").main(["--root", str(tmp_path), "--no_progress"])
  lines = [l.split()[:3] for l in open(out) if not l.startswith("#")]
  # scan4's second camera looks away from the plane: no covisible pair there
  assert lines == [["scan1", "0", "1"]]
  src = data.get_source("dtu", str(tmp_path))
  assert [tuple(p) for p in src.pairs] == [("scan1", "0", "1")]


def test_scannet1500_prepare_from_loftr(tmp_path):
  K = np.array([[575.66, 0, 320.5], [0, 576.0, 242.4], [0, 0, 1]])
  T = np.eye(4)
  T[:3, :3] = trees._axis_rot((0.1, 1, 0), 0.3)
  T[:3, 3] = (0.4, -0.1, 0.2)
  np.savez(tmp_path / "test.npz", name=np.array([[707, 0, 15, 585]], np.uint16),
           rel_pose=T[:3].reshape(1, 12).astype(np.float32))
  np.savez(tmp_path / "intrinsics.npz", scene0707_00=K)
  color = tmp_path / "root" / "scannet_test_1500" / "scene0707_00" / "color"
  color.mkdir(parents=True)
  for f in (15, 585):
    trees.write_image(str(color / f"{f}.jpg"), np.zeros((48, 64, 3), np.uint8))
  tool = testing.load_script("data/scannet1500/prepare.py")
  n, missing = tool.main(["--root", str(tmp_path / "root"), "--loftr_npz", str(tmp_path / "test.npz"),
                          "--loftr_intrinsics", str(tmp_path / "intrinsics.npz")])
  assert (n, missing) == (1, 0)
  s = data.get_source("scannet1500", str(tmp_path / "root"))[0]
  # images at 64x48 = 640x480 / 10: K follows
  np.testing.assert_allclose(s["meta"]["K0"], K * np.array([[0.1], [0.1], [1]]), rtol=1e-5)
  np.testing.assert_allclose(s["meta"]["T_0to1"], T, atol=1e-6)
