"""FlyingChairs (Dosovitskiy et al. 2015): 22872 synthetic pairs, 512x384, dense `.flo` flow.

Layout under `root` (the unpacked `FlyingChairs_release/`, see data/flyingchairs/README.md):
  data/{%05d}_img1.ppm, data/{%05d}_img2.ppm, data/{%05d}_flow.flo
  chairs_split.txt (or FlyingChairs_train_val.txt): one line per pair, 1 = train, 2 = val

Labels (supplementary "Computing Covisibility Mask"): FlyingChairs has neither occlusion nor scene
flow, so covisibility is the FoV mask (target location inside image1) used as a proxy for flow
supervision, and the covisibility supervision mask is all zero. flow_valid = |u|, |v| < 1000
(RAFT); the flow is dense, so NaN/Inf in it makes the sample corrupt (ValueError).

Backward (`both(i)`): FlyingChairs has no backward flow, and the official reader's second view
(uniflowmatch/datasets/flyingchairs.py:47-58 of the train branch) carries zero flow with every
mask False. Its masks supervise nothing, but the 980 recipes' "all" range reads the flow alone
(loss/epe.py:63-69: every pixel counts as valid), so the official (b, a) rows train the model
towards zero flow on every pixel. `backward_zero_flow` (quirk, True = official) keeps that:
flow_valid is True on the backward row (zero flow is its label), covisibility, covis_valid and
fov_mask False. False: flow_valid False too, so the row supervises nothing in any recipe (what
the symmetrization of other datasets without backward labels gives).
"""

from __future__ import annotations

import os
import re

import numpy as np

from ufm_jax.data import io, official_ops
from ufm_jax.data.registry import register
from ufm_jax.geometry import sceneflow

LAYOUT = ("data/{id:05d}_img1.ppm, data/{id:05d}_img2.ppm, data/{id:05d}_flow.flo (+ chairs_split.txt "
          "for split='train'/'val'); see data/flyingchairs/README.md")
SPLIT_FILES = ("chairs_split.txt", "FlyingChairs_train_val.txt")
MAX_FLOW = 1000.0  # larger |u| or |v| is treated as undefined (RAFT convention)


class FlyingChairs:
  """Random-access FlyingChairs source. split: 'train' (22232), 'val' (640) or 'all' (22872)."""

  has_backward = True
  static_scene = False

  def __init__(self, root, split: str = "train", backward_zero_flow: bool = True):
    if root is None:
      raise ValueError(f"flyingchairs: root is required (folder with {LAYOUT})")
    self.root = os.fspath(root)
    self.data_dir = io.check_dir(os.path.join(self.root, "data"), LAYOUT)
    ids = sorted(int(m.group(1)) for f in os.listdir(self.data_dir)
                 if (m := re.fullmatch(r"(\d{5})_flow\.flo", f)))
    if not ids:
      raise FileNotFoundError(f"{self.data_dir}: no *_flow.flo files; expected {LAYOUT}")
    if split not in ("train", "val", "all"):
      raise ValueError(f"flyingchairs: split must be 'train', 'val' or 'all', got {split!r}")
    if split != "all":
      labels = self._read_split(len(ids))
      want = 1 if split == "train" else 2
      ids = [i for i, lab in zip(ids, labels) if lab == want]
    self.split = split
    self.ids = ids
    self.backward_zero_flow = bool(backward_zero_flow)

  def _read_split(self, n: int) -> list[int]:
    for name in SPLIT_FILES:
      path = os.path.join(self.root, name)
      if os.path.isfile(path):
        with open(path) as f:
          tokens = f.read().split()
        if len(tokens) != n or any(t not in ("1", "2") for t in tokens):
          raise ValueError(f"{path}: expected {n} lines of 1 (train) or 2 (val), one per pair in "
                           f"sorted order; got {len(tokens)} lines")
        return [int(t) for t in tokens]
    raise FileNotFoundError(f"{os.path.join(self.root, SPLIT_FILES[0])}: split file not found "
                            "(needed for split='train'/'val'; use split='all' without it)")

  def __len__(self):
    return len(self.ids)

  def __getitem__(self, index: int) -> dict:
    pid = self.ids[index]
    stem = os.path.join(self.data_dir, f"{pid:05d}")
    image0, image1 = io.read_image(stem + "_img1.ppm"), io.read_image(stem + "_img2.ppm")
    flow = io.read_flo(stem + "_flow.flo")
    if flow.shape[:2] != image0.shape[:2] or image1.shape != image0.shape:
      raise ValueError(f"{stem}_flow.flo: flow {flow.shape[:2]} and images {image0.shape[:2]}, "
                       f"{image1.shape[:2]} differ in size")
    io.require_finite(flow, stem + "_flow.flo")  # FlyingChairs flow is dense
    flow_valid = (np.abs(flow[..., 0]) < MAX_FLOW) & (np.abs(flow[..., 1]) < MAX_FLOW)
    flow = sceneflow.fill_invalid(flow, flow_valid)
    # The official test (flyingchairs.py:28-31, 65-80): x + u in [0, W), y + v in [0, H), on the
    # integer pixel index. fov_mask: the official view's key (= its non_occluded_mask), which the
    # official crop ANDs and the recipes' losses do not read.
    covisibility = official_ops.in_frame(flow) & flow_valid
    return dict(image0=image0, image1=image1, flow=flow, covisibility=covisibility,
                flow_valid=flow_valid, covis_valid=np.zeros_like(flow_valid),
                fov_mask=covisibility.copy(),
                meta=dict(dataset="flyingchairs", scene="", frame0=f"{pid:05d}_img1",
                          frame1=f"{pid:05d}_img2", pair_id=pid, split=self.split,
                          gt_relpath=f"{pid:05d}_flow.flo", direction="forward"))

  def backward(self, index: int) -> dict:
    return self.both(index)[1]

  def both(self, index: int) -> tuple[dict, dict]:
    """(forward, the official second view as the (image1 -> image0) pair): zero flow, every
    mask False, flow_valid = `backward_zero_flow` (see the module docstring)."""
    fwd = self[index]
    hw = fwd["flow"].shape[:2]
    off = np.zeros(hw, bool)
    bwd = dict(image0=fwd["image1"], image1=fwd["image0"], flow=np.zeros(hw + (2,), np.float32),
               covisibility=off, flow_valid=np.full(hw, self.backward_zero_flow),
               covis_valid=off.copy(), fov_mask=off.copy(),
               meta=dict(fwd["meta"], frame0=fwd["meta"]["frame1"], frame1=fwd["meta"]["frame0"],
                         direction="backward"))
    return fwd, bwd


@register("flyingchairs")
def make_flyingchairs(root, split: str = "train", backward_zero_flow: bool = True) -> FlyingChairs:
  return FlyingChairs(root, split=split, backward_zero_flow=backward_zero_flow)
