"""TA-WB geometric sampler end to end on a synthetic cube-map scene written in TartanAir V2's
layout (six 90-degree pinhole faces per pose, float32-in-PNG depth, NED poses)."""

import json
import os

import cv2
import numpy as np

from ufm_jax import data
from ufm_jax.data.sources import _tawb_sampler as ts
from ufm_jax import testing
from ufm_jax.testing import wide_trees as trees

ROOM = np.array([[-5.0, 5.0], [-4.0, 4.0], [-3.0, 3.0]])  # x, y, z (NED world: z down)
LUT = np.random.default_rng(7).integers(30, 226, size=(32, 32, 32, 3)).astype(np.uint8)


def _room_hit(C, rays):
  """Distance to the room walls from inside along unit rays, and the hit points."""
  t = np.full(rays.shape[:-1], np.inf)
  for a in range(3):
    with np.errstate(divide="ignore", invalid="ignore"):
      for bound in ROOM[a]:
        ta = (bound - C[a]) / rays[..., a]
        t = np.where((ta > 1e-9) & (ta < t), ta, t)
  return t, C + rays * t[..., None]


def _texture(X):
  # 1 m cells with random colours plus a smooth blob pattern: corners and blobs for SIFT, and
  # smooth enough that resampling at different scales agrees.
  idx = np.floor(X * 1.0).astype(np.int64) % 32
  blobs = np.sin(5.0 * X[..., 0]) * np.sin(5.0 * X[..., 1]) * np.sin(5.0 * X[..., 2] + 0.5)
  out = 0.6 * LUT[idx[..., 0], idx[..., 1], idx[..., 2]] + 50 + 45 * blobs[..., None]
  return np.clip(out, 0, 255).astype(np.uint8)


FACE_AXES = {  # OpenCV (x right, y down, z forward) axes in NED world coordinates
    "front": ((0, 1, 0), (0, 0, 1), (1, 0, 0)), "back": ((0, -1, 0), (0, 0, 1), (-1, 0, 0)),
    "left": ((1, 0, 0), (0, 0, 1), (0, -1, 0)), "right": ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    "top": ((0, 1, 0), (1, 0, 0), (0, 0, -1)), "bottom": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
}


def write_cube_scene(root, centres, size=48, scene="Room/Data_easy/P000"):
  d = os.path.join(root, scene)
  K = trees.K_of(size / 2, size / 2, (size - 1) / 2, (size - 1) / 2)  # 90 degree faces
  v, u = np.mgrid[0:size, 0:size].astype(np.float64)
  rc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
  for face, axes in FACE_AXES.items():
    cam = f"lcam_{face}"
    os.makedirs(os.path.join(d, f"image_{cam}"), exist_ok=True)
    os.makedirs(os.path.join(d, f"depth_{cam}"), exist_ok=True)
    R = np.array(axes, np.float64).T
    lines = []
    for k, C in enumerate(centres):
      rw = rc @ R.T
      n = np.linalg.norm(rw, axis=-1)
      t, X = _room_hit(np.asarray(C, np.float64), rw / n[..., None])
      z = t / n
      trees.write_image(os.path.join(d, f"image_{cam}", f"{k:06d}_{cam}.png"), _texture(X))
      dz = z.astype("<f4")
      assert cv2.imwrite(os.path.join(d, f"depth_{cam}", f"{k:06d}_{cam}_depth.png"),
                         dz.view(np.uint8).reshape(dz.shape + (4,)))
      c2w = np.eye(4)
      c2w[:3, :3], c2w[:3, 3] = R, C
      ned = c2w @ trees.NED_FROM_OPENCV.T
      q = trees.rotmat_to_qvec(ned[:3, :3])
      lines.append(" ".join(f"{x:.10f}" for x in (*ned[:3, 3], q[1], q[2], q[3], q[0])))
    with open(os.path.join(d, f"pose_{cam}.txt"), "w") as f:
      f.write("\n".join(lines) + "\n")
  return scene


def test_bin_counts_equal_three_and_half():
  assert ts.bin_counts(7) == [2, 2, 2, 1]
  assert ts.bin_counts(70) == [20, 20, 20, 10]
  assert sum(ts.bin_counts(11)) == 11


def test_render_view_reproduces_cube_faces(tmp_path):
  """A virtual view aligned with a face must reproduce that face (image and depth)."""
  scene = write_cube_scene(str(tmp_path), [(0.5, -0.3, 0.4)])
  src = data.get_source("tartanair_v2", str(tmp_path), cameras=("lcam_front",))
  pose = ts.load_cube_pose(src, scene, 0)
  front = pose.faces["front"]
  img, depth = ts.render_view(pose, front.cam2world[:3, :3], front.K, front.depth.shape)
  np.testing.assert_allclose(depth, front.depth, rtol=1e-5)
  assert np.abs(img.astype(int) - front.image).max() <= 1


def test_tawb_sampler_end_to_end(tmp_path):
  rng = np.random.default_rng(0)
  centres = np.stack([rng.uniform(-3.5, 3.5, 20), rng.uniform(-2.8, 2.8, 20),
                      rng.uniform(-1.5, 1.5, 20)], 1)
  scene = write_cube_scene(str(tmp_path / "tav2"), centres, size=96)
  src = data.get_source("tartanair_v2", str(tmp_path / "tav2"))
  cfg = ts.SamplerConfig(voxel_size=0.5, point_stride=2, height=96, width=96, min_dist=1.0,
                         max_dist=12.0, min_matches=8, max_attempts_per_pair=400)
  out = tmp_path / "tawb" / "train" / "Room"
  records, rejected = ts.sample_environment(src, scene, list(range(len(centres))), str(out),
                                            total=7, seed=3, cfg=cfg, progress=False)
  per_bin = [sum(r["bin"] == list(b) for r in records) for b in ts.ANGLE_BINS]
  assert per_bin == [2, 2, 2, 1], (per_bin, rejected)
  for r in records:
    assert r["bin"][0] <= r["angle"] < r["bin"][1]
    assert r["covis_fwd"] >= 0.2 and r["covis_bwd"] >= 0.2 and r["match_error"] < 6
  meta = [json.loads(l) for l in open(out / "pairs_meta.jsonl")]
  assert len(meta) == 7
  # The written pairs load through the `tawb` source, and match the analytic room: depth, the
  # texture of the 3D point each pixel sees, and flow = projection of that point into view 1.
  tawb = data.get_source("tawb", str(tmp_path / "tawb"), split="train")
  assert len(tawb) == 7
  blur = lambda x: cv2.GaussianBlur(x, (7, 7), 2.0).astype(int)
  for i in range(len(tawb)):
    s = tawb[i]
    m = s["covisibility"]
    assert m.mean() >= 0.2
    points = []
    for k in (0, 1):
      c2w, K = s["meta"][f"cam2world{k}"].astype(float), s["meta"][f"K{k}"].astype(float)
      h, w = s[f"image{k}"].shape[:2]
      v, u = np.mgrid[0:h, 0:w].astype(float)
      rw = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) \
          @ c2w[:3, :3].T
      n = np.linalg.norm(rw, axis=-1)
      t, X = _room_hit(c2w[:3, 3], rw / n[..., None])
      points.append(X)
      # exact on planar patches; room corners and the half-pixel band at cube-face seams are
      # interpolated across, so allow a few pixels a small error
      rel = np.abs(s["meta"][f"depth{k}"] - t / n) / (t / n)
      assert (rel < 1e-3).mean() > 0.85 and rel.max() < 0.06, ((rel < 1e-3).mean(), rel.max())
      assert np.median(np.abs(blur(s[f"image{k}"]) - blur(_texture(X))).max(-1)) < 8
    w2c1 = np.linalg.inv(s["meta"]["cam2world1"].astype(float))
    K1 = s["meta"]["K1"].astype(float)
    pc = points[0] @ w2c1[:3, :3].T + w2c1[:3, 3]
    uv = pc[..., :2] / pc[..., 2:] * np.diag(K1)[:2] + K1[:2, 2]
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1)
    ferr = np.linalg.norm((grid + s["flow"])[m] - uv[m], axis=-1)
    assert (ferr < 0.05).mean() > 0.8 and np.median(ferr) < 1e-3, ((ferr < 0.05).mean(), ferr.max())
    R0, R1 = s["meta"]["cam2world0"][:3, :3], s["meta"]["cam2world1"][:3, :3]
    assert np.allclose(R0.T @ R0, np.eye(3), atol=1e-5)
  assert np.allclose(R1.T @ R1, np.eye(3), atol=1e-5)


def test_sample_pairs_cli(tmp_path):
  rng = np.random.default_rng(1)
  centres = np.stack([rng.uniform(-3.5, 3.5, 10), rng.uniform(-2.8, 2.8, 10),
                      rng.uniform(-1.5, 1.5, 10)], 1)
  write_cube_scene(str(tmp_path / "tav2"), centres, size=64)
  tool = testing.load_script("data/tawb/sample_pairs.py")
  n = tool.main(["--tav2", str(tmp_path / "tav2"), "--out", str(tmp_path / "out"), "--split",
                 "val", "--pairs_per_env", "3", "--height", "64", "--width", "64",
                 "--voxel_size", "0.5", "--min_dist", "1.0", "--min_matches", "5",
                 "--max_attempts_per_pair", "300", "--no_progress"])
  assert n == 3
  src = data.get_source("tawb", str(tmp_path / "out"), split="val")
  assert len(src) == 3 and src.scenes() == ["Room"]
