"""Tiny trees in the benchmark datasets' own layouts, for the evaluate.py tests.

Sintel (MPI-Sintel-complete) and KITTI-2015 (data_scene_flow) with random content; the wide-
baseline layouts are in `wide_trees`.
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data import io


def write_sintel(root, h=28, w=42, frames=3, scene="alley_1"):
  rng = np.random.default_rng(0)
  tr = os.path.join(root, "training")
  for sub in ("clean", "final", "flow", "occlusions", "invalid"):
    os.makedirs(os.path.join(tr, sub, scene))
  for k in range(1, frames + 1):
    for p in ("clean", "final"):
      io.write_image(os.path.join(tr, p, scene, f"frame_{k:04d}.png"),
                     rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    if k < frames:
      io.write_flo(os.path.join(tr, "flow", scene, f"frame_{k:04d}.flo"),
                   rng.normal(0, 3, (h, w, 2)).astype(np.float32))
      occ = np.zeros((h, w), bool)
      occ[:, :5] = True
      io.write_mask(os.path.join(tr, "occlusions", scene, f"frame_{k:04d}.png"), occ)
      io.write_mask(os.path.join(tr, "invalid", scene, f"frame_{k:04d}.png"), np.zeros((h, w), bool))


def write_kitti(root, h=30, w=50, n=2):
  rng = np.random.default_rng(1)
  tr = os.path.join(root, "training")
  for sub in ("image_2", "flow_occ", "flow_noc", "obj_map"):
    os.makedirs(os.path.join(tr, sub))
  for i in range(n):
    for f in (10, 11):
      io.write_image(os.path.join(tr, "image_2", f"{i:06d}_{f}.png"),
                     rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    flow = rng.normal(0, 20, (h, w, 2)).astype(np.float32)
    valid = rng.random((h, w)) < 0.6
    io.write_kitti_flow(os.path.join(tr, "flow_occ", f"{i:06d}_10.png"), flow, valid)
    io.write_kitti_flow(os.path.join(tr, "flow_noc", f"{i:06d}_10.png"), flow, valid & (rng.random((h, w)) < 0.8))
    obj = np.zeros((h, w), np.uint8)
    obj[10:20, 10:30] = 1
    io.write_image(os.path.join(tr, "obj_map", f"{i:06d}_10.png"), np.repeat(obj[..., None], 3, -1))


# ------------------------------------------- the official benchmark branch's data (dataset_root)
def write_eth3d_processed(root, scene, name="courtyard", views=("DSC_0286", "DSC_0287")):
  """`eth3d_processed/<scene>/` as the official preprocess_eth3d.py writes it: undistorted_images
  (JPEG), undistorted_depths (z, metres, 0 = none), undistorted_camera_params (fx, fy, cx, cy),
  poses (world-to-camera). `scene` is a wide_trees.PlaneScene; returns (scene, view0, view1)."""
  from ufm_jax.testing import wide_trees
  d = os.path.join(root, name)
  for sub in ("undistorted_images", "undistorted_depths", "undistorted_camera_params", "poses"):
    os.makedirs(os.path.join(d, sub), exist_ok=True)
  for i, v in enumerate(views):
    wide_trees.write_image(os.path.join(d, "undistorted_images", v + ".jpg"), scene.image(i))
    np.save(os.path.join(d, "undistorted_depths", v + ".npy"), scene.z_depth(i).astype(np.float32))
    K = scene.K[i]
    np.save(os.path.join(d, "undistorted_camera_params", v + ".npy"),
            np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    np.save(os.path.join(d, "poses", v + ".npy"), np.linalg.inv(scene.c2w[i]).astype(np.float32))
  return name, views[0], views[1]


def write_dtu_processed(root, scene, scan="scan1", views=("00000000", "00000001")):
  """`dtu_processed/<scan>/` as the official preprocess_dtu.py writes it, in millimetres: images
  (PNG), depths (z mm, 0 = none), camera_params/<v>_intrinsics.npy, poses (world-to-camera, mm).
  `scene` (metres) is written scaled by 1000; returns (scan, view0, view1)."""
  d = os.path.join(root, scan)
  for sub in ("images", "depths", "camera_params", "poses"):
    os.makedirs(os.path.join(d, sub), exist_ok=True)
  for i, v in enumerate(views):
    io.write_image(os.path.join(d, "images", v + ".png"), scene.image(i))
    np.save(os.path.join(d, "depths", v + ".npy"), (scene.z_depth(i) * 1000).astype(np.float32))
    np.save(os.path.join(d, "camera_params", v + "_intrinsics.npy"), scene.K[i].astype(np.float32))
    w2c = np.linalg.inv(scene.c2w[i])
    w2c[:3, 3] *= 1000
    np.save(os.path.join(d, "poses", v + ".npy"), w2c.astype(np.float32))
  return scan, views[0], views[1]


def write_anymap_pairs(path, rows, object_array=True):
  """An AnyMap pair table (`anymap_data_pairs/<set>_valid_pairs.npz`): key `data`, rows (scene,
  view0, view1, score); the release stores an object array (np.load needs allow_pickle)."""
  os.makedirs(os.path.dirname(path), exist_ok=True)
  rows = [(str(s), str(a), str(b), float(c)) for s, a, b, c in rows]
  data = np.array(rows, dtype=object) if object_array else np.array(rows, dtype=str)
  np.savez(path, data=data)
  return path


TAWB_KEYS = ("img0", "img1", "flow_fwd", "flow_bwd", "non_occluded_fwd", "non_occluded_bwd",
             "occlusion_supervision_mask_fwd", "occlusion_supervision_mask_bwd", "fov_mask_fwd",
             "fov_mask_bwd")


def write_tawb_data(root, samples, split="data", per_shard=2):
  """`TA-WB/<split>/` in the official DistributedH5Reader format: shards `part_<k>.h5` holding the
  TAWB_KEYS datasets stacked along a first axis, an index-map JSON {"<sample>": [shard, index]},
  and a statistics JSON the reader must skip. `samples`: dicts with img0, img1 [H, W, 3] uint8,
  flow_fwd [2, H, W], non_occluded_fwd, fov_mask_fwd, occlusion_supervision_mask_fwd [H, W]
  (the backward keys are filled with the forward ones when absent)."""
  import json

  from ufm_jax.testing import official_trees
  d = os.path.join(root, split)
  os.makedirs(d, exist_ok=True)
  index = {}
  for k in range(0, len(samples), per_shard):
    chunk = samples[k:k + per_shard]
    name = f"part_{k // per_shard:03d}.h5"
    official_trees.write_h5(os.path.join(d, name), **{
        key: np.stack([s.get(key, s.get(key.replace("_bwd", "_fwd"))) for s in chunk])
        for key in TAWB_KEYS})
    index.update({str(k + j): [name, j] for j in range(len(chunk))})
  with open(os.path.join(d, "index_map.json"), "w") as f:
    json.dump(index, f)
  with open(os.path.join(d, "statistics.json"), "w") as f:
    json.dump({"forward_match_errors": [0.5] * len(samples)}, f)
  return d


def write_official_bench_root(root, scene, tawb_samples, flow_benches=True):
  """The official benchmark branch's dataset_root: Sintel/ and KITTI/ (with flow_benches),
  eth3d_processed/ with 4 pairs of distinct views DSC_<2k>, DSC_<2k+1> and dtu_processed/ with
  one scan listed in 51 rows (the branch's every third / fiftieth row: 2 pairs each), their
  anymap_data_pairs/ tables (ETH3D's an object array as released, DTU's a string array), and
  TA-WB/ holding `tawb_samples` (`write_tawb_data`). `scene`: a wide_trees.PlaneScene."""
  if flow_benches:
    write_sintel(os.path.join(root, "Sintel"))
    write_kitti(os.path.join(root, "KITTI"))
  pairs = os.path.join(root, "anymap_data_pairs")
  rows = [write_eth3d_processed(os.path.join(root, "eth3d_processed"), scene,
                                views=(f"DSC_{2 * k}", f"DSC_{2 * k + 1}")) + (0.5,)
          for k in range(4)]
  write_anymap_pairs(os.path.join(pairs, "eth3d_valid_pairs.npz"), rows)
  scan = write_dtu_processed(os.path.join(root, "dtu_processed"), scene)
  write_anymap_pairs(os.path.join(pairs, "dtu_valid_pairs.npz"),
                     [scan + (float(k),) for k in range(51)], object_array=False)
  write_tawb_data(os.path.join(root, "TA-WB"), tawb_samples)
  return root


def scored_prediction(flow_gt: np.ndarray) -> np.ndarray:
  """The prediction tests/fixtures/benchmark_protocol scores with the official metric code: GT
  flow [2, H, W] (channel first) + an analytic field (float32) large enough that every mask,
  outlier threshold and pooling rule of the metrics shows in the numbers."""
  _, h, w = np.shape(flow_gt)
  y, x = np.mgrid[0:h, 0:w].astype(np.float64)
  delta = np.stack([4.0 * np.sin(2 * np.pi * x / 97.0) + 0.4,
                    3.0 * np.cos(2 * np.pi * y / 61.0) - 0.3]).astype(np.float32)
  return (np.asarray(flow_gt, np.float32) + delta).astype(np.float32)
