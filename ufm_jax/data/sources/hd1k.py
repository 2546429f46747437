"""HD1K (Kondermann et al. 2016): real driving sequences with sparse flow GT in KITTI PNG format.

Layout under `root` (see data/hd1k/README.md):
  hd1k_input/image_2/{%06d seq}_{%04d frame}.png
  hd1k_flow_gt/flow_occ/{%06d seq}_{%04d frame}.png      (KITTI 16-bit PNG: flow frame -> frame+1)

Pairs: every flow file whose frame and the next frame of the same sequence have images
(~1046 pairs, paper Table 1). No backward flow.

Labels: flow_valid = the PNG's valid channel; HD1K ships no occlusion or covisibility map, so (like
UFM's own loader) covisibility is the valid GT landing inside image1, and the covisibility
supervision mask is all zero.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _official
from ufm_jax.geometry import sceneflow

LAYOUT = ("hd1k_input/image_2/<seq %06d>_<frame %04d>.png and hd1k_flow_gt/flow_occ/<seq>_<frame>.png; "
          "see data/hd1k/README.md")


class HD1K:
  """Random-access HD1K source (training set; split='train')."""

  has_backward = False
  static_scene = False

  def __init__(self, root, split: str = "train"):
    if root is None:
      raise ValueError(f"hd1k: root is required; expected {LAYOUT}")
    if split != "train":
      raise ValueError(f"hd1k: only split='train' has ground truth, got {split!r}")
    self.root = os.fspath(root)
    self.image_dir = io.check_dir(os.path.join(self.root, "hd1k_input", "image_2"), LAYOUT)
    self.flow_dir = io.check_dir(os.path.join(self.root, "hd1k_flow_gt", "flow_occ"), LAYOUT)
    pattern = re.compile(r"(\d{6})_(\d{4})\.png")
    images = {(int(m.group(1)), int(m.group(2)))
              for f in os.listdir(self.image_dir) if (m := pattern.fullmatch(f))}
    flows = sorted((int(m.group(1)), int(m.group(2)))
                   for f in os.listdir(self.flow_dir) if (m := pattern.fullmatch(f)))
    self.pairs = [(s, f) for s, f in flows if (s, f) in images and (s, f + 1) in images]
    if not self.pairs:
      raise FileNotFoundError(f"{self.root}: no HD1K flow file with both images; expected {LAYOUT}")

  def __len__(self):
    return len(self.pairs)

  def __getitem__(self, index: int) -> dict:
    seq, frame = self.pairs[index]
    image0 = io.read_image(os.path.join(self.image_dir, f"{seq:06d}_{frame:04d}.png"))
    image1 = io.read_image(os.path.join(self.image_dir, f"{seq:06d}_{frame + 1:04d}.png"))
    flow_path = os.path.join(self.flow_dir, f"{seq:06d}_{frame:04d}.png")
    flow, flow_valid = io.read_kitti_flow(flow_path)
    if flow.shape[:2] != image0.shape[:2]:
      raise ValueError(f"{flow_path}: flow {flow.shape[:2]} does not match image {image0.shape[:2]}")
    covisibility = flow_valid & sceneflow.fov_mask(flow)
    return dict(image0=image0, image1=image1, flow=flow, covisibility=covisibility,
                flow_valid=flow_valid, covis_valid=np.zeros_like(flow_valid),
                meta=dict(dataset="hd1k", scene=f"{seq:06d}", frame0=f"{frame:04d}",
                          frame1=f"{frame + 1:04d}", direction="forward", split="train",
                          gt_relpath=f"{seq:06d}_{frame:04d}.png"))


@register("hd1k")
def make_hd1k(root, split: str = "train") -> HD1K:
  return HD1K(root, split=split)


# ------------------------------------------------------------------------ official processed layout

INVALID_FLOW = 4000.0  # the official HD1K reader's value for pixels without ground truth


@register("hd1k_official")
class HD1KProcessed(_official.PrecomputedPairs):
  """HD1K as UFM's `preprocess_datasets/preprocess_hd1k.py` writes it (`hd1k_processed`, 1330x560,
  LANCZOS images, nearest flow), read like the official `uniflowmatch.datasets.HD1K`:
    <root>/%04d.npz   img0, img1 (H, W, 3) uint8, flow (2, H, W) float32, valid (H, W) bool
  Forward: flow set to 4000 where not valid, covisibility = fov = valid, no covisibility
  supervision. Backward (the official's second view): flow 4000 everywhere, every mask False."""

  def __init__(self, root, split="train"):
    if root is None:
      raise ValueError("hd1k_official: root is required (see data/hd1k/README.md)")
    if split != "train":
      raise ValueError(f"hd1k_official: only split='train' exists, got {split!r}")
    self.root, self.split = os.fspath(root), split
    io.check_dir(self.root, "%04d.npz files (see data/hd1k/README.md)")
    self.files = sorted(os.path.join(self.root, f) for f in os.listdir(self.root)
                        if f.endswith(".npz"))
    if not self.files:
      raise FileNotFoundError(f"{self.root}: no .npz files (expected hd1k_processed/%04d.npz)")

  def __len__(self):
    return len(self.files)

  def _views(self, index):
    path = self.files[index]
    z = _official.load_npz(path, ("img0", "img1", "flow", "valid"))
    valid = np.asarray(z["valid"], bool)
    flow = np.array(z["flow"], np.float32)
    if flow.shape[1:] != valid.shape:
      raise ValueError(f"{path}: flow {flow.shape} does not match valid {valid.shape}")
    flow[:, ~valid] = INVALID_FLOW
    none = np.zeros_like(valid)
    labels = {"flow": (flow, np.full_like(flow, INVALID_FLOW)), "non_occluded_mask": (valid, none),
              "occlusion_supervision_mask": (none, none), "fov_mask": (valid, none)}
    img0, img1 = (_official.rgb_u8(z[k], path) for k in ("img0", "img1"))
    fwd, bwd = _official.two_directions(
        "hd1k", img0, img1, lambda q, v: labels[q][v], path, scene=os.path.basename(path)[:-4],
        split="train", suitable_for_refinement=False)
    fwd["flow_valid"] = valid.copy()
    bwd["flow_valid"] = none.copy()
    return [fwd, bwd]
