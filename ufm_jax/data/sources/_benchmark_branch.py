"""What the official benchmark branch does to its wide-baseline data before scoring (etola/UFM
`benchmark`, 2a949e5; paths below are relative to its root), for the `*_official` sources:

  * `crop_resize_view`: ETH3D / DTU views, `BaseStereoViewDataset._crop_resize_if_necessary`
    (uniflowmatch/datasets/base/base_stereo_view_dataset.py:183-211 with
    uniflowmatch/datasets/utils/cropping.py:60-132), by ufm_jax.data.official_ops, which the
    training augmentation uses too;
  * `resize_short_center_crop`: TA-WB's precomputed labels, `ResizeShortAxisManipulation` then
    `CenterCropManipulation` (uniflowmatch/datasets/base/base_optical_flow_dataset.py:64-106,
    uniflowmatch/datasets/utils/flow_manipulation.py:224-347, 366-502), by official_ops too;
  * `BranchPosedPairs`: a dense bench over posed views listed in an AnyMap pair table
    (uniflowmatch/datasets/{eth3d,dtu}.py), labelled by the training code's rule
    (`flow_occlusion_post_processing`, the same on both branches): ufm_jax.geometry.official_labels
    with the bench's geometry.thresholds.BENCHMARK_RENDERING_PARAMETERS.
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax import geometry
from ufm_jax.data import io, official_ops

BENCH_SIZE = (420, 560)  # (H, W): `resolution=(560, 420)` (W, H) of every wide-baseline bench
_F = np.float32


# ------------------------------------------------------------------------------ ETH3D / DTU views
def crop_resize_view(image: np.ndarray, depth: np.ndarray, K: np.ndarray, cam2world=None,
                     size=BENCH_SIZE, where: str = "view"):
  """Resize so that the image covers `size` (H, W), then centre-crop to it
  (`official_ops.resize_cover_center_crop`, with K and the pose in float32 as the branch's
  arrays). A portrait view (H > 1.1 W) is cropped to the transposed size and turned to landscape
  as the branch does (`transpose_to_landscape` -> `rotate_90(k=1)`,
  base_stereo_view_dataset.py:194-196, 417, 492-529): image and depth counter-clockwise, K's
  focal lengths swapped and principal point (cy, W - 1 - cx), the pose turned about its z axis.

  Returns (image [H', W', 3] uint8, depth [H', W'] float32, K float32, cam2world float32 (the
  identity when none is given)).
  """
  h, w = image.shape[:2]
  if depth.shape != (h, w):
    raise ValueError(f"{where}: image is {h}x{w} but depth is {depth.shape}")
  c2w = np.eye(4, dtype=_F) if cam2world is None else np.asarray(cam2world, _F)
  v = official_ops.resize_cover_center_crop(
      official_ops.StaticView(image, depth, np.array(K, _F), c2w), size)
  return v.image, v.depth, np.asarray(v.K, _F), np.asarray(v.cam2world, _F)


# --------------------------------------------------------------------------- TA-WB stored labels
def resize_short_center_crop(image0, image1, flow, masks, size=BENCH_SIZE):
  """Stored labels -> the bench crop (ResizeShortAxis + CenterCrop of the branch:
  `official_ops.center_flow_crop`, images exact to torch's).

  image0/1 [H, W, 3] uint8, flow [H, W, 2], masks {name: [H, W] bool} with `non_occluded` (and
  optionally `fov`, `occlusion_supervision`). `non_occluded` then also requires the flow target
  inside the crop, and the other masks are ANDed with the cropped `non_occluded` before that test
  (flow_manipulation.py:295-313: the branch's `additional_masks`).
  Returns (image0, image1, flow, masks) at `size`.
  """
  if image1.shape != image0.shape:
    raise ValueError(f"image shapes differ: {image0.shape} vs {image1.shape}")
  crop = official_ops.center_flow_crop(image0.shape[:2], size)
  image0, image1 = official_ops.flow_crop_images(image0, image1, crop, exact=True)
  names = {"non_occluded": "covisibility", "fov": "fov_mask",
           "occlusion_supervision": "covis_valid"}
  unknown = sorted(set(masks) - set(names))
  if unknown or "non_occluded" not in masks:
    raise ValueError(f"masks {sorted(masks)}: need non_occluded, optionally fov and "
                     "occlusion_supervision")
  labels = official_ops.flow_crop_labels(
      {"flow": flow, **{names[k]: m for k, m in masks.items()}}, crop, 0, "center_forward")
  return (image0, image1, labels["flow"], {k: labels[names[k]] for k in masks})


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
  `geometry.official_labels` gives flow (0 -> 1), covisibility (the branch's `covisible_mask`),
  flow_valid (its `valid_mask`: in view and valid source depth) and covis_valid (its
  `occlusion_supervision_mask`). Subclasses set name, pairs_file, stride, thresholds ((absolute,
  temperature, relative) of geometry.thresholds.BENCHMARK_RENDERING_PARAMETERS) and implement
  `load_view`.
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
      views.append(crop_resize_view(image, depth, K, np.linalg.inv(np.asarray(w2c, _F)),
                                    self.size, f"{self.name}:{scene}/{f}"))
    (im0, d0, K0, c2w0), (im1, d1, K1, c2w1) = views
    lab = geometry.official_labels(d0, K0, c2w0, d1, K1, c2w1, self.thresholds)
    meta = dict(dataset=self.name, scene=scene, frame0=f0, frame1=f1, K0=K0, K1=K1,
                cam2world0=c2w0, cam2world1=c2w1, depth0=d0, depth1=d1,
                gt_relpath=f"{scene}/{f0}_{f1}.flo")
    return dict(image0=im0, image1=im1, flow=lab["flow"], covisibility=lab["covisibility"],
                flow_valid=lab["flow_valid"], covis_valid=lab["covis_valid"], meta=meta)

