"""TA-WB training pairs as the UFM authors ship them: the assembled TartanAir h5 shards read by the
official `uniflowmatch.datasets.TartanairAssembled` (the `tartanair_v2` row of the mixture in
the official recipes). The benchmark layout of TA-WB is `tawb.py`.

Layout under root (`<root_data_dir>/TartanAir/assembled/tartanair_640_mega_training_0328_good`,
the Hugging Face `infinity1096/TA-WB` download; see data/tartanair_v2/README.md):
  <split>/*.h5    per pair: img0, img1 (N, H, W, 3) uint8; flow_fwd, flow_bwd (N, 2, H, W);
                  non_occluded_fwd|bwd, occlusion_supervision_mask_fwd|bwd, fov_mask_fwd|bwd
                  (N, H, W) bool
  <split>/*.json  index maps {pair index: [file, index in file]} or {..: {file_name, file_index}}
                  (match_errors.json, which holds `forward_match_errors`, is not one)
split 'train' reads train/, 'val' val/. Labels are the shards' precomputed masks (covisibility =
non_occluded, covis_valid = occlusion_supervision_mask, fov in meta); flow is cast to float32 as
the official `.float()` does, so float16 shards read the same way.
"""

from __future__ import annotations

import os

from ufm_jax.data import io
from ufm_jax.data.registry import register
from ufm_jax.data.sources import _official

KEYS = ("img0", "img1", "flow_fwd", "flow_bwd", "non_occluded_fwd", "non_occluded_bwd",
        "occlusion_supervision_mask_fwd", "occlusion_supervision_mask_bwd", "fov_mask_fwd",
        "fov_mask_bwd")
# Our label names -> the shard's dataset name stems.
_STEMS = {"flow": "flow", "non_occluded_mask": "non_occluded",
          "occlusion_supervision_mask": "occlusion_supervision_mask", "fov_mask": "fov_mask"}


@register("tartanair_assembled")
class TartanAirAssembled(_official.PrecomputedPairs):

  def __init__(self, root, split="train"):
    if root is None:
      raise ValueError("tartanair_assembled: root is required (see data/tartanair_v2/README.md)")
    self.root, self.split = os.fspath(root), split
    folder = io.check_dir(os.path.join(self.root, "val" if split == "val" else "train"),
                          "train/ with *.h5 shards and *.json index maps "
                          "(see data/tartanair_v2/README.md)")
    self.index = _official.H5Index(folder)

  def __len__(self):
    return len(self.index)

  def _views(self, index):
    i = self.index.keys[index]
    path, pos = self.index.location(i)
    d = self.index.read(i, KEYS)
    where = f"{path}[{pos}]"
    img0, img1 = (_official.rgb_u8(d[k], where) for k in ("img0", "img1"))
    return _official.two_directions(
        "tartanair_v2", img0, img1, lambda q, v: d[f"{_STEMS[q]}_{('fwd', 'bwd')[v]}"], where,
        scene=str(i), pair_index=i, suitable_for_refinement=False)
