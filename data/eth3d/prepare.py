"""ETH3D high-res multi-view (training scenes) -> the tree the `eth3d` source reads.

  python data/eth3d/prepare.py --raw /data/eth3d_raw --out /data/eth3d --scale 0.25

Input (the official `<scene>_dslr_undistorted.7z` and `<scene>_dslr_depth.7z`, plus
`<scene>_dslr_jpg.7z` for the distorted calibration, unpacked into --raw):
  <scene>/images/dslr_images_undistorted/DSC_*.JPG
  <scene>/dslr_calibration_undistorted/{cameras,images}.txt   PINHOLE, COLMAP convention, w2c
  <scene>/dslr_calibration_jpg/cameras.txt                     THIN_PRISM_FISHEYE (same poses)
  <scene>/ground_truth_depth/dslr_images/DSC_*.JPG             raw float32 z-depth (metres),
                                                               W x H of the distorted image,
                                                               inf / nan = no ground truth
The GT depth is aligned with the distorted images, so each output pixel (undistorted PINHOLE
geometry, scaled by --scale) is mapped through COLMAP's THIN_PRISM_FISHEYE model into the
distorted image and takes the nearest depth there (z is unchanged: same camera frame).
Output (read by ufm_jax/data/sources/eth3d.py):
  <out>/<scene>/scene_meta.json, images/<DSC_x>.jpg, depth/<DSC_x>.exr
  <out>/pairs_test.txt   every view pair of a scene with mutual covisibility > --min_covis

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import json
import os

import cv2
import numpy as np

from ufm_jax import data
from ufm_jax.data import io
from ufm_jax.data.sources import exr, posed


def thin_prism_fisheye_project(params, x, y):
  """COLMAP THIN_PRISM_FISHEYE: normalised image-plane coordinates -> pixel (COLMAP convention).
  params = fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1."""
  fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1 = params
  r = np.sqrt(x * x + y * y)
  safe = np.where(r > np.finfo(float).eps, r, 1.0)
  theta = np.arctan(r)
  uu = np.where(r > np.finfo(float).eps, theta * x / safe, x)
  vv = np.where(r > np.finfo(float).eps, theta * y / safe, y)
  u2, uv, v2 = uu * uu, uu * vv, vv * vv
  r2 = u2 + v2
  radial = k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3 + k4 * r2 ** 4
  du = uu * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2) + sx1 * r2
  dv = vv * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2) + sy1 * r2
  return fx * (uu + du) + cx, fy * (vv + dv) + cy


def read_raw_depth(path, width, height):
  posed.require_file(path, f"raw float32 ETH3D depth of {width}x{height}")
  d = np.fromfile(path, "<f4")
  if d.size != width * height:
    raise ValueError(f"{path}: {d.size} floats, expected {width}x{height} (the distorted image)")
  return posed.sanitize_depth(d.reshape(height, width))


def undistorted_depth(depth_d, cam_d, K_out, hw_out):
  """Depth in the output PINHOLE geometry (OpenCV K_out) by nearest lookup in the distorted map."""
  h, w = hw_out
  v, u = np.mgrid[0:h, 0:w].astype(np.float64)
  x = (u - K_out[0, 2]) / K_out[0, 0]
  y = (v - K_out[1, 2]) / K_out[1, 1]
  pu, pv = thin_prism_fisheye_project(cam_d["params"], x, y)
  pu, pv = pu - 0.5, pv - 0.5  # COLMAP -> pixel centres at integers
  hd, wd = depth_d.shape
  ok = (pu >= -0.5) & (pu < wd - 0.5) & (pv >= -0.5) & (pv < hd - 0.5)
  iu = np.clip(np.rint(pu), 0, wd - 1).astype(np.int64)
  iv = np.clip(np.rint(pv), 0, hd - 1).astype(np.int64)
  return np.where(ok, depth_d[iv, iu], 0).astype(np.float32)


def prepare_scene(raw, out, scene, scale, progress=True):
  import tqdm
  base = os.path.join(raw, scene)
  und = os.path.join(base, "dslr_calibration_undistorted")
  cams_u = posed.read_colmap_cameras(os.path.join(und, "cameras.txt"))
  imgs_u = posed.read_colmap_images(os.path.join(und, "images.txt"))
  cams_d_path = os.path.join(base, "dslr_calibration_jpg", "cameras.txt")
  cams_d = posed.read_colmap_cameras(cams_d_path)
  imgs_d_path = os.path.join(base, "dslr_calibration_jpg", "images.txt")
  imgs_d = posed.read_colmap_images(imgs_d_path) if os.path.isfile(imgs_d_path) else {}
  cam_of_d = {os.path.basename(k): v["camera_id"] for k, v in imgs_d.items()}
  os.makedirs(os.path.join(out, scene, "images"), exist_ok=True)
  os.makedirs(os.path.join(out, scene, "depth"), exist_ok=True)
  frames = []
  for name, entry in tqdm.tqdm(sorted(imgs_u.items()), desc=scene, disable=not progress):
    stem = os.path.splitext(os.path.basename(name))[0]
    cu = cams_u[entry["camera_id"]]
    if cu["model"] != "PINHOLE":
      raise ValueError(f"{und}/cameras.txt: camera {entry['camera_id']} is {cu['model']}, "
                       "expected PINHOLE")
    cd = cams_d.get(cam_of_d.get(os.path.basename(name), entry["camera_id"]))
    if cd is None or cd["model"] != "THIN_PRISM_FISHEYE":
      raise ValueError(f"{cams_d_path}: no THIN_PRISM_FISHEYE camera for {name}")
    img = io.read_image(os.path.join(base, "images", name))
    h, w = round(cu["height"] * scale), round(cu["width"] * scale)
    K = posed.colmap_to_opencv_K(posed.colmap_K(cu, und))
    K_out = K.copy()
    K_out[:2, :2] *= scale
    K_out[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
    K_out[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
    if img.shape[:2] != (cu["height"], cu["width"]):
      raise ValueError(f"{os.path.join(base, 'images', name)}: image is {img.shape[:2]}, "
                       f"cameras.txt says {(cu['height'], cu['width'])}")
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if (h, w) != img.shape[:2] else img
    depth_d = read_raw_depth(os.path.join(base, "ground_truth_depth", "dslr_images",
                                          os.path.basename(name)), cd["width"], cd["height"])
    depth = undistorted_depth(depth_d, cd, K_out, (h, w))
    jpg = os.path.join(out, scene, "images", stem + ".jpg")
    if not cv2.imwrite(jpg + ".tmp.jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95]):
      raise OSError(f"{jpg}: cannot write")
    os.replace(jpg + ".tmp.jpg", jpg)
    exr.write_exr(os.path.join(out, scene, "depth", stem + ".exr"), depth)
    frames.append(dict(frame_name=stem, file_path=f"images/{stem}.jpg", depth=f"depth/{stem}.exr",
                       transform_matrix=np.linalg.inv(entry["w2c"]).tolist(), h=h, w=w,
                       fl_x=K_out[0, 0], fl_y=K_out[1, 1], cx=K_out[0, 2], cy=K_out[1, 2]))
  meta = dict(scene_name=scene, dataset_name="eth3d", camera_model="PINHOLE",
              camera_convention="opencv", scale_type="metric", frames=frames,
              note=f"prepared by data/eth3d/prepare.py at scale {scale}")
  path = os.path.join(out, scene, "scene_meta.json")
  with open(path + ".tmp", "w") as f:
    json.dump(meta, f)
  os.replace(path + ".tmp", path)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--raw", required=True)
  p.add_argument("--out", required=True)
  p.add_argument("--scale", type=float, default=0.25, help="output size / 6048x4032")
  p.add_argument("--scenes", nargs="*", default=None)
  p.add_argument("--min_covis", type=float, default=0.1)
  p.add_argument("--max_side", type=int, default=128)
  p.add_argument("--no_progress", action="store_true")
  args = p.parse_args(argv)
  posed.require_dir(args.raw, "the unpacked ETH3D multi-view training archives")
  scenes = args.scenes or sorted(
      s for s in os.listdir(args.raw)
      if os.path.isdir(os.path.join(args.raw, s, "dslr_calibration_undistorted")))
  if not scenes:
    raise SystemExit(f"{args.raw}: no <scene>/dslr_calibration_undistorted/ folders")
  for scene in scenes:
    prepare_scene(args.raw, args.out, scene, args.scale, not args.no_progress)
  src = data.get_source("eth3d", args.out)
  pairs, skipped = posed.mine_pairs(src, scenes, args.min_covis, args.max_side,
                                     progress=not args.no_progress)
  out = os.path.join(args.out, "pairs_test.txt")
  posed.write_pair_list(out, pairs, header=(
      f"ETH3D test pairs: all view pairs with mutual covisibility > {args.min_covis}\n"
      "scene frame0 frame1 score"))
  print(f"prepared {len(scenes)} scenes, {len(pairs)} pairs -> {out}; {len(skipped)} skipped")
  return out


if __name__ == "__main__":
  main()
