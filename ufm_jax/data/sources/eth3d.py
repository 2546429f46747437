"""ETH3D high-res multi-view (training scenes) as a dense-correspondence benchmark.

The official GT depth is aligned with the distorted DSLR images (THIN_PRISM_FISHEYE) and is
6048x4032 raw float32; `python data/eth3d/prepare.py` resamples it into the undistorted PINHOLE
geometry (optionally downscaled) and writes a WAI-style tree, which is what this reader reads:
  <scene>/scene_meta.json   frames with file_path, depth, transform_matrix (c2w, OpenCV), fl_x,
                            fl_y, cx, cy (OpenCV pixel-centre convention)
  <scene>/images/<DSC_xxxx>.jpg, <scene>/depth/<DSC_xxxx>.exr (z-depth, metres, 0 = none)
Pairs: `<root>/pairs_test.txt` (written by the preparation tool: every view pair of a scene with
mutual covisibility above its --min_covis). See data/eth3d/README.md.
"""

from __future__ import annotations

import os

from ufm_jax.data.registry import register
from ufm_jax.data.sources import posed
from ufm_jax.data.sources.scannetpp import WaiScenes, wai_view


@register("eth3d")
class ETH3D(WaiScenes, posed.PosedPairSource):
  name = "eth3d"
  has_backward = False
  static_scene = True

  def __init__(self, root, split="test", pairs=None, thresholds=None):
    super().__init__(root, split, pairs, thresholds)

  def scenes(self):
    return self.wai_scenes()

  def default_pairs(self):
    raise FileNotFoundError(
        f"{os.path.join(self.root, f'pairs_{self.split}.txt')}: missing ETH3D pair list; build the "
        "tree and the list with `python data/eth3d/prepare.py` (see data/eth3d/README.md)")

  def load_view(self, scene, frame):
    m = self._meta(scene)
    if frame not in m["frames"]:
      raise KeyError(f"{os.path.join(self.root, scene, 'scene_meta.json')}: no frame {frame!r}")
    return wai_view(os.path.join(self.root, scene), m["meta"], m["frames"][frame],
                    depth_keys=("depth",))
