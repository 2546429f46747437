"""ScanNet-1500 (SuperGlue's 1500 test pairs) for relative-pose evaluation (AUC@5/10/20).

Layout under root (see data/scannet1500/README.md):
  scannet_test_pairs_with_gt.txt   SuperGlue's list: `name0 name1 rot0 rot1 K0(9) K1(9) T_0to1(16)`
                                   K for the original 1296x968 colour images; T_0to1 maps camera-0
                                   coordinates to camera-1 coordinates (x1 = R x0 + t)
  images, looked up in this order for `scene0707_00_frame-000015.jpg` (or a listed relative path):
    <root>/<name as listed>
    <root>/scans_test/<scene>/color/<frame>.jpg       (ScanNet SensReader export)
    <root>/scannet_test_1500/<scene>/color/<frame>.jpg (LoFTR's test tarball)
    <root>/<scene>/color/<frame>.jpg
K is rescaled per axis when the image found is not 1296x968 (as LoFTR / RoMa do).

This is a pose-only benchmark: the sample has no dense ground truth. `flow` is zeros and
`flow_valid`, `covisibility`, `covis_valid` are all False; the pose lives in meta:
`K0`, `K1` (for the returned images), `cam2world0` = identity, `cam2world1` = inverse(T_0to1) (so
the generic relative pose inverse(cam2world1) @ cam2world0 equals T_0to1), and `T_0to1` itself.
"""

from __future__ import annotations

import os

import numpy as np

from ufm_jax.data.registry import register
from ufm_jax.data import io
from ufm_jax.data.sources import posed

PAIRS_FILE = "scannet_test_pairs_with_gt.txt"
ORIGINAL_WH = (1296, 968)


def read_superglue_pairs(path):
  posed.require_file(path, "SuperGlue's scannet_test_pairs_with_gt.txt")
  out = []
  with open(path) as f:
    for n, line in enumerate(f, 1):
      w = line.split()
      if not w:
        continue
      if len(w) != 38:
        raise ValueError(f"{path}:{n}: expected 38 fields (2 names, 2 rotations, 2x9 K, 16 "
                         f"T_0to1), got {len(w)}")
      nums = np.array(w[2:], np.float64)
      if nums[0] or nums[1]:
        raise ValueError(f"{path}:{n}: EXIF rotations other than 0 are not supported")
      out.append(dict(name0=w[0], name1=w[1], K0=nums[2:11].reshape(3, 3),
                      K1=nums[11:20].reshape(3, 3), T_0to1=nums[20:36].reshape(4, 4)))
  return out


def _scene_frame(name):
  base = os.path.basename(name)
  if "_frame-" in base:  # scene0707_00_frame-000015.jpg
    scene, frame = base.split("_frame-")
  else:  # scans_test/scene0707_00/sens/frame-000015.color.jpg
    scene = next(p for p in name.split("/") if p.startswith("scene"))
    frame = base.split("frame-")[-1]
  return scene, str(int(frame.split(".")[0]))


@register("scannet1500")
class ScanNet1500:
  name = "scannet1500"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="test", pairs=None):
    if root is None:
      raise ValueError("scannet1500: a dataset root is required (see data/scannet1500/README.md)")
    self.root = posed.require_dir(os.fspath(root), "the ScanNet-1500 root "
                                   "(data/scannet1500/README.md)")
    self.pairs = read_superglue_pairs(pairs or os.path.join(self.root, PAIRS_FILE))

  def __len__(self):
    return len(self.pairs)

  def _image_path(self, name):
    scene, frame = _scene_frame(name)
    candidates = [os.path.join(self.root, name),
                  os.path.join(self.root, "scans_test", scene, "color", f"{frame}.jpg"),
                  os.path.join(self.root, "scannet_test_1500", scene, "color", f"{frame}.jpg"),
                  os.path.join(self.root, scene, "color", f"{frame}.jpg")]
    for c in candidates:
      if os.path.isfile(c):
        return c
    raise FileNotFoundError(f"ScanNet-1500 image {name} not found; looked for: "
                            + ", ".join(candidates))

  def __getitem__(self, i):
    p = self.pairs[i]
    images, Ks = [], []
    for k in (0, 1):
      img = io.read_image(self._image_path(p[f"name{k}"]))
      K = p[f"K{k}"].copy()
      h, w = img.shape[:2]
      K[0] *= w / ORIGINAL_WH[0]
      K[1] *= h / ORIGINAL_WH[1]
      images.append(img)
      Ks.append(K)
    h, w = images[0].shape[:2]
    scene, f0 = _scene_frame(p["name0"])
    _, f1 = _scene_frame(p["name1"])
    meta = dict(dataset=self.name, scene=scene, frame0=f0, frame1=f1,
                K0=Ks[0].astype(np.float32), K1=Ks[1].astype(np.float32),
                cam2world0=np.eye(4, dtype=np.float32),
                cam2world1=np.linalg.inv(p["T_0to1"]).astype(np.float32),
                T_0to1=p["T_0to1"].astype(np.float32))
    return dict(image0=images[0], image1=images[1], flow=np.zeros((h, w, 2), np.float32),
                covisibility=np.zeros((h, w), bool), flow_valid=np.zeros((h, w), bool),
                covis_valid=np.zeros((h, w), bool), meta=meta)
