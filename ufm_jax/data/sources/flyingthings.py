"""FlyingThings3D and Monkaa (Mayer et al. 2016, "Scene Flow Datasets"), 960x540.

Layout under `root` (full release, see data/flyingthings/README.md and data/monkaa/README.md):
FlyingThings3D (`<S>` = `TRAIN|TEST/{A,B,C}/{%04d seq}`; frames 0006..0015):
  frames_{clean,final}pass/<S>/{left,right}/{%04d}.png
  optical_flow/<S>/{into_future,into_past}/{left,right}/OpticalFlowInto{Future,Past}_{%04d}_{L,R}.pfm
  disparity/<S>/{left,right}/{%04d}.pfm
  disparity_change/<S>/{into_future,into_past}/{left,right}/{%04d}.pfm
Monkaa: the same with `<S>` = `<scene name>` (no split level).

Pairs: per sequence and camera, consecutive frames (I[i], I[i+1]) with the into_future flow of
frame i; `backward(k)` gives (I[i+1], I[i]) with the into_past flow of frame i+1 (both directions are
real ground truth). With `directions="both"` the source enumerates them interleaved (2k forward,
2k+1 its backward pair) so batches can be symmetrised by adjacent indices.

Labels: flow_valid = |u|, |v| < 1000 (RAFT); NaN/Inf flow (no marker in this dense format) makes the
sample corrupt (ValueError). Covisibility follows the official preprocess
(`ufm_jax.geometry.sceneflow.official_sceneflow_covisibility`): flow + disparity change,
depth = 1050 / disparity, z-depths compared with tau = 0.01 + 0.001 z - ln(0.5) 0.01. meta holds K (shared by both frames) and the
depth maps; camera poses (camera_data.txt) are not read, their convention is not documented here.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources._bidirectional import BidirectionalPairs
from ufm_jax.geometry import sceneflow

MAX_FLOW = 1000.0
_DIRS = {"forward": ("into_future", "Future"), "backward": ("into_past", "Past")}


def _thresholds(name: str) -> tuple[float, float, float]:
  """(absolute, temperature, relative) of the official preprocess (geometry.RENDERING_PARAMETERS)."""
  from ufm_jax.geometry import rendering_parameters
  return rendering_parameters(name)


class SceneFlowSource(BidirectionalPairs):
  """FlyingThings3D / Monkaa pairs with scene-flow covisibility.

  Args:
    root: dataset root (layout above).
    dataset: 'flyingthings' or 'monkaa'.
    split: FlyingThings3D 'train' | 'test'; Monkaa has no split ('train' or None).
    dstype: 'clean', 'final' or 'both' (both passes enumerated).
    cameras: tuple of 'left' / 'right'.
    directions: 'forward' (default; `backward(k)` gives the backward pair) or 'both'.
  """

  has_backward = True
  static_scene = False

  def __init__(self, root, dataset: str, split: str | None = "train", dstype: str = "clean",
               cameras=("left",), directions: str = "forward"):
    self.dataset = dataset
    layout = f"see data/{dataset}/README.md (frames_<pass>pass/, optical_flow/, disparity/, " \
             "disparity_change/)"
    if root is None:
      raise ValueError(f"{dataset}: root is required; {layout}")
    self.root = os.fspath(root)
    io.check_dir(self.root, layout)
    passes = {"clean": ("clean",), "final": ("final",), "both": ("clean", "final")}.get(dstype)
    if passes is None:
      raise ValueError(f"{dataset}: dstype must be 'clean', 'final' or 'both', got {dstype!r}")
    if directions not in ("forward", "both"):
      raise ValueError(f"{dataset}: directions must be 'forward' or 'both', got {directions!r}")
    for cam in cameras:
      if cam not in ("left", "right"):
        raise ValueError(f"{dataset}: cameras must be 'left'/'right', got {cam!r}")
    self.tau = _thresholds(dataset)
    self.directions = directions
    self.split = split
    frames_root = io.check_dir(os.path.join(self.root, f"frames_{passes[0]}pass"), layout)
    if dataset == "flyingthings":
      if split not in ("train", "test"):
        raise ValueError(f"flyingthings: split must be 'train' or 'test', got {split!r}")
      top = io.check_dir(os.path.join(frames_root, split.upper()), layout)
      scenes = [f"{split.upper()}/{letter}/{seq}" for letter in sorted(os.listdir(top))
                if os.path.isdir(os.path.join(top, letter))
                for seq in sorted(os.listdir(os.path.join(top, letter)))]
    else:
      if split not in (None, "train"):
        raise ValueError(f"monkaa: has no splits (use split='train'), got {split!r}")
      scenes = sorted(s for s in os.listdir(frames_root)
                      if os.path.isdir(os.path.join(frames_root, s)))
    self.pairs = []  # (pass, scene, camera, frame i, frame i + 1)
    for dpass in passes:
      for scene in scenes:
        for cam in cameras:
          d = os.path.join(self.root, f"frames_{dpass}pass", scene, cam)
          if not os.path.isdir(d):
            continue
          frames = sorted(int(m.group(1)) for f in os.listdir(d)
                          if (m := re.fullmatch(r"(\d{4})\.png", f)))
          self.pairs += [(dpass, scene, cam, a, b) for a, b in zip(frames, frames[1:]) if b == a + 1]
    if not self.pairs:
      raise FileNotFoundError(f"{frames_root}: no consecutive frame pairs found; {layout}")

  def _load(self, k: int, backward: bool, images=None) -> dict:
    dpass, scene, cam, a, b = self.pairs[k]
    src, dst = (b, a) if backward else (a, b)
    direction = "backward" if backward else "forward"
    into, word = _DIRS[direction]
    lr = "L" if cam == "left" else "R"
    r = self.root
    gt_relpath = f"{scene}/{into}/{cam}/OpticalFlowInto{word}_{src:04d}_{lr}.pfm"
    if images is None:
      images = [io.read_image(os.path.join(r, f"frames_{dpass}pass", scene, cam, f"{f:04d}.png"))
                for f in (src, dst)]
    image0, image1 = images
    flow_path = os.path.join(r, "optical_flow", gt_relpath)
    flow = io.read_pfm(flow_path)
    if flow.ndim != 3:
      raise ValueError(f"{flow_path}: expected a 3-channel PFM (PF) flow file, got shape {flow.shape}")
    flow = flow[..., :2]
    paths = (os.path.join(r, "disparity", scene, cam, f"{src:04d}.pfm"),
             os.path.join(r, "disparity", scene, cam, f"{dst:04d}.pfm"),
             os.path.join(r, "disparity_change", scene, into, cam, f"{src:04d}.pfm"))
    disp0, disp1, change = (io.read_pfm(p) for p in paths)
    h, w = image0.shape[:2]
    for path, arr, ndim in ((flow_path, flow, 3), (paths[0], disp0, 2), (paths[1], disp1, 2),
                            (paths[2], change, 2)):
      if arr.shape[:2] != (h, w) or arr.ndim != ndim:
        raise ValueError(f"{path}: shape {arr.shape} does not match the {h}x{w} images of "
                         f"{scene}/{cam} (expected {'(H, W, 2)' if ndim == 3 else '(H, W)'})")
    io.require_finite(flow, flow_path)  # dense PFM: NaN/Inf is no marker but a damaged file
    flow_valid = (np.abs(flow[..., 0]) < MAX_FLOW) & (np.abs(flow[..., 1]) < MAX_FLOW)
    K = sceneflow.sceneflow_intrinsics(h, w)
    geo = sceneflow.official_sceneflow_covisibility(
        sceneflow.fill_invalid(flow, flow_valid, np.nan), disp0, change, disp1, self.tau, K=K)
    flow = sceneflow.fill_invalid(flow, flow_valid)
    return dict(image0=image0, image1=image1, flow=flow,
                covisibility=geo["covisibility"] & flow_valid, flow_valid=flow_valid,
                covis_valid=geo["covis_valid"],
                meta=dict(dataset=self.dataset, scene=scene, camera=cam, dstype=dpass,
                          frame0=f"{src:04d}", frame1=f"{dst:04d}", direction=direction,
                          split=self.split, gt_relpath=gt_relpath, K0=K, K1=K.copy(),
                          depth0=geo["depth0"], depth1=geo["depth1"]))


@register("flyingthings")
def make_flyingthings(root, split: str = "train", **options) -> SceneFlowSource:
  return SceneFlowSource(root, "flyingthings", split=split, **options)


@register("monkaa")
def make_monkaa(root, split: str | None = "train", **options) -> SceneFlowSource:
  return SceneFlowSource(root, "monkaa", split=split, **options)
