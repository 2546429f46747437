"""What the official benchmark branch does to its wide-baseline data before scoring (etola/UFM
`benchmark`, 2a949e5; paths below are relative to its root), for the `*_official` sources:

  * `crop_resize_view`: ETH3D / DTU views, `BaseStereoViewDataset._crop_resize_if_necessary`
    (uniflowmatch/datasets/base/base_stereo_view_dataset.py:183-211 with
    uniflowmatch/datasets/utils/cropping.py:60-132);
  * `resize_short_center_crop`: TA-WB's precomputed labels, `ResizeShortAxisManipulation` then
    `CenterCropManipulation` (uniflowmatch/datasets/base/base_optical_flow_dataset.py:64-106,
    uniflowmatch/datasets/utils/flow_manipulation.py:224-347, 366-502);
  * `BranchPosedPairs`: a dense bench over posed views listed in an AnyMap pair table
    (uniflowmatch/datasets/{eth3d,dtu}.py), labelled by
    ufm_jax.geometry.benchmark_labels.branch_static_labels.
"""

from __future__ import annotations

import os

import cv2
import numpy as np

from ufm_jax.data import io
from ufm_jax.geometry import benchmark_labels

BENCH_SIZE = (420, 560)  # (H, W): `resolution=(560, 420)` (W, H) of every wide-baseline bench
_F = np.float32


# ------------------------------------------------------------------------------ ETH3D / DTU views
def _crop_camera(K, in_wh, out_wh, scaling=1.0):
  """cropping.camera_matrix_of_crop: scale about COLMAP pixel corners, shift by half the margin;
  float32 in place as the branch's arrays."""
  margins = np.asarray(in_wh, np.float64) * scaling - np.asarray(out_wh, np.float64)
  if (margins < 0).any():
    raise ValueError(f"crop of {tuple(out_wh)} does not fit in {tuple(in_wh)} x {scaling}")
  K = np.array(K, _F)
  K[:2, 2] += _F(0.5)
  K[:2, :] *= np.float64(scaling)
  K[:2, 2] -= 0.5 * margins
  K[:2, 2] -= _F(0.5)
  return K


def crop_resize_view(image: np.ndarray, depth: np.ndarray, K: np.ndarray, size=BENCH_SIZE,
                     where: str = "view"):
  """Resize so that the image covers `size` (H, W), then centre-crop to it.

  scale = max(W' / W, H' / H) + 1e-8, the resized size floor((W, H) * scale); the image with PIL
  Lanczos when shrinking, bicubic otherwise, the depth with OpenCV nearest; the crop box is the
  rounded shift of the principal point (cropping.py:60-132). Returns (image [H', W', 3] uint8,
  depth [H', W'] float32, K float32). Portrait views (H > 1.1 W), which the branch crops in
  portrait and turns to landscape, are refused; the benchmark data has none.
  """
  import PIL.Image

  h, w = image.shape[:2]
  if depth.shape != (h, w):
    raise ValueError(f"{where}: image is {h}x{w} but depth is {depth.shape}")
  if h > 1.1 * w:
    raise ValueError(f"{where}: portrait view {h}x{w}; the official benches only have landscape")
  out_wh = np.array([size[1], size[0]])
  scale = np.max(out_wh / np.array([w, h])) + 1e-8  # a float64 scalar, as the branch's
  new_wh = np.floor(np.array([w, h]) * scale).astype(int)
  resample = PIL.Image.Resampling.LANCZOS if scale < 1 else PIL.Image.Resampling.BICUBIC
  img = np.asarray(PIL.Image.fromarray(np.ascontiguousarray(image)).resize(tuple(new_wh), resample))
  depth = cv2.resize(np.asarray(depth, _F), tuple(int(v) for v in new_wh),
                     interpolation=cv2.INTER_NEAREST)
  K = _crop_camera(K, (w, h), new_wh, scale)
  K_crop = _crop_camera(K, new_wh, out_wh)
  left, top = np.round(K[:2, 2] - K_crop[:2, 2]).astype(np.int32)
  img = img[top:top + size[0], left:left + size[1]]
  depth = depth[top:top + size[0], left:left + size[1]]
  K[0, 2] -= left
  K[1, 2] -= top
  return np.ascontiguousarray(img), np.ascontiguousarray(depth), K


# --------------------------------------------------------------------------- TA-WB stored labels
def resize_short_center_crop(image0, image1, flow, masks, size=BENCH_SIZE):
  """Stored labels -> the bench crop (ResizeShortAxis + CenterCrop of the branch).

  image0/1 [H, W, 3] uint8, flow [H, W, 2], masks {name: [H, W] bool} with `non_occluded`.
  Resize by r = max(H' / H + 1e-8, W' / W + 1e-8) to (int(H r), int(W r)): images with torch's
  antialiased bilinear and a truncating cast to uint8, flow and masks with legacy nearest (flow
  scaled per axis); centre crop; `non_occluded` then also requires the flow target inside the crop
  (0 <= x < W', 0 <= y < H'), and every other mask is ANDed with the cropped `non_occluded` before
  that test (flow_manipulation.py:295-313: the branch's `additional_masks`).
  Returns (image0, image1, flow, masks) at `size`.
  """
  from ufm_jax import inference

  h, w = image0.shape[:2]
  if image1.shape != image0.shape:
    raise ValueError(f"image shapes differ: {image0.shape} vs {image1.shape}")
  th, tw = size
  r = max(th / h + 1e-8, tw / w + 1e-8)
  rh, rw = int(h * r), int(w * r)

  def img(x):
    return inference.resize_bilinear_aa(np.asarray(x, _F), (rh, rw)).astype(np.uint8)

  image0, image1 = img(image0), img(image1)
  flow = inference.resize_nearest(np.asarray(flow, _F), (rh, rw)).copy()
  flow[..., 0] *= rw / w
  flow[..., 1] *= rh / h
  masks = {k: inference.resize_nearest(np.asarray(m, bool), (rh, rw)) for k, m in masks.items()}
  top, left = (rh - th) // 2, (rw - tw) // 2
  crop = (slice(top, top + th), slice(left, left + tw))
  image0, image1, flow = image0[crop], image1[crop], np.ascontiguousarray(flow[crop])
  masks = {k: m[crop] for k, m in masks.items()}
  gy, gx = np.mgrid[0:th, 0:tw].astype(_F)
  tx, ty = gx + flow[..., 0], gy + flow[..., 1]
  inside = (tx >= 0) & (ty >= 0) & (tx < tw) & (ty < th)
  nonocc = masks["non_occluded"]
  out = {k: m & nonocc for k, m in masks.items() if k != "non_occluded"}
  out["non_occluded"] = nonocc & inside
  return np.ascontiguousarray(image0), np.ascontiguousarray(image1), flow, out


# ----------------------------------------------------------------------------- AnyMap pair tables
def read_pair_table(path: str) -> list[tuple[str, str, str]]:
  """AnyMap `<set>_valid_pairs.npz`: key `data`, rows (scene, view0, view1, score)."""
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: missing pair table (download_pairs_eth3d_dtu.sh)")
  with np.load(path, allow_pickle=False) as z:
    if "data" not in z.files:
      raise ValueError(f"{path}: no `data` array (expected rows scene, view0, view1, score)")
    try:
      rows = z["data"]
    except ValueError:  # an object array (as the release stores it): needs pickle
      with np.load(path, allow_pickle=True) as zp:
        rows = zp["data"]
  rows = np.asarray(rows)
  if rows.ndim != 2 or rows.shape[1] < 3 or len(rows) == 0:
    raise ValueError(f"{path}: `data` is {rows.shape}, expected [N, 4] rows (scene, view0, "
                     "view1, score)")
  text = lambda x: x.decode() if isinstance(x, bytes) else str(x)  # noqa: E731 (bytes arrays)
  return [(text(r[0]), text(r[1]), text(r[2])) for r in rows]


class BranchPosedPairs:
  """A wide-baseline dense bench of the benchmark branch over posed views.

  Pairs: every `stride`-th row of the pair table. Both views go through `crop_resize_view`, then
  `branch_static_labels` gives flow (0 -> 1), covisibility (the branch's `covisible_mask`),
  flow_valid (its `valid_mask`: in view and valid source depth) and covis_valid (its
  `occlusion_supervision_mask`). Subclasses set name, pairs_file, stride, thresholds (a, T, r of
  benchmark_labels.BRANCH_THRESHOLDS) and implement `load_view`.
  """

  name = "branch"
  pairs_file = ""
  stride = 1
  thresholds = (0.1, 0.1, 0.005)
  has_backward = False
  static_scene = False  # benchmark samples: no backward labels, not for the training pipeline

  def __init__(self, root, pairs=None, stride=None, size=BENCH_SIZE):
    if root is None:
      raise ValueError(f"{self.name}: a root is required (see data/{self.name.split('_')[0]}/)")
    self.root = os.fspath(root)
    io.check_dir(self.root, f"the {self.name} scenes folder")
    self.pairs_path = pairs or self.default_pairs_path()
    stride = self.stride if stride is None else int(stride)
    self.pairs = read_pair_table(self.pairs_path)[::stride]
    self.size = tuple(size)

  def default_pairs_path(self) -> str:
    """`anymap_data_pairs/<file>` beside the scenes folder (the official data root), else inside
    it, else the file itself inside it."""
    parent = os.path.dirname(os.path.abspath(self.root))
    options = [os.path.join(parent, "anymap_data_pairs", self.pairs_file),
               os.path.join(self.root, "anymap_data_pairs", self.pairs_file),
               os.path.join(self.root, self.pairs_file)]
    for p in options:
      if os.path.isfile(p):
        return p
    raise FileNotFoundError(f"{self.name}: no pair table; looked for {', '.join(options)} (get it "
                            "with the official download_pairs_eth3d_dtu.sh)")

  def load_view(self, scene: str, view: str):
    """-> (image [H, W, 3] uint8, depth [H, W] float32, K [3, 3], world2cam [4, 4])."""
    raise NotImplementedError

  def __len__(self):
    return len(self.pairs)

  def __getitem__(self, i):
    scene, f0, f1 = self.pairs[i]
    views = []
    for f in (f0, f1):
      image, depth, K, w2c = self.load_view(scene, f)
      image, depth, K = crop_resize_view(image, depth, K, self.size, f"{self.name}:{scene}/{f}")
      views.append((image, depth, K, np.linalg.inv(np.asarray(w2c, _F))))
    (im0, d0, K0, c2w0), (im1, d1, K1, c2w1) = views
    lab = benchmark_labels.branch_static_labels(d0, K0, c2w0, d1, K1, c2w1, self.thresholds)
    meta = dict(dataset=self.name, scene=scene, frame0=f0, frame1=f1, K0=K0, K1=K1,
                cam2world0=c2w0, cam2world1=c2w1, depth0=d0, depth1=d1,
                gt_relpath=f"{scene}/{f0}_{f1}.flo")
    return dict(image0=im0, image1=im1, flow=lab["flow"], covisibility=lab["non_occluded"],
                flow_valid=lab["fov_mask"], covis_valid=lab["occlusion_supervision"], meta=meta)


def load_npy(path: str, what: str, shape=None) -> np.ndarray:
  """A .npy array, with its path in every error."""
  if not os.path.isfile(path):
    raise FileNotFoundError(f"{path}: missing file (expected {what})")
  try:
    arr = np.load(path, allow_pickle=False)
  except ValueError as e:
    raise ValueError(f"{path}: not a .npy array ({e})") from None
  if shape is not None and arr.size != int(np.prod(shape)):
    raise ValueError(f"{path}: expected {what} of shape {shape}, got {arr.shape}")
  return arr.reshape(shape) if shape is not None else arr
