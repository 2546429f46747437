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
from ufm_jax.data.sources import _official, posed
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


# ------------------------------------------------------------------------ official processed layout

class SceneFlowProcessed(_official.PrecomputedPairs):
  """FlyingThings3D / Monkaa as UFM's `preprocess_datasets/preprocess_{flyingthings,monkaa}.py`
  write them (or the UFM data mirror's `flyingthings3d_processed`), read like the official
  `uniflowmatch.datasets.{FlyingThings3D,Monkaa}`. Under root (FlyingThings3D: with a split
  level `<q>/train`, Monkaa without):
    individual_quantities/<q>/index.json   {i: {file_name, file_index, [split, division,] seq, idx}}
    individual_quantities/<q>/<a>_<b>.h5   frame_{cleanpass,finalpass}_{left,right} (N, H, W, 3)
                                           uint8, depth_*, intrinsics_*, pose_*
    flow/<q>/index.json or job_df.csv      one row per pair: [split, division,] seq, pair0_id,
                                           pair1_id (the FlyingThings3D preprocess writes only
                                           job_df.csv; row i then lives in the `<a>_<b>.h5` with
                                           a <= i <= b at index i - a, as the preprocess writes it)
    flow/<q>/<a>_<b>.h5                    <cam>_view<0|1>_{flow ((N, H, W, 2) or (N, 2, H, W)
                                           float32), fov_mask, non_occluded_mask,
                                           occlusion_supervision_mask} (N, H, W) bool
  view0 = forward (frame pair0 -> pair1), view1 = backward; both are precomputed, so `both(i)`
  returns the pair and its reverse from one read. The official draws the camera (left / right)
  and the rendering at random per sample when its aug_left_right / aug_clean_final are on (the
  recipes): FlyingThings3D one pass for both frames (flyingthings3d.py:66-71), Monkaa each
  frame's pass on its own (monkaa.py:61-64). Here every (camera, pass) combination is its own
  index, `variants` consecutive ones per official sample: index = pair * variants + camera *
  (variants / len(cameras)) + pass (FlyingThings3D) or + pass0 * len(passes) + pass1 (Monkaa);
  the training pipeline draws one of them per sample (`input.draw_variants`). The
  no-augmentation config: cameras=("left",), passes=("clean",)."""

  def __init__(self, root, dataset: str, split="train", cameras=("left", "right"),
               passes=("clean", "final")):
    if root is None:
      raise ValueError(f"{dataset}_official: root is required (see data/{dataset}/README.md)")
    self.root, self.dataset, self.split = os.fspath(root), dataset, split
    for c in cameras:
      if c not in ("left", "right"):
        raise ValueError(f"{dataset}_official: cameras must be left/right, got {c!r}")
    for p in passes:
      if p not in ("clean", "final"):
        raise ValueError(f"{dataset}_official: passes must be clean/final, got {p!r}")
    if not cameras or not passes:
      raise ValueError(f"{dataset}_official: cameras and passes must not be empty")
    self.cameras, self.passes = tuple(cameras), tuple(passes)
    sub = (split,) if dataset == "flyingthings" else ()
    iq = io.check_dir(os.path.join(self.root, "individual_quantities", *sub),
                      f"individual_quantities/{'/'.join(sub)} (see data/{dataset}/README.md)")
    self.flow_dir = io.check_dir(os.path.join(self.root, "flow", *sub),
                                 f"flow/{'/'.join(sub)} (see data/{dataset}/README.md)")
    self.frames = _official.H5Index(iq)
    iq_rows = _read_json_rows(os.path.join(iq, "index.json"))
    keys = ("split", "division", "seq", "idx") if dataset == "flyingthings" else ("seq", "idx")
    frame_of = {}
    for i, row in iq_rows.items():
      try:
        frame_of[tuple(str(row[k]) for k in keys)] = i
      except KeyError as e:
        raise ValueError(f"{iq}/index.json: entry {i} lacks {e}") from None
    rows = self._flow_rows()
    split_key = "TRAIN" if split == "train" else "TEST"
    self.pairs = []   # (flow index, frame index 0, frame index 1, label)
    missing = []
    for i, row in rows:
      lead = (split_key, str(row["division"])) if dataset == "flyingthings" else ()
      try:
        a = frame_of[lead + (str(row["seq"]), str(row["pair0_id"]))]
        b = frame_of[lead + (str(row["seq"]), str(row["pair1_id"]))]
      except KeyError as e:
        missing.append(f"flow row {i}: frame {e.args[0]}")
        continue
      label = "_".join(str(x) for x in (lead[1:] + (row["seq"],)))
      self.pairs.append((i, a, b, label))
    if missing:
      raise ValueError(f"{self.flow_dir}: {len(missing)} flow rows name frames absent from "
                       f"{iq}/index.json, e.g. {missing[0]}")
    if not self.pairs:
      raise FileNotFoundError(f"{self.flow_dir}: no pairs")

  def _flow_rows(self):
    """[(flow index, row dict)] and self.flow (an H5Index over flow/<q>)."""
    index = os.path.join(self.flow_dir, "index.json")
    if os.path.isfile(index):
      rows = _read_json_rows(index)
      self.flow = _official.H5Index(self.flow_dir)
      return sorted(rows.items())
    csv = posed.require_file(os.path.join(self.flow_dir, "job_df.csv"),
                             "flow/index.json or the preprocess's job_df.csv")
    rows = _read_job_csv(csv)
    ranges = _official.h5_ranges(self.flow_dir)
    entries = {}
    for i in rows:
      hit = next(((name, i - a) for a, b, name in ranges if a <= i <= b), None)
      if hit is None:
        raise ValueError(f"{csv}: row {i} lies in no <first>_<last>.h5 of {self.flow_dir}")
      entries[i] = hit
    self.flow = _official.H5Index(self.flow_dir, entries)
    return sorted(rows.items())

  @property
  def _frame_passes(self):
    """The (pass of frame 0, pass of frame 1) renderings of one camera."""
    if self.dataset == "monkaa":
      return [(p0, p1) for p0 in self.passes for p1 in self.passes]
    return [(p, p) for p in self.passes]

  @property
  def variants(self) -> int:
    """Consecutive indices that are renderings of one official sample."""
    return len(self.cameras) * len(self._frame_passes)

  def __len__(self):
    return len(self.pairs) * self.variants

  def _variant(self, index):
    k, r = divmod(int(index), self.variants)
    c, p = divmod(r, len(self._frame_passes))
    return k, self.cameras[c], self._frame_passes[p]

  def _views(self, index):
    k, cam, (pass0, pass1) = self._variant(index)
    dpass = pass0 if pass0 == pass1 else f"{pass0}/{pass1}"
    i, a, b, label = self.pairs[k]
    key0, key1 = f"frame_{pass0}pass_{cam}", f"frame_{pass1}pass_{cam}"
    where = f"{self.dataset}:{self.flow.location(i)[0]}[{self.flow.location(i)[1]}]"
    img0 = _official.rgb_u8(self.frames.read(a, (key0,))[key0], where)
    img1 = _official.rgb_u8(self.frames.read(b, (key1,))[key1], where)
    f = self.flow.read(i, [f"{cam}_view{v}_{q}" for v in (0, 1) for q in _official.LABELS])
    return _official.two_directions(
        self.dataset, img0, img1, lambda q, v: f[f"{cam}_view{v}_{q}"], where, flow_layout="auto",
        scene=f"{label}_{cam}_{dpass}", camera=cam, dstype=dpass, pair_index=i,
        suitable_for_refinement=self.dataset == "flyingthings")


def _read_json_rows(path: str) -> dict[int, dict]:
  import json  # pylint: disable=g-import-not-at-top
  posed.require_file(path, "an index.json of the official preprocess")
  try:
    with open(path) as f:
      m = json.load(f)
    return {int(k): v for k, v in m.items()}
  except (OSError, ValueError, AttributeError) as e:
    raise ValueError(f"{path}: not an index json ({{i: {{...}}}}): {e}") from None


def _read_job_csv(path: str) -> dict[int, dict]:
  import csv  # pylint: disable=g-import-not-at-top
  with open(path, newline="") as f:
    reader = csv.reader(f)
    header = next(reader, None)
    if not header or not {"seq", "pair0_id", "pair1_id"} <= set(header):
      raise ValueError(f"{path}: expected a pandas job_df.csv with columns seq, pair0_id, "
                       f"pair1_id, got {header}")
    return {int(r[0]): dict(zip(header[1:], r[1:])) for r in reader if r}


@register("flyingthings_official")
def make_flyingthings_official(root, split="train", **options) -> SceneFlowProcessed:
  return SceneFlowProcessed(root, "flyingthings", split=split, **options)


@register("monkaa_official")
def make_monkaa_official(root, split="train", **options) -> SceneFlowProcessed:
  return SceneFlowProcessed(root, "monkaa", split=split, **options)
