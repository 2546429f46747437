"""Spring (Mehl et al. 2023): 1920x1080 stereo video, optical flow GT in HDF5 `.flo5`.

Layout under `root` (see data/spring/README.md): `{train,test}/<seq %04d>/`
  frame_{left,right}/frame_{cam}_{%04d}.png                       (frames 1-based)
  flow_{FW,BW}_{cam}/flow_{FW,BW}_{cam}_{%04d}.flo5               (train only)
  maps/matchmap_flow_{FW,BW}_{cam}/matchmap_flow_{FW,BW}_{cam}_{%04d}.png   (train only)
  disp1_{cam}/disp1_{cam}_{%04d}.dsp5                              (train only; with_depth=True)
  cam_data/intrinsics.txt (fx fy cx cy per frame), cam_data/extrinsics.txt (16 numbers per frame,
  world-to-camera of the left camera; train only)

Ground truth is stored at 2x resolution (3840x2160) with values in 1920x1080 pixel units; the
sample's flow is `gt[::2, ::2]` (official spring_utils). `full_gt=True` adds the full-resolution
field as meta["flow_full"] for the official 2x2-minimum evaluation.

Pairs: per sequence and camera, FW file k maps frame k -> k+1; BW file k+1 maps k+1 -> k, which
`backward()` (or directions="both": 2k forward, 2k+1 its backward pair) returns.

Labels ("Dataset-provided" in supplementary Table S1): flow_valid = finite GT (NaN = no GT);
covisibility = matched in the dataset's matchmap (red channel: occluded, green: leaves the view;
both must be 0), the flow landing inside image1, and valid flow; covis_valid = flow_valid.
meta: K0/K1 from intrinsics.txt; cam2world0/1 (4x4, inverted extrinsics; the right camera's
world-to-camera is the left one with x translation decreased by the 0.065 m baseline) when
extrinsics.txt exists. Their axis convention is taken as OpenCV (map-anything's reading; unverified).
with_depth=True adds depth0/depth1 = fx * 0.065 / disparity (disp1 files subsampled [::2, ::2];
0 where the disparity is missing or not positive), in metres.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _official
from ufm_jax.data.sources._bidirectional import BidirectionalPairs
from ufm_jax.geometry import sceneflow

LAYOUT = ("{train,test}/<seq>/frame_<cam>/frame_<cam>_%04d.png, flow_FW_<cam>/, flow_BW_<cam>/, "
          "maps/matchmap_flow_<FW|BW>_<cam>/, cam_data/; see data/spring/README.md")
BASELINE = 0.065


def _read_lines(path: str, n_values: int) -> np.ndarray:
  rows = []
  with open(path) as f:
    for lineno, line in enumerate(f, 1):
      if not line.strip():
        continue
      vals = line.split()
      if len(vals) != n_values:
        raise ValueError(f"{path}:{lineno}: expected {n_values} numbers, got {len(vals)}")
      rows.append([float(v) for v in vals])
  return np.array(rows, np.float64).reshape(-1, n_values)


class Spring(BidirectionalPairs):
  """Random-access Spring source.

  Args:
    root: dataset root holding train/ and test/.
    split: 'train' or 'test' (test has no GT: zero flow, all-False masks, meta["has_gt"] False).
    cameras: tuple of 'left' / 'right' (default both, as the paper's 9.9k pairs).
    directions: 'forward' or 'both'.
    full_gt: also return the 2x-resolution flow in meta["flow_full"].
    with_depth: also return z-depth maps meta["depth0"], meta["depth1"] (two more HDF5 reads).
  """

  has_backward = True
  static_scene = False

  def __init__(self, root, split: str = "train", cameras=("left", "right"),
               directions: str = "forward", full_gt: bool = False, with_depth: bool = False):
    if root is None:
      raise ValueError(f"spring: root is required; expected {LAYOUT}")
    if split not in ("train", "test"):
      raise ValueError(f"spring: split must be 'train' or 'test', got {split!r}")
    if directions not in ("forward", "both"):
      raise ValueError(f"spring: directions must be 'forward' or 'both', got {directions!r}")
    self.root = os.fspath(root)
    self.split_dir = io.check_dir(os.path.join(self.root, split), LAYOUT)
    self.split, self.directions, self.full_gt = split, directions, full_gt
    self.with_depth = with_depth
    self.has_gt = split == "train"
    self.pairs = []  # (seq, cam, k, k + 1)
    for seq in sorted(os.listdir(self.split_dir)):
      for cam in cameras:
        d = os.path.join(self.split_dir, seq, f"frame_{cam}")
        if not os.path.isdir(d):
          continue
        frames = sorted(int(m.group(1)) for f in os.listdir(d)
                        if (m := re.fullmatch(rf"frame_{cam}_(\d{{4}})\.png", f)))
        self.pairs += [(seq, cam, a, b) for a, b in zip(frames, frames[1:]) if b == a + 1]
    if not self.pairs:
      raise FileNotFoundError(f"{self.split_dir}: no consecutive frame pairs found; expected {LAYOUT}")
    self._cams: dict[str, tuple] = {}

  def _camera_data(self, seq: str):
    if seq not in self._cams:
      cam_dir = os.path.join(self.split_dir, seq, "cam_data")
      intr_path = os.path.join(cam_dir, "intrinsics.txt")
      intr = _read_lines(intr_path, 4) if os.path.isfile(intr_path) else None
      extr_path = os.path.join(cam_dir, "extrinsics.txt")
      extr = _read_lines(extr_path, 16).reshape(-1, 4, 4) if os.path.isfile(extr_path) else None
      self._cams[seq] = (intr, extr, intr_path, extr_path)
    return self._cams[seq]

  def _camera_meta(self, seq: str, cam: str, frame: int, suffix: str, meta: dict):
    intr, extr, intr_path, extr_path = self._camera_data(seq)
    if intr is not None:
      if frame > len(intr):
        raise ValueError(f"{intr_path}: {len(intr)} lines, frame {frame} needs line {frame}")
      fx, fy, cx, cy = intr[frame - 1]
      meta["K" + suffix] = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
    if extr is not None:
      if frame > len(extr):
        raise ValueError(f"{extr_path}: {len(extr)} lines, frame {frame} needs line {frame}")
      w2c = extr[frame - 1].copy()
      if cam == "right":
        w2c[0, 3] -= BASELINE
      meta["cam2world" + suffix] = np.linalg.inv(w2c)

  def _load(self, k: int, backward: bool, images=None) -> dict:
    seq, cam, a, b = self.pairs[k]
    src, dst = (b, a) if backward else (a, b)
    fb = "BW" if backward else "FW"
    base = os.path.join(self.split_dir, seq)
    if images is None:
      images = [io.read_image(os.path.join(base, f"frame_{cam}", f"frame_{cam}_{f:04d}.png"))
                for f in (src, dst)]
    image0, image1 = images
    h, w = image0.shape[:2]
    gt_relpath = f"{seq}/flow_{fb}_{cam}/flow_{fb}_{cam}_{src:04d}.flo5"
    meta = dict(dataset="spring", scene=seq, camera=cam, frame0=f"{src:04d}", frame1=f"{dst:04d}",
                direction="backward" if backward else "forward", split=self.split,
                gt_relpath=gt_relpath, has_gt=self.has_gt)
    self._camera_meta(seq, cam, src, "0", meta)
    self._camera_meta(seq, cam, dst, "1", meta)
    if not self.has_gt:
      zeros = np.zeros((h, w), bool)
      return dict(image0=image0, image1=image1, flow=np.zeros((h, w, 2), np.float32),
                  covisibility=zeros, flow_valid=zeros.copy(), covis_valid=zeros.copy(), meta=meta)
    flow_path = os.path.join(base, gt_relpath.split("/", 1)[1])
    if self.full_gt:
      full = io.read_flo5(flow_path)
      flow, full_hw = full[::2, ::2], full.shape[:2]  # a view: fill_invalid writes a copy
    else:
      flow, full_hw = io.read_flo5_strided(flow_path, 2)
    if full_hw != (2 * h, 2 * w):
      raise ValueError(f"{flow_path}: flow is {full_hw[0]}x{full_hw[1]}, expected the 2x "
                       f"resolution {2 * h}x{2 * w} of the {h}x{w} frames")
    flow_valid = np.isfinite(flow[..., 0]) & np.isfinite(flow[..., 1])
    flow = sceneflow.fill_invalid(flow, flow_valid)
    mm_path = os.path.join(base, "maps", f"matchmap_flow_{fb}_{cam}",
                           f"matchmap_flow_{fb}_{cam}_{src:04d}.png")
    matched = self._matched(mm_path, h, w)
    covisibility = matched & sceneflow.fov_mask(flow) & flow_valid
    if self.full_gt:
      meta["flow_full"] = full
    if self.with_depth:
      for suffix, frame in (("0", src), ("1", dst)):
        meta["depth" + suffix] = self._depth(base, cam, frame, h, w, meta.get("K" + suffix))
    return dict(image0=image0, image1=image1, flow=flow, covisibility=covisibility,
                flow_valid=flow_valid, covis_valid=flow_valid.copy(), meta=meta)

  @staticmethod
  def _depth(base: str, cam: str, frame: int, h: int, w: int, K) -> np.ndarray:
    path = os.path.join(base, f"disp1_{cam}", f"disp1_{cam}_{frame:04d}.dsp5")
    if K is None:
      raise FileNotFoundError(f"{os.path.join(base, 'cam_data', 'intrinsics.txt')}: needed to turn "
                              "disparity into depth (with_depth=True)")
    disp = io.read_dsp5(path)
    if disp.shape != (2 * h, 2 * w):
      raise ValueError(f"{path}: disparity is {disp.shape}, expected the 2x resolution {(2 * h, 2 * w)}")
    disp = disp[::2, ::2]
    with np.errstate(invalid="ignore", divide="ignore"):
      ok = np.isfinite(disp) & (disp > 0)
      return np.where(ok, np.float32(K[0, 0] * BASELINE) / disp, np.float32(0)).astype(np.float32)

  @staticmethod
  def _matched(path: str, h: int, w: int) -> np.ndarray:
    rgb = io.read_image(path, bgr=True)  # red: occluded, green: out of view
    if rgb.shape[:2] == (2 * h, 2 * w):
      rgb = rgb[::2, ::2]
    elif rgb.shape[:2] != (h, w):
      raise ValueError(f"{path}: matchmap is {rgb.shape[0]}x{rgb.shape[1]}, expected {h}x{w} or "
                       f"{2 * h}x{2 * w}")
    return (rgb[..., 2] == 0) & (rgb[..., 1] == 0)


@register("spring")
def make_spring(root, split: str = "train", **options) -> Spring:
  return Spring(root, split=split, **options)


# ------------------------------------------------------------------------ official processed layout

@register("spring_official")
class SpringProcessed(_official.PrecomputedPairs):
  """Spring as UFM's `preprocess_datasets/preprocess_spring.py` writes it (`spring_processed`,
  926x560, sequences 38 and up under test/), read like the official `uniflowmatch.datasets.Spring`:
    <root>/<split>/<seq>/<left|right>/images/%04d.png
    <root>/<split>/<seq>/<left|right>/flow/%04d_%04d.npz   flow_<i> (2, H, W) float32 (NaN = no
        ground truth), fov_mask_<i>, non_occluded_mask_<i>, occlusion_supervision_mask_<i>
        (H, W) bool; i = 0 forward (first -> second frame), 1 backward
  The official lists the npz files with an unsorted glob; here they are sorted (seq, camera,
  frames), so indices are stable across machines. NaN flow is kept (flow_valid is False there;
  the preprocess clears the masks of both views where the forward flow is NaN)."""

  def __init__(self, root, split="train"):
    if root is None:
      raise ValueError("spring_official: root is required (see data/spring/README.md)")
    self.root, self.split = os.fspath(root), split
    base = io.check_dir(os.path.join(self.root, split),
                        f"{split}/<seq>/<left|right>/{{images,flow}}/ (see data/spring/README.md)")
    self.files = []
    for seq in sorted(os.listdir(base)):
      for cam in ("left", "right"):
        d = os.path.join(base, seq, cam, "flow")
        if os.path.isdir(d):
          self.files += [os.path.join(d, f) for f in sorted(os.listdir(d))
                         if re.fullmatch(r"\d{4}_\d{4}\.npz", f)]
    if not self.files:
      raise FileNotFoundError(f"{base}: no <seq>/<left|right>/flow/%04d_%04d.npz files")

  def __len__(self):
    return len(self.files)

  def _views(self, index):
    path = self.files[index]
    cam_dir = os.path.dirname(os.path.dirname(path))
    a, b = os.path.basename(path)[:-4].split("_")
    images = [io.read_image(os.path.join(cam_dir, "images", f"{x}.png")) for x in (a, b)]
    z = _official.load_npz(path, [f"{q}_{i}" for i in (0, 1) for q in _official.LABELS])
    seq, cam = os.path.basename(os.path.dirname(cam_dir)), os.path.basename(cam_dir)
    fwd, bwd = _official.two_directions(
        "spring", images[0], images[1], lambda q, i: z[f"{q}_{i}"], path, scene=seq, camera=cam,
        frame0=a, frame1=b, split=self.split, suitable_for_refinement=False)
    bwd["meta"].update(frame0=b, frame1=a)
    return [fwd, bwd]
