"""KITTI-2015 scene flow benchmark, optical-flow part (Menze & Geiger 2015), ~1242x375.

Layout under `root` (the unpacked `data_scene_flow/`, see data/kitti2015/README.md):
  training/image_2/{%06d}_10.png, {%06d}_11.png        (200 pairs)
  training/flow_occ/{%06d}_10.png                       (KITTI 16-bit PNG, all measured pixels)
  training/flow_noc/{%06d}_10.png                       (non-occluded pixels only)
  training/obj_map/{%06d}_10.png                        (optional; 0 = background, >0 = object id)
  testing/image_2/{%06d}_{10,11}.png                    (no GT)

Labels: flow and flow_valid from flow_occ (the official "all" ranking; `gt="noc"` to use
flow_noc); covisibility = flow_noc valid (measured, not occluded, stays in view); covis_valid =
flow_occ valid (where the GT can tell covisible from not). meta adds `noc_valid`, `occ_valid`
and, when obj_map exists, `obj_map` (uint8) and `foreground` (obj_map > 0) for Fl-bg / Fl-fg.
gt_relpath is `flow/{%06d}_10.png`, the submission layout. No backward flow.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ufm_jax.data import decode, io
from ufm_jax.data.registry import register

LAYOUT = ("training/image_2/%06d_{10,11}.png, training/flow_occ/%06d_10.png, "
          "training/flow_noc/%06d_10.png (testing/image_2/ for split='testing'); "
          "see data/kitti2015/README.md")


class Kitti2015:
  """Random-access KITTI-2015 flow source. split: 'training' (alias 'train') or 'testing'."""

  has_backward = False
  static_scene = False

  def __init__(self, root, split: str = "training", gt: str = "occ"):
    if root is None:
      raise ValueError(f"kitti2015: root is required; expected {LAYOUT}")
    split = {"train": "training", "test": "testing"}.get(split, split)
    if split not in ("training", "testing"):
      raise ValueError(f"kitti2015: split must be 'training' or 'testing', got {split!r}")
    if gt not in ("occ", "noc"):
      raise ValueError(f"kitti2015: gt must be 'occ' or 'noc', got {gt!r}")
    self.root, self.split, self.gt = os.fspath(root), split, gt
    self.has_gt = split == "training"
    self.base = os.path.join(self.root, split)
    image_dir = io.check_dir(os.path.join(self.base, "image_2"), LAYOUT)
    if self.has_gt:
      io.check_dir(os.path.join(self.base, "flow_occ"), LAYOUT)
      io.check_dir(os.path.join(self.base, "flow_noc"), LAYOUT)
    self.ids = sorted(int(m.group(1)) for f in os.listdir(image_dir)
                      if (m := re.fullmatch(r"(\d{6})_10\.png", f)))
    if not self.ids:
      raise FileNotFoundError(f"{image_dir}: no *_10.png images; expected {LAYOUT}")

  def __len__(self):
    return len(self.ids)

  def __getitem__(self, index: int) -> dict:
    pid = self.ids[index]
    name = f"{pid:06d}_10.png"
    image0 = io.read_image(os.path.join(self.base, "image_2", name))
    image1 = io.read_image(os.path.join(self.base, "image_2", f"{pid:06d}_11.png"))
    h, w = image0.shape[:2]
    if image1.shape != image0.shape:
      raise ValueError(f"{os.path.join(self.base, 'image_2', name)}: frames 10 and 11 differ in "
                       f"size ({image0.shape} vs {image1.shape})")
    meta = dict(dataset="kitti2015", scene=f"{pid:06d}", frame0="10", frame1="11",
                direction="forward", split=self.split, gt_relpath=f"flow/{name}",
                has_gt=self.has_gt)
    if not self.has_gt:
      zeros = np.zeros((h, w), bool)
      return dict(image0=image0, image1=image1, flow=np.zeros((h, w, 2), np.float32),
                  covisibility=zeros, flow_valid=zeros.copy(), covis_valid=zeros.copy(), meta=meta)
    occ_path = os.path.join(self.base, "flow_occ", name)
    flow_occ, occ_valid = io.read_kitti_flow(occ_path)
    flow_noc, noc_valid = io.read_kitti_flow(os.path.join(self.base, "flow_noc", name))
    if flow_occ.shape[:2] != (h, w) or flow_noc.shape[:2] != (h, w):
      raise ValueError(f"{occ_path}: flow maps {flow_occ.shape[:2]}/{flow_noc.shape[:2]} do not "
                       f"match image {(h, w)}")
    obj_path = os.path.join(self.base, "obj_map", name)
    if os.path.isfile(obj_path):
      obj = decode.imread_unchanged(obj_path)
      if obj is None or obj.shape[:2] != (h, w):
        raise ValueError(f"{obj_path}: expected a {h}x{w} object map PNG (0 = background)")
      if obj.ndim == 2:
        meta.update(obj_map=obj.astype(np.uint8), foreground=obj > 0)
      else:  # a colour-expanded palette image: ids are lost, background is black
        meta.update(foreground=obj.any(-1))
    flow, flow_valid = (flow_occ, occ_valid) if self.gt == "occ" else (flow_noc, noc_valid)
    meta.update(noc_valid=noc_valid, occ_valid=occ_valid)
    return dict(image0=image0, image1=image1, flow=flow, covisibility=noc_valid & flow_valid,
                flow_valid=flow_valid, covis_valid=occ_valid.copy(), meta=meta)


@register("kitti2015")
def make_kitti2015(root, split: str = "training", **options) -> Kitti2015:
  return Kitti2015(root, split=split, **options)
