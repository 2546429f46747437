"""TA-WB release (Hugging Face `infinity1096/TA-WB-MapAnything`) -> the extracted layout the
`tawb` source reads.

  python data/tawb/prepare.py --download /data/TA-WB-MapAnything --out /data/tawb --split test

Input (the dataset repository as downloaded):
  <split>/*.json              index maps str(pair) -> [h5 file, index in file] (or
                              {"file_name", "file_index"}); JSONs holding `forward_match_errors`
                              are statistics, not index maps, and are skipped
  <split>/*.h5                per pair `img0`, `img1` (RGB), `depth0`, `depth1`: either datasets
                              indexed along their first axis by the index in file, or a group
                              named by that index holding the four arrays
  <split>_camera_data/cam{1,2}_extrinsics.npz, cam{1,2}_intrinsics.npz   `arr_0`, row = pair
                              (4x4 camera-to-world OpenCV; 3x3 K)
  <split>_camera_data/metadata.json   pandas orient="split" table with `img1_env`
Output: <out>/<split>/<Env>/{images,depth,camera_params,poses}/{pair:08d}_{0,1}.* where Env is
the geometry environment (condition suffixes such as Winter/Night stripped). Sky is masked as the
map-anything extraction does: depth >= 80 m (Prison, OldTown), 120 m (ShoreCaves), 35 m
(OldBrickHouse), 200 m elsewhere becomes 0.

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import json
import os

import cv2
import h5py
import numpy as np

from ufm_jax.data.sources import exr, posed, tawb

CONDITIONS = ("SummerNight", "WinterNight", "Autumn", "Spring", "Winter", "Day", "Night", "Fall",
              "Summer")
SKY = {"Prison": 80.0, "OldTown": 80.0, "ShoreCaves": 120.0, "OldBrickHouse": 35.0}
DEFAULT_SKY = 200.0


def geometry_env(env: str) -> str:
  for c in CONDITIONS:
    if env.endswith(c) and len(env) > len(c):
      return env[:-len(c)].rstrip("_")
  return env


def _read_pair(h5, index, path):
  if str(index) in h5:
    g = h5[str(index)]
    return [np.asarray(g[k]) for k in ("img0", "img1", "depth0", "depth1")]
  try:
    return [np.asarray(h5[k][index]) for k in ("img0", "img1", "depth0", "depth1")]
  except KeyError as e:
    raise ValueError(f"{path}: expected img0/img1/depth0/depth1 (datasets or group '{index}')") \
        from e


def _load_npz(path, what):
  posed.require_file(path, what)
  with np.load(path) as z:
    return z["arr_0"]


def prepare(download, out, split, progress=True):
  import tqdm
  split_dir = posed.require_dir(os.path.join(download, split), f"the TA-WB {split}/ shards")
  cam_dir = posed.require_dir(os.path.join(download, f"{split}_camera_data"),
                               f"{split}_camera_data/")
  ext = [_load_npz(os.path.join(cam_dir, f"cam{i}_extrinsics.npz"), "4x4 c2w per pair")
         for i in (1, 2)]
  intr = [_load_npz(os.path.join(cam_dir, f"cam{i}_intrinsics.npz"), "3x3 K per pair")
          for i in (1, 2)]
  meta_path = posed.require_file(os.path.join(cam_dir, "metadata.json"),
                                  "pandas orient='split' metadata with img1_env")
  with open(meta_path) as f:
    table = json.load(f)
  try:
    col = table["columns"].index("img1_env")
    index = table.get("index", list(range(len(table["data"]))))
    envs = {int(i): row[col] for i, row in zip(index, table["data"])}
  except (KeyError, ValueError) as e:
    raise ValueError(f"{meta_path}: expected a split-oriented table with column img1_env") from e
  entries = tawb.read_index_maps(split_dir)
  open_files, written = {}, 0
  try:
    for pair, (fname, idx) in tqdm.tqdm(sorted(entries.items()), desc=split, disable=not progress):
      path = os.path.join(split_dir, fname)
      if path not in open_files:
        posed.require_file(path, "a TA-WB HDF5 shard")
        open_files[path] = h5py.File(path, "r")
      img0, img1, d0, d1 = _read_pair(open_files[path], idx, path)
      env = geometry_env(envs[pair])
      d = os.path.join(out, split, env)
      for sub in ("images", "depth", "camera_params", "poses"):
        os.makedirs(os.path.join(d, sub), exist_ok=True)
      cut = SKY.get(env, DEFAULT_SKY)
      for k, (img, depth) in enumerate(((img0, d0), (img1, d1))):
        name = f"{pair:08d}_{k}"
        img = np.clip(img, 0, 255).astype(np.uint8)
        p = os.path.join(d, "images", name + ".png")
        if not cv2.imwrite(p + ".tmp.png", img[..., ::-1]):
          raise OSError(f"{p}: cannot write")
        os.replace(p + ".tmp.png", p)
        depth = posed.sanitize_depth(depth)
        depth[depth >= cut] = 0
        exr.write_exr(os.path.join(d, "depth", name + ".exr"), depth)
        for sub, arr in (("camera_params", intr[k][pair]), ("poses", ext[k][pair])):
          q = os.path.join(d, sub, name + ".npy")
          with open(q + ".tmp", "wb") as f:
            np.save(f, np.asarray(arr, np.float64))
          os.replace(q + ".tmp", q)
      written += 1
  finally:
    for f in open_files.values():
      f.close()
  return written


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--download", required=True)
  p.add_argument("--out", required=True)
  p.add_argument("--split", default="test", choices=("train", "val", "test"))
  p.add_argument("--no_progress", action="store_true")
  args = p.parse_args(argv)
  n = prepare(args.download, args.out, args.split, not args.no_progress)
  print(f"extracted {n} {args.split} pairs to {os.path.join(args.out, args.split)}")
  return n


if __name__ == "__main__":
  main()
