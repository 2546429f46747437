"""`pairs_folder`: the project's own pair-folder format (custom user data, synthetic dumps).

Layout (see data/pairs_folder/README.md):
  <root>[/<split>]/<pair>/image0.png image1.png flow.flo      required (flow.flo not for
                                                               distillation: `images(i)`)
                          covisibility.png flow_valid.png covis_valid.png   optional, 0/255
                          meta.json depth.npz (depth0, depth1)              optional
                          reverse/flow.flo [+ the three masks]              optional, 1 -> 0 labels
Pairs are the sub-folders holding an image0.png, in sorted order (names starting with "." are
skipped: folders still being written). When `<root>/<split>` exists it
is used, otherwise `root` itself (a flat folder of pairs serves every split).
Flow with no value (NaN/Inf, or |u|, |v| > 1e9: the Middlebury unknown marker) is invalid; where
flow_valid.png marks it valid the sample is corrupt (ValueError). Missing masks: flow_valid = flow
with a value; covisibility = the FoV mask of the flow with
covis_valid all False (unknown covisibility never trains the covisibility head, like
FlyingChairs); covis_valid when only covisibility.png is given = all True.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ufm_jax.data import decode
from ufm_jax.data.io import FLO_UNKNOWN, read_flo
from ufm_jax.data.registry import register
from ufm_jax.geometry.masks import fov_mask_from_flow

_ARRAY_META = ("K0", "K1", "cam2world0", "cam2world1")


def _read_rgb(path):
  img = decode.imread_unchanged(path, rgb=True)
  if img is None:
    raise ValueError(f"{path}: missing or unreadable image (expected an RGB PNG)")
  if img.dtype != np.uint8:
    raise ValueError(f"{path}: expected 8-bit image, got {img.dtype}")
  if img.ndim == 2:
    img = np.repeat(img[..., None], 3, axis=-1)
  elif img.shape[2] == 4:
    img = img[..., :3]
  if img.shape[2] != 3:
    raise ValueError(f"{path}: expected 3 channels, got shape {img.shape}")
  return np.ascontiguousarray(img)


def _read_mask(path, shape):
  m = decode.imread_unchanged(path)
  if m is None:
    raise ValueError(f"{path}: unreadable mask PNG (expected 0/255 single channel)")
  if m.ndim == 3:
    m = m[..., 0]
  if m.shape != tuple(shape):
    raise ValueError(f"{path}: mask shape {m.shape} differs from image0 shape {tuple(shape)}")
  return m > (127 if m.dtype == np.uint8 else 32767)


def read_labels(folder: str, shape, target_shape) -> dict:
  """flow + masks of one direction stored in `folder`."""
  path = os.path.join(folder, "flow.flo")
  if not os.path.isfile(path):
    raise ValueError(f"{path}: missing (every pair needs flow.flo, source -> target)")
  flow = read_flo(path)
  if flow.shape[:2] != tuple(shape):
    raise ValueError(f"{path}: flow shape {flow.shape[:2]} differs from image0 shape {tuple(shape)}")
  opt = {}
  for key in ("covisibility", "flow_valid", "covis_valid"):
    p = os.path.join(folder, f"{key}.png")
    if os.path.isfile(p):
      opt[key] = _read_mask(p, shape)
  with np.errstate(invalid="ignore"):
    known = (np.abs(flow) <= FLO_UNKNOWN).all(-1)  # False for NaN/Inf and the 1e10 marker
  if "flow_valid" in opt:
    bad = int((opt["flow_valid"] & ~known).sum())
    if bad:  # the labels contradict each other: a damaged or mis-exported file
      raise ValueError(f"{path}: no flow (NaN/Inf or |u|, |v| > 1e9) at {bad} pixels that "
                       f"flow_valid.png marks valid")
  flow = np.where(known[..., None], flow, 0.0).astype(np.float32)
  flow_valid = opt.get("flow_valid", known)
  if "covisibility" in opt:
    covis = opt["covisibility"]
    covis_valid = opt.get("covis_valid", np.ones(shape, bool))
  else:
    covis = fov_mask_from_flow(flow, target_shape) & known
    covis_valid = opt.get("covis_valid", np.zeros(shape, bool))
  return dict(flow=flow, covisibility=covis, flow_valid=flow_valid, covis_valid=covis_valid)


@register("pairs_folder")
class PairsFolder:
  has_backward = True    # per pair: `both` gives None for a pair without reverse/
  static_scene = False   # any pairs; depth + poses in meta.json do not say the scene is static

  def __init__(self, root, split: str | None = None):
    if root is None or not os.path.isdir(root):
      raise FileNotFoundError(f"pairs_folder: root {root!r} is not a folder of pair folders")
    if split and os.path.isdir(os.path.join(root, split)):
      root = os.path.join(root, split)
    self.root = root
    # Dot-folders are pairs still being written (see synthetic.write_pair).
    self.pairs = sorted(d for d in os.listdir(root) if not d.startswith(".")
                        and os.path.isfile(os.path.join(root, d, "image0.png")))
    if not self.pairs:
      raise FileNotFoundError(f"pairs_folder: no pair folders (sub-folders holding image0.png) "
                              f"in {root}")

  def __len__(self):
    return len(self.pairs)

  def path(self, index) -> str:
    return os.path.join(self.root, self.pairs[index])

  def _meta(self, folder):
    meta = {}
    meta_path = os.path.join(folder, "meta.json")
    if os.path.isfile(meta_path):
      try:
        with open(meta_path) as f:
          meta = json.load(f)
      except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{meta_path}: not valid JSON ({e})") from e
      if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
      for k in _ARRAY_META:
        if k in meta:
          meta[k] = np.asarray(meta[k], np.float64)
          want = (3, 3) if k.startswith("K") else (4, 4)
          if meta[k].shape != want:
            raise ValueError(f"{meta_path}: {k} has shape {meta[k].shape}, expected {want}")
    depth_path = os.path.join(folder, "depth.npz")
    if os.path.isfile(depth_path):
      try:
        with np.load(depth_path) as z:
          meta.update({k: z[k].astype(np.float32) for k in ("depth0", "depth1") if k in z})
      except (OSError, ValueError) as e:
        raise ValueError(f"{depth_path}: unreadable depth archive ({e})") from e
    return meta

  def _load(self, index, backward: bool, images=None, meta=None):
    """One direction; `images` (source, target) and `meta` (forward's, as read) skip re-reading
    what the other direction of the same pair already decoded."""
    folder = self.path(index)
    if images is None:
      im0 = _read_rgb(os.path.join(folder, "image0.png"))
      im1 = _read_rgb(os.path.join(folder, "image1.png"))
      if backward:
        im0, im1 = im1, im0
    else:
      im0, im1 = images
    labels_dir = os.path.join(folder, "reverse") if backward else folder
    if backward and not os.path.isdir(labels_dir):
      raise ValueError(f"{labels_dir}: missing (this pair has no backward labels in reverse/)")
    labels = read_labels(labels_dir, im0.shape[:2], im1.shape[:2])
    meta = dict(self._meta(folder) if meta is None else meta)
    if backward:
      for a, b in (("K0", "K1"), ("cam2world0", "cam2world1"), ("depth0", "depth1"),
                   ("frame0", "frame1")):
        if a in meta or b in meta:
          meta[a], meta[b] = meta.get(b), meta.get(a)
      meta = {k: v for k, v in meta.items() if v is not None}
    if "dataset" in meta:  # e.g. "synthetic" for generator dumps
      meta["origin"] = meta["dataset"]
    meta["dataset"] = "pairs_folder"
    meta.update(scene=self.pairs[index], path=folder, backward=backward)
    return dict(image0=im0, image1=im1, **labels, meta=meta)

  def __getitem__(self, index):
    return self._load(index, backward=False)

  def images(self, index):
    """(image0, image1) alone: what distillation reads (ufm_jax.data.distill_rows), so pairs
    without flow.flo, images only, serve it."""
    folder = self.path(index)
    return (_read_rgb(os.path.join(folder, "image0.png")),
            _read_rgb(os.path.join(folder, "image1.png")))

  def backward(self, index):
    """The backward pair (image1 -> image0), labelled from <pair>/reverse/."""
    return self._load(index, backward=True)

  def both(self, index):
    """(forward, backward), decoding the images, meta.json and depth.npz once; backward is None
    for a pair without reverse/."""
    folder = self.path(index)
    meta = self._meta(folder)
    forward = self._load(index, backward=False, meta=meta)
    if not os.path.isdir(os.path.join(folder, "reverse")):
      return forward, None
    images = (forward["image1"].copy(), forward["image0"].copy())
    return forward, self._load(index, backward=True, images=images, meta=meta)
