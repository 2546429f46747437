"""Readers shared by the official processed layouts (UFM's `preprocess_datasets/`, DUSt3R's
preprocessing, the authors' Hugging Face mirror): npz and distributed-h5 files, and the
precomputed-label sample dict of the official flow datasets.

The official flow datasets (FlyingThings3D, Monkaa, Spring, HD1K, TA-WB training shards) store
per view: flow (2, H, W) or (H, W, 2), `fov_mask`, `non_occluded_mask` (= covisible) and
`occlusion_supervision_mask` (where the covisibility BCE is evaluated). In our sample dict:
covisibility = non_occluded_mask, covis_valid = occlusion_supervision_mask, flow_valid = finite
flow (the official losses read the non-occluded mask, or for the 980 recipe every pixel whose
target lies near the image, from the flow itself), and the extra key `fov_mask` keeps the
official fov mask for the official resize / crop (`augment.official_no_aug` and the official
augmentation AND it with the covisibility).

Every reader raises ValueError naming the file (and key / index) for a damaged file and
FileNotFoundError for a missing one, so the training pipeline skips, counts and logs the sample.
"""

from __future__ import annotations

import glob
import json
import logging
import os
import re
import zipfile
import zlib
from typing import Iterable, Mapping

import cv2
import numpy as np

from ufm_jax.data import decode, io
from ufm_jax.data.sources import exr, posed
from ufm_jax.geometry import camera

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------- DUSt3R-processed views

def find_pairs_file(root: str, name: str, given: str | None = None) -> str:
  """The DUSt3R pair file of a processed root: `given`, else `<root>/<name>`, else
  `<root>/../dust3r_data_pairs/<name>` (the official `root_data_dir` layout)."""
  if given:
    return posed.require_file(os.path.expanduser(given), f"the DUSt3R pair file {name}")
  candidates = (os.path.join(root, name),
                os.path.join(os.path.dirname(os.path.abspath(root)), "dust3r_data_pairs", name))
  for c in candidates:
    if os.path.isfile(c):
      return c
  raise FileNotFoundError(f"{candidates[1]}: missing DUSt3R pair file (also looked for "
                          f"{candidates[0]}); see data/{os.path.basename(name).split('_')[0]}/"
                          "README.md")


def processed_view(stem: str, keys) -> posed.View:
  """A DUSt3R-processed view: `<stem>.jpg`, `<stem>.exr` (z-depth), `<stem>.npz` with K under
  keys[0][0] and the camera-to-world pose as keys[1] = (4x4,) or (R, t); float32 like the
  official readers (`np.float32(...)`, a float32 eye(4) filled with R and t)."""
  cam = load_npz(stem + ".npz", keys[0] + keys[1])
  K = np.asarray(cam[keys[0][0]], np.float32)
  pose = np.eye(4, dtype=np.float32)
  if len(keys[1]) == 1:
    pose = np.asarray(cam[keys[1][0]], np.float32)
  else:
    pose[:3, :3] = cam[keys[1][0]]
    pose[:3, 3] = cam[keys[1][1]]
  if K.shape != (3, 3) or pose.shape != (4, 4):
    raise ValueError(f"{stem}.npz: expected 3x3 intrinsics and a 4x4 pose, got {K.shape}, "
                     f"{pose.shape}")
  image = io.read_image(stem + ".jpg")
  depth = posed.sanitize_depth(exr.read_exr(stem + ".exr"))
  return posed.check_view(posed.View(image, depth, K.astype(np.float64), pose.astype(np.float64)),
                          stem)


# ------------------------------------------------------------------------------------------ npz

def load_npz(path: str, keys: Iterable[str] | None = None, allow_pickle: bool = False) -> dict:
  """{key: array} of an .npz (all keys, or `keys`, each required)."""
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: file not found")
  try:
    with np.load(path, allow_pickle=allow_pickle) as z:
      names = list(z.keys())
      want = names if keys is None else list(keys)
      missing = [k for k in want if k not in names]
      if missing:
        raise KeyError(f"{path}: no key {missing[0]!r} (keys: {names})")
      return {k: z[k] for k in want}
  except KeyError as e:
    raise ValueError(e.args[0]) from None
  except (zipfile.BadZipFile, EOFError, OSError, ValueError, zlib.error) as e:
    raise ValueError(f"{path}: not a readable .npz ({type(e).__name__}: {e})") from None


def load_npy(path: str, what: str | None = None, shape=None, allow_pickle: bool = False
             ) -> np.ndarray:
  """A .npy array, with its path (and `what` it should hold) in every error; `shape`: reshaped
  to it, refused unless it has that many elements."""
  expected = f" (expected {what})" if what else ""
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: file not found{expected}")
  try:
    arr = np.load(path, allow_pickle=allow_pickle)
  except (OSError, ValueError, EOFError) as e:
    raise ValueError(f"{path}: not a readable .npy ({type(e).__name__}: {e})") from None
  if shape is None:
    return arr
  if arr.size != int(np.prod(shape)):
    raise ValueError(f"{path}: expected {what or 'an array'} of shape {tuple(shape)}, got "
                     f"{arr.shape}")
  return arr.reshape(shape)


# ---------------------------------------------------------------------------- distributed h5

def read_index_maps(folder) -> dict[int, tuple[str, int]]:
  """{sample: (h5 file name, index in file)} from every index-map JSON of a folder in the
  official `DistributedH5Reader` format (uniflowmatch/datasets/utils/distributed_h5.py): entries
  [file name, index in file] or {file_name, file_index}; JSONs that are not such a dict, or hold
  `forward_match_errors` (TA-WB's statistics, match_errors.json), are not index maps."""
  entries = {}
  for path in sorted(glob.glob(os.path.join(folder, "*.json"))):
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
    raise FileNotFoundError(f"{folder}: no index-map JSON (sample -> [h5 file, index])")
  return entries


class H5Index:
  """The official `DistributedH5Reader`: the index maps of `folder` (`read_index_maps`), or
  `entries`."""

  def __init__(self, folder: str, entries: Mapping[int, tuple[str, int]] | None = None):
    self.folder = folder
    if entries is None:
      entries = read_index_maps(folder)
    self.entries = dict(entries)
    if not self.entries:
      raise FileNotFoundError(f"{folder}: no entries mapping sample index -> (h5 file, index)")
    self.keys = sorted(self.entries)

  def __len__(self):
    return len(self.entries)

  def location(self, index: int) -> tuple[str, int]:
    if index not in self.entries:
      raise KeyError(f"{self.folder}: index {index} is in no index map")
    name, pos = self.entries[index]
    return os.path.join(self.folder, name), pos

  def read(self, index: int, keys: Iterable[str]) -> dict:
    path, pos = self.location(index)
    return read_h5_row(path, pos, keys)


def read_h5_row(path: str, pos: int, keys: Iterable[str]) -> dict:
  """{key: dataset[pos]} of an HDF5 file; errors name the file, key and row."""
  import h5py  # pylint: disable=g-import-not-at-top
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: h5 file not found")
  out = {}
  try:
    with h5py.File(path, "r") as f:
      for k in keys:
        if k not in f:
          raise KeyError(f"{path}: no dataset {k!r} (datasets: {sorted(f.keys())})")
        ds = f[k]
        if not 0 <= pos < ds.shape[0]:
          raise ValueError(f"{path}: row {pos} of {k!r} out of range ({ds.shape[0]} rows)")
        out[k] = decode.h5_row(ds, pos, f"{path}: ")
  except KeyError as e:
    raise ValueError(e.args[0]) from None
  except (OSError, RuntimeError) as e:  # h5py's errors for truncated or damaged files
    raise ValueError(f"{path}: not a readable HDF5 file ({e})") from None
  return out


def h5_ranges(folder: str) -> list[tuple[int, int, str]]:
  """(first, last, file name) of the `<first>_<last>.h5` files the official preprocess writes."""
  out = []
  for name in os.listdir(folder):
    m = re.fullmatch(r"(\d+)_(\d+)\.h5", name)
    if m:
      out.append((int(m.group(1)), int(m.group(2)), name))
  return sorted(out)


# ------------------------------------------------------------------------- precomputed labels

def hwc_flow(flow, where: str, layout: str = "chw") -> np.ndarray:
  """Stored flow -> [H, W, 2] float32 (NaN kept). layout 'chw' = (2, H, W); 'auto' = the
  official FlyingThings3D rule: (H, W, 2) when the last axis is 2, else (2, H, W)."""
  flow = np.asarray(flow)
  hwc = layout == "auto" and flow.ndim == 3 and flow.shape[-1] == 2
  if flow.ndim != 3 or (flow.shape[-1] if hwc else flow.shape[0]) != 2:
    raise ValueError(f"{where}: flow must be (2, H, W){' or (H, W, 2)' if layout == 'auto' else ''}"
                     f", got {flow.shape}")
  if hwc:
    return np.ascontiguousarray(flow, np.float32)
  # cv2.merge interleaves the planes several times faster than numpy's moveaxis copy.
  return cv2.merge([np.ascontiguousarray(p, np.float32) for p in flow])


def precomputed_sample(dataset: str, image0, image1, flow, non_occluded, occlusion_supervision,
                       fov, where: str, flow_layout: str = "chw", **meta) -> dict:
  """The sample dict of one direction of an official flow dataset (see module docstring)."""
  flow = hwc_flow(flow, where, flow_layout)
  hw = flow.shape[:2]
  masks = []
  for name, m in (("non_occluded_mask", non_occluded), ("occlusion_supervision_mask",
                                                        occlusion_supervision), ("fov_mask", fov)):
    m = np.asarray(m)
    if m.shape != hw:
      raise ValueError(f"{where}: {name} is {m.shape}, flow is {hw}")
    masks.append(m.astype(bool, copy=False))
  for k, im in (("image0", image0), ("image1", image1)):
    if np.asarray(im).shape[:2] != hw:
      raise ValueError(f"{where}: {k} is {np.asarray(im).shape}, flow is {hw}")
  flow_valid = camera.finite_pixels(flow)
  return dict(image0=np.ascontiguousarray(image0), image1=np.ascontiguousarray(image1),
              flow=flow, covisibility=masks[0], flow_valid=flow_valid, covis_valid=masks[1],
              fov_mask=masks[2], meta=dict(dataset=dataset, where=where, **meta))


def rgb_u8(image, where: str) -> np.ndarray:
  """An (H, W, 3|4) uint8 array as stored -> (H, W, 3) uint8 (the official readers keep
  [..., :3])."""
  a = np.asarray(image)
  if a.ndim != 3 or a.shape[2] < 3 or a.dtype != np.uint8:
    raise ValueError(f"{where}: expected an (H, W, 3) uint8 image, got {a.shape} {a.dtype}")
  return np.ascontiguousarray(a[..., :3])


# The per-view label arrays of the official flow datasets, in `precomputed_sample`'s order.
LABELS = ("flow", "non_occluded_mask", "occlusion_supervision_mask", "fov_mask")


def two_directions(dataset: str, image0, image1, label, where: str, flow_layout: str = "chw",
                   **meta) -> list[dict]:
  """[forward, backward] sample dicts of a pair whose views carry precomputed labels;
  label(name, view) -> that view's array of LABELS (view 0 = forward)."""
  out = []
  for v, (x0, x1) in enumerate(((image0, image1), (image1, image0))):
    out.append(precomputed_sample(dataset, x0, x1, *(label(q, v) for q in LABELS), where=where,
                                  flow_layout=flow_layout, direction=("forward", "backward")[v],
                                  layout="official", **meta))
  return out


class PrecomputedPairs:
  """Mixin of the official flow datasets: `_views(i)` -> [forward, backward] from one read."""

  has_backward = True
  static_scene = False

  def __getitem__(self, index):
    return self._views(index)[0]

  def backward(self, index):
    return self._views(index)[1]

  def both(self, index):
    fwd, bwd = self._views(index)
    return fwd, bwd


# --------------------------------------------------------------------- official static readers

class OfficialPosed:
  """Mixin of the official static (depth + pose) readers, before posed.PosedPairSource.

  Pairs come from `_official_pairs()` (the official pair file; a list given as `pairs` replaces
  it); `pairs_file` names a DUSt3R pair file found by `find_pairs_file` (or given as
  `pair_metadata_path`). meta carries what the official dataset class attaches to each view and
  its flow post-processing reads (the rendering parameters of the covisibility test, whether the
  pair may train the refiner)."""

  suitable_for_refinement = False
  pairs_file: str | None = None

  def __init__(self, root, split="train", pairs=None, thresholds=None, pair_metadata_path=None):
    super().__init__(root, split, pairs, thresholds)
    self.pairs_path = None
    if self.pairs_file and not isinstance(pairs, (list, tuple)):
      self.pairs_path = find_pairs_file(self.root, self.pairs_file, pair_metadata_path or pairs)

  @property
  def pairs(self):
    if self._pairs is None:
      self._pairs = (list(map(tuple, self._pairs_arg)) if isinstance(self._pairs_arg, (list, tuple))
                     else list(self._official_pairs()))
      if not self._pairs:
        raise ValueError(f"{self.pairs_path or self.root}: no {self.name} pairs for split "
                         f"{self.split!r}")
    return self._pairs

  def _official_pairs(self):
    raise NotImplementedError

  def __getitem__(self, i):
    sample = super().__getitem__(i)
    sample["meta"].update(official_meta(self))
    return sample


def official_meta(source) -> dict:
  """meta of an official static sample: the dataset's covisibility rendering parameters
  [absolute, temperature, relative] (geometry.RENDERING_PARAMETERS) and the refiner flag."""
  from ufm_jax import geometry  # pylint: disable=g-import-not-at-top
  return dict(layout="official", covisible_rendering_parameters=np.array(
      geometry.rendering_parameters(source.name), np.float32),
              suitable_for_refinement=bool(source.suitable_for_refinement))
