"""MPI-Sintel (Butler et al. 2012), clean and final passes, 1024x436.

Layout under `root` (the unpacked `MPI-Sintel-complete/`, see data/sintel/README.md):
  training/{clean,final}/<scene>/frame_{%04d}.png      (1-based)
  training/flow/<scene>/frame_{%04d}.flo               (frame k -> k+1)
  training/occlusions/<scene>/frame_{%04d}.png         (set = occluded in frame k+1)
  training/invalid/<scene>/frame_{%04d}.png            (set = GT invalid)
  test/{clean,final}/<scene>/frame_{%04d}.png          (no GT)

Labels: flow_valid = known GT, |u|, |v| <= 1e9 (the .flo unknown marker; NaN/Inf is none, so it makes
the sample corrupt, a ValueError; the standard "Sintel train" EPE averages over all pixels; the
`invalid` map is kept in meta, not applied); covisibility = not occluded and landing inside
image1 (`covis_in_image=False`: not occluded only, the benchmark branch's mask); covis_valid = not
invalid. meta adds the boolean maps `occlusion`, `invalid` and `matched` (visible in both frames:
not occluded, x + flow inside [0, W-1] x [0, H-1] and |u| <= W-1, |v| <= H-1, the unimatch
approximation of the official matched/unmatched split; unmatched = ~matched). gt_relpath is
`<pass>/<scene>/frame_%04d.flo` (the submission layout). No backward flow.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.geometry import sceneflow

LAYOUT = ("training/<pass>/<scene>/frame_%04d.png, training/flow/, training/occlusions/, "
          "training/invalid/ (test/<pass>/ for split='test'); see data/sintel/README.md")
UNKNOWN_FLOW = io.FLO_UNKNOWN


class Sintel:
  """Random-access Sintel source.

  Args:
    root: MPI-Sintel-complete folder.
    dstype: 'clean' or 'final' (registered as sintel_clean / sintel_final).
    split: 'training' (alias 'train'; 1041 pairs) or 'test' (alias 'testing'; no GT: zero flow,
      all-False masks, meta["has_gt"] False).
    scenes: optional list of scene names to keep (e.g. a validation subset).
    covis_in_image: covisibility also requires the GT target inside image1 (default). False gives
      the benchmark branch's mask, not occluded only (opticalflow_datasets.py:116-122), which
      `evaluate.py --protocol official` scores the [covis] EPE on.
  """

  has_backward = False
  static_scene = False

  def __init__(self, root, dstype: str, split: str = "training", scenes=None,
               covis_in_image: bool = True):
    if root is None:
      raise ValueError(f"sintel_{dstype}: root is required; expected {LAYOUT}")
    split = {"train": "training", "testing": "test"}.get(split, split)
    if split not in ("training", "test"):
      raise ValueError(f"sintel_{dstype}: split must be 'training' or 'test', got {split!r}")
    self.root, self.dstype, self.split = os.fspath(root), dstype, split
    self.has_gt = split == "training"
    self.covis_in_image = bool(covis_in_image)
    image_root = io.check_dir(os.path.join(self.root, split, dstype), LAYOUT)
    if self.has_gt:
      for sub in ("flow", "occlusions", "invalid"):
        io.check_dir(os.path.join(self.root, split, sub), LAYOUT)
    names = sorted(s for s in os.listdir(image_root) if os.path.isdir(os.path.join(image_root, s)))
    if scenes is not None:
      missing = sorted(set(scenes) - set(names))
      if missing:
        raise FileNotFoundError(f"{image_root}: scenes {missing} not found")
      names = [s for s in names if s in set(scenes)]
    self.pairs = []
    for scene in names:
      frames = sorted(int(m.group(1)) for f in os.listdir(os.path.join(image_root, scene))
                      if (m := re.fullmatch(r"frame_(\d{4})\.png", f)))
      self.pairs += [(scene, a) for a, b in zip(frames, frames[1:]) if b == a + 1]
    if not self.pairs:
      raise FileNotFoundError(f"{image_root}: no consecutive frame pairs; expected {LAYOUT}")

  def __len__(self):
    return len(self.pairs)

  def __getitem__(self, index: int) -> dict:
    scene, k = self.pairs[index]
    base = os.path.join(self.root, self.split)
    name = f"frame_{k:04d}"
    image0 = io.read_image(os.path.join(base, self.dstype, scene, name + ".png"))
    image1 = io.read_image(os.path.join(base, self.dstype, scene, f"frame_{k + 1:04d}.png"))
    h, w = image0.shape[:2]
    meta = dict(dataset=f"sintel_{self.dstype}", scene=scene, frame0=f"{k:04d}",
                frame1=f"{k + 1:04d}", dstype=self.dstype, direction="forward", split=self.split,
                gt_relpath=f"{self.dstype}/{scene}/{name}.flo", has_gt=self.has_gt)
    if not self.has_gt:
      zeros = np.zeros((h, w), bool)
      return dict(image0=image0, image1=image1, flow=np.zeros((h, w, 2), np.float32),
                  covisibility=zeros, flow_valid=zeros.copy(), covis_valid=zeros.copy(), meta=meta)
    flow_path = os.path.join(base, "flow", scene, name + ".flo")
    flow = io.read_flo(flow_path)
    occlusion = io.read_mask(os.path.join(base, "occlusions", scene, name + ".png"))
    invalid = io.read_mask(os.path.join(base, "invalid", scene, name + ".png"))
    for what, shape in (("flow", flow.shape[:2]), ("occlusion", occlusion.shape),
                        ("invalid", invalid.shape)):
      if shape != (h, w):
        raise ValueError(f"{flow_path}: {what} map is {shape}, images of {scene} are {(h, w)}")
    io.require_finite(flow, flow_path)  # unknown flow is marked with 1e10, never NaN
    flow_valid = (np.abs(flow[..., 0]) <= UNKNOWN_FLOW) & (np.abs(flow[..., 1]) <= UNKNOWN_FLOW)
    flow = sceneflow.fill_invalid(flow, flow_valid)
    covisibility = ~occlusion & flow_valid
    if self.covis_in_image:
      covisibility &= sceneflow.fov_mask(flow)
    u = np.arange(w)[None, :] + flow[..., 0]
    v = np.arange(h)[:, None] + flow[..., 1]
    matched = (~occlusion & flow_valid & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
               & (np.abs(flow[..., 0]) <= w - 1) & (np.abs(flow[..., 1]) <= h - 1))
    meta.update(occlusion=occlusion, invalid=invalid, matched=matched)
    return dict(image0=image0, image1=image1, flow=flow, covisibility=covisibility,
                flow_valid=flow_valid, covis_valid=~invalid & flow_valid, meta=meta)


@register("sintel_clean")
def make_sintel_clean(root, split: str = "training", **options) -> Sintel:
  return Sintel(root, "clean", split=split, **options)


@register("sintel_final")
def make_sintel_final(root, split: str = "training", **options) -> Sintel:
  return Sintel(root, "final", split=split, **options)
