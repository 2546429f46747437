"""Per-dataset sample load time: CPU ms per sample of every reader on a tree at a given shape.

  python benchmarks/source_load.py                   # all readers, 560x420 trees
  python benchmarks/source_load.py --shape 420,560 --repeats 10 --datasets blendedmvs,spring
  python benchmarks/source_load.py --native          # flow readers at their datasets' real sizes
  python benchmarks/source_load.py --opencv_png      # every PNG through cv2.imread instead

Each reader gets a one-pair tree written in its dataset's on-disk format (the wide-baseline trees
of ufm_jax/testing/wide_trees.py: a textured plane with depth holes; the flow trees below:
smooth textures and flow fields with invalid regions), then `source[0]` is timed: file decoding,
depth conversion, flow/covisibility labels, everything the training pipeline pays per sample.
The figure is CPU time (time.process_time) of a single-threaded process (OpenCV and BLAS threads
set to 1), the minimum over `--repeats` loads, so other processes on a shared machine inflate it
less than wall time. Issue 7's budget is < 50 ms per sample at the 560 training shape.
Prints figures, asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
  os.environ.setdefault(_var, "1")

import cv2  # pylint: disable=g-import-not-at-top
import numpy as np  # pylint: disable=g-import-not-at-top

from ufm_jax import data  # pylint: disable=g-import-not-at-top
from ufm_jax.data import io  # pylint: disable=g-import-not-at-top

# Native frame sizes (H, W) of the flow datasets (for --native).
NATIVE = {"flyingchairs": (384, 512), "flyingthings": (540, 960), "monkaa": (540, 960),
          "sintel_clean": (436, 1024), "spring": (1080, 1920), "hd1k": (1080, 2560),
          "kitti2015": (375, 1242)}


def _image(hw, seed):
  """Smooth colour texture (compresses like a rendered frame, unlike noise)."""
  h, w = hw
  v, u = np.mgrid[0:h, 0:w].astype(np.float32)
  a = np.random.default_rng(seed).uniform(0.01, 0.08, 6).astype(np.float32)
  chans = [np.sin(a[0] * u + a[1] * v), np.cos(a[2] * u - a[3] * v), np.sin(a[4] * u * a[5] * v)]
  return np.clip(128 + 110 * np.stack(chans, -1), 0, 255).astype(np.uint8)


def _flow(hw, seed, scale=1.0):
  h, w = hw
  v, u = np.mgrid[0:h, 0:w].astype(np.float32)
  a = np.random.default_rng(seed).uniform(-1, 1, 4).astype(np.float32)
  f = np.stack([8 * a[0] + 0.01 * a[1] * u, 5 * a[2] + 0.01 * a[3] * v], -1) * np.float32(scale)
  return f.astype(np.float32)


def _mk(path):
  os.makedirs(os.path.dirname(path), exist_ok=True)
  return path


def write_flyingthings(root, hw, scene="TRAIN/A/0000", frames=(6, 7)):
  for k, fr in enumerate(frames):
    io.write_image(_mk(f"{root}/frames_cleanpass/{scene}/left/{fr:04d}.png"), _image(hw, fr))
    disp = 20 + 10 * _image(hw, 50 + k)[..., 0].astype(np.float32) / 255
    io.write_pfm(_mk(f"{root}/disparity/{scene}/left/{fr:04d}.pfm"), disp)
    flow3 = np.concatenate([_flow(hw, fr), np.zeros(hw + (1,), np.float32)], -1)
    for into, word in (("into_future", "Future"), ("into_past", "Past")):
      io.write_pfm(_mk(f"{root}/optical_flow/{scene}/{into}/left/"
                       f"OpticalFlowInto{word}_{fr:04d}_L.pfm"), flow3)
      io.write_pfm(_mk(f"{root}/disparity_change/{scene}/{into}/left/{fr:04d}.pfm"),
                   np.full(hw, 0.1, np.float32))


def write_flyingchairs(root, hw):
  for j in (1, 2):
    img = _image(hw, j)
    with open(_mk(f"{root}/data/00001_img{j}.ppm"), "wb") as f:
      f.write(f"P6\n{hw[1]} {hw[0]}\n255\n".encode() + img.tobytes())
  io.write_flo(f"{root}/data/00001_flow.flo", _flow(hw, 0))
  with open(f"{root}/chairs_split.txt", "w") as f:
    f.write("1\n")


def write_sintel(root, hw):
  for k in (1, 2):
    io.write_image(_mk(f"{root}/training/clean/alley_1/frame_{k:04d}.png"), _image(hw, k))
  io.write_flo(_mk(f"{root}/training/flow/alley_1/frame_0001.flo"), _flow(hw, 1))
  occ = _image(hw, 9)[..., 0] > 200
  io.write_mask(_mk(f"{root}/training/occlusions/alley_1/frame_0001.png"), occ)
  io.write_mask(_mk(f"{root}/training/invalid/alley_1/frame_0001.png"), np.zeros(hw, bool))


def write_spring(root, hw):
  seq = f"{root}/train/0001"
  h, w = hw
  for k in (1, 2):
    io.write_image(_mk(f"{seq}/frame_left/frame_left_{k:04d}.png"), _image(hw, k))
  mm = np.zeros((2 * h, 2 * w, 3), np.uint8)
  mm[h:, :w // 3, 0] = 255
  # FW 0001 (1 -> 2) and BW 0002 (2 -> 1): what a symmetrized training batch reads.
  for fb, frame, scale in (("FW", 1, 1.0), ("BW", 2, -1.0)):
    full = _flow((2 * h, 2 * w), 3, scale=scale)
    full[: h // 4, : w // 4] = np.nan  # no GT there
    io.write_flo5(_mk(f"{seq}/flow_{fb}_left/flow_{fb}_left_{frame:04d}.flo5"), full)
    io.write_image(_mk(f"{seq}/maps/matchmap_flow_{fb}_left/matchmap_flow_{fb}_left_{frame:04d}.png"), mm)
  os.makedirs(f"{seq}/cam_data")
  with open(f"{seq}/cam_data/intrinsics.txt", "w") as f:
    f.write(f"{w} {w} {w / 2} {h / 2}\n" * 2)


def write_hd1k(root, hw):
  for fr in (0, 1):
    io.write_image(_mk(f"{root}/hd1k_input/image_2/000000_{fr:04d}.png"), _image(hw, fr))
  valid = _image(hw, 7)[..., 1] > 60  # sparse-ish GT
  io.write_kitti_flow(_mk(f"{root}/hd1k_flow_gt/flow_occ/000000_0000.png"), _flow(hw, 0), valid)


def write_kitti(root, hw):
  t = f"{root}/training"
  io.write_image(_mk(f"{t}/image_2/000000_10.png"), _image(hw, 1))
  io.write_image(_mk(f"{t}/image_2/000000_11.png"), _image(hw, 2))
  valid = _image(hw, 7)[..., 1] > 60
  io.write_kitti_flow(_mk(f"{t}/flow_occ/000000_10.png"), _flow(hw, 0), valid)
  io.write_kitti_flow(_mk(f"{t}/flow_noc/000000_10.png"), _flow(hw, 0), valid & (_flow(hw, 0)[..., 0] > 0))


def flow_trees(hw, native=False):
  """(dataset, writer(root), get_source kwargs) for the flow readers."""
  size = (lambda name: NATIVE[name]) if native else (lambda name: hw)
  return [
      ("flyingchairs", lambda r: write_flyingchairs(r, size("flyingchairs")), {"split": "train"}),
      ("flyingthings", lambda r: write_flyingthings(r, size("flyingthings")), {}),
      ("monkaa", lambda r: write_flyingthings(r, size("monkaa"), scene="a_rain_of_stones_x2"), {}),
      ("sintel_clean", lambda r: write_sintel(r, size("sintel_clean")), {}),
      ("spring", lambda r: write_spring(r, size("spring")), {"cameras": ("left",)}),
      ("hd1k", lambda r: write_hd1k(r, size("hd1k")), {}),
      ("kitti2015", lambda r: write_kitti(r, size("kitti2015")), {}),
  ]


def all_trees(hw, native=False):
  from ufm_jax.testing import wide_trees as wide  # pylint: disable=g-import-not-at-top
  return [(n, w, k, "wide") for n, w, k in wide.timing_trees(hw)] + \
      [(n, w, k, "flow") for n, w, k in flow_trees(hw, native)]


def measure(hw=(420, 560), repeats=5, datasets=None, native=False, progress=True):
  """{dataset: (CPU ms/sample (min over repeats), wall ms (min), sample shape)}."""
  cv2.setNumThreads(1)
  out = {}
  for name, writer, kwargs, _ in all_trees(hw, native):
    if datasets and name not in datasets:
      continue
    with tempfile.TemporaryDirectory() as tmp:
      writer(tmp)
      src = data.get_source(name, tmp, **kwargs)
      sample = src[0]  # warm-up: file-system cache, lazy imports, per-source caches
      cpu, wall = [], []
      for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        src[0]
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - t)
      out[name] = (1e3 * min(cpu), 1e3 * min(wall), sample["image0"].shape[:2])
      if progress:
        print(f"{name:14s} {out[name][0]:8.1f} ms CPU  {out[name][1]:8.1f} ms wall  "
              f"({out[name][2][1]}x{out[name][2][0]})", flush=True)
  return out


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--shape", default="420,560", help="H,W of the trees (default the 560 shape)")
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--datasets", default="", help="comma list (default: all readers)")
  p.add_argument("--native", action="store_true",
                 help="flow readers at their datasets' native sizes instead of --shape")
  p.add_argument("--opencv_png", action="store_true",
                 help="decode every PNG with cv2.imread instead of ufm_jax.data.decode's own PNG "
                      "path, to measure what that path saves")
  args = p.parse_args(argv)
  if args.opencv_png:
    from ufm_jax.data import decode  # pylint: disable=g-import-not-at-top
    decode.decode_png = lambda buf, rgb=True: None  # "not a layout handled here": OpenCV decodes
  hw = tuple(int(x) for x in args.shape.split(","))
  print(f"CPU ms per sample, single thread, min of {args.repeats} (budget < 50 ms at 560x420)")
  measure(hw, args.repeats, [d for d in args.datasets.split(",") if d], args.native)


if __name__ == "__main__":
  main()
