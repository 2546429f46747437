"""TA-WB (TartanAir V2 wide-baseline pairs, UFM's benchmark / training pairs), extracted layout.

Layout under root (written by data/tawb/prepare.py from the Hugging Face release
`infinity1096/TA-WB-MapAnything`, or by the geometric sampler data/tawb/sample_pairs.py):
  <split>/<Env>/images/{pair:08d}_{view}.png          view in {0, 1}, RGB
  <split>/<Env>/depth/{pair:08d}_{view}.exr           z-depth metres, 0 = invalid (sky masked)
  <split>/<Env>/camera_params/{pair:08d}_{view}.npy   3x3 K (OpenCV)
  <split>/<Env>/poses/{pair:08d}_{view}.npy           4x4 camera-to-world (OpenCV)
Scene = Env, frame = `{pair:08d}_{view}`. Pairs: `<root>/pairs_<split>.txt` when present, else
every pair index with both views (the release's fixed pair list). Thresholds: TartanAir's row of
Table S1. `percentile_cut` (map-anything zeroes depth above the 95th percentile per image to drop
windows; default None = keep) is available for parity with that loader.

`tawb_official` reads the benchmark branch's TA-WB bench instead (official download_ta_wb.sh,
uniflowmatch/datasets/tartanair_assembled.py, widebaseline_datasets.py:188-230): HDF5 shards with
precomputed labels, the split `data`:
  <root>/data/*.json     index maps {"<sample>": [h5 file, index in file]} (or {"file_name",
                         "file_index"}); JSONs holding `forward_match_errors` are statistics
  <root>/data/*.h5       datasets indexed along their first axis: img0, img1 [H, W, 3] uint8,
                         flow_fwd [2, H, W], non_occluded_fwd, fov_mask_fwd,
                         occlusion_supervision_mask_fwd [H, W] bool
The bench takes samples 0..1499 (`__len__` = 1500) and brings them to 560x420 with
`_benchmark_branch.resize_short_center_crop`.
"""

from __future__ import annotations

import glob
import json
import os

import h5py
import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _benchmark_branch, exr, posed


def _load_npy(path, shape, what):
  posed.require_file(path, what)
  try:
    arr = np.load(path)
  except ValueError as e:
    raise ValueError(f"{path}: not a .npy array ({e})") from e
  if arr.shape != shape:
    raise ValueError(f"{path}: expected shape {shape} ({what}), got {arr.shape}")
  return arr.astype(np.float64)


def read_index_maps(split_dir) -> dict[int, tuple[str, int]]:
  """{sample: (h5 file name, index in file)} from every index-map JSON of a TA-WB HDF5 split
  (the official DistributedH5Reader format); statistics JSONs (`forward_match_errors`) and
  non-dict JSONs are skipped."""
  entries = {}
  for path in sorted(glob.glob(os.path.join(split_dir, "*.json"))):
    with open(path) as f:
      try:
        m = json.load(f)
      except ValueError as e:
        raise ValueError(f"{path}: not JSON ({e})") from e
    if not isinstance(m, dict) or "forward_match_errors" in m:
      continue
    for k, v in m.items():
      try:
        v = (v["file_name"], v["file_index"]) if isinstance(v, dict) else v
        entries[int(k)] = (str(v[0]), int(v[1]))
      except (KeyError, IndexError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: entry {k!r} is {v!r}, expected [h5 file, index]") from e
  if not entries:
    raise FileNotFoundError(f"{split_dir}: no index-map JSON (sample -> [h5 file, index])")
  return entries


@register("tawb")
class TAWB(posed.PosedPairSource):
  name = "tawb"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="test", pairs=None, thresholds=None, percentile_cut=None):
    super().__init__(root, split, pairs, thresholds)
    self.base = os.path.join(self.root, split)
    self.percentile_cut = percentile_cut

  def scenes(self):
    posed.require_dir(self.base, f"the TA-WB {self.split}/<Env>/ folders")
    return sorted(e for e in os.listdir(self.base)
                  if os.path.isdir(os.path.join(self.base, e, "images")))

  def frames(self, scene):
    return sorted(f[:-4] for f in os.listdir(os.path.join(self.base, scene, "images"))
                  if f.endswith(".png"))

  def default_pairs(self):
    scenes = self.scenes()
    if not scenes:
      raise FileNotFoundError(f"{self.base}: no TA-WB environments (<Env>/images/)")
    for env in scenes:
      names = set(self.frames(env))
      for n in sorted(names):
        if n.endswith("_0") and n[:-2] + "_1" in names:
          yield env, n, n[:-2] + "_1"

  def load_view(self, scene, frame):
    d = os.path.join(self.base, scene)
    image = io.read_image(os.path.join(d, "images", f"{frame}.png"))
    depth = posed.sanitize_depth(exr.read_exr(os.path.join(d, "depth", f"{frame}.exr")))
    if self.percentile_cut is not None and (depth > 0).any():
      depth[depth > np.percentile(depth[depth > 0], self.percentile_cut)] = 0
    K = _load_npy(os.path.join(d, "camera_params", f"{frame}.npy"), (3, 3), "3x3 intrinsics")
    c2w = _load_npy(os.path.join(d, "poses", f"{frame}.npy"), (4, 4), "4x4 camera-to-world")
    return posed.View(image, depth, K, c2w)


@register("tawb_official")
class TAWBOfficial:
  """The benchmark branch's TA-WB dense bench (module docstring): samples 0..num-1 of the HDF5
  split, their stored labels brought to the 560x420 crop. flow_valid = the branch's `valid_mask`
  (stored fov_mask AND the resized non_occluded), covisibility = its `covisible_mask`
  (non_occluded with the target inside the crop), covis_valid = the stored
  occlusion_supervision_mask AND non_occluded."""

  has_backward = False
  static_scene = False  # benchmark samples, not for the training pipeline
  KEYS = ("img0", "img1", "flow_fwd", "non_occluded_fwd", "fov_mask_fwd",
          "occlusion_supervision_mask_fwd")

  def __init__(self, root, split="data", num=1500, size=_benchmark_branch.BENCH_SIZE):
    if root is None:
      raise ValueError("tawb_official: a root is required (the official TA-WB/ folder)")
    self.dir = io.check_dir(os.path.join(os.fspath(root), split),
                            "TA-WB <split>/*.json index maps + *.h5 shards (download_ta_wb.sh)")
    index = read_index_maps(self.dir)
    n = min(int(num), len(index))
    missing = [k for k in range(n) if k not in index]
    if missing:
      raise ValueError(f"{self.dir}: the index maps lack samples {missing[:5]} of 0..{n - 1}")
    self.entries = [index[k] for k in range(n)]
    self.size = tuple(size)

  def __len__(self):
    return len(self.entries)

  def read(self, i) -> dict:
    fname, j = self.entries[i]
    path = posed.require_file(os.path.join(self.dir, fname), "a TA-WB HDF5 shard")
    with h5py.File(path, "r") as f:
      try:
        return {k: np.asarray(f[k][j]) for k in self.KEYS}
      except KeyError as e:
        raise ValueError(f"{path}: sample {i} (index {j}): missing {e}; expected datasets "
                         f"{', '.join(self.KEYS)}") from None

  def __getitem__(self, i):
    d = self.read(i)
    where = os.path.join(self.dir, self.entries[i][0])
    h, w = d["img0"].shape[:2]
    if d["img0"].shape != (h, w, 3) or d["img1"].shape != (h, w, 3):
      raise ValueError(f"{where}: sample {i}: images {d['img0'].shape}, {d['img1'].shape}, "
                       "expected two [H, W, 3]")
    if d["flow_fwd"].shape != (2, h, w):
      raise ValueError(f"{where}: sample {i}: flow_fwd is {d['flow_fwd'].shape}, expected "
                       f"{(2, h, w)}")
    masks = {}
    for key, name in (("non_occluded_fwd", "non_occluded"), ("fov_mask_fwd", "fov"),
                      ("occlusion_supervision_mask_fwd", "occlusion_supervision")):
      if d[key].shape != (h, w):
        raise ValueError(f"{where}: sample {i}: {key} is {d[key].shape}, expected {(h, w)}")
      masks[name] = d[key].astype(bool)
    flow = np.moveaxis(d["flow_fwd"].astype(np.float32), 0, -1)
    io.require_finite(flow, f"{where} sample {i}", masks["fov"])
    im0, im1, flow, m = _benchmark_branch.resize_short_center_crop(
        d["img0"].astype(np.uint8), d["img1"].astype(np.uint8), flow, masks, self.size)
    meta = dict(dataset="tawb_official", scene="data", frame0=f"{i:06d}_0", frame1=f"{i:06d}_1",
                index=i, gt_relpath=f"{i:06d}.flo")
    return dict(image0=im0, image1=im1, flow=flow, covisibility=m["non_occluded"],
                flow_valid=m["fov"], covis_valid=m["occlusion_supervision"], meta=meta)
