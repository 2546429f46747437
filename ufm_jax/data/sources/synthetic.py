"""`synthetic`: the embedded procedural posed-scene dataset (ufm_jax.data.synthetic), no files.

  src = get_source("synthetic", None, split="train", num_pairs=10000, seed=0, size=(112, 112))
  src[i]            -> sample dict, view 0 -> view 1
  src.backward(i)   -> the same pair reversed (view 1 -> view 0), labels computed from geometry
  src.both(i)       -> (forward, backward) from one rendering (what symmetrized batches want)

`root` is ignored (nothing is read from disk). Pair i of a split is rendered from
SeedSequence([seed, split, i]), so any index is reproducible on its own and the train, val and
test streams never share a scene. meta holds K0, K1, cam2world0, cam2world1 (OpenCV c2w), depth0,
depth1 (z-depth), segmentation0 (1 = the moving object), pair_type, view_angle_deg; that of
`pair_type="shift"` pairs (translated textures, no scene) only pair_type and the shift (dx, dy);
that of `"layers"` pairs also layer_shift (the rectangle's) and layer_rect (top, left, h, w).
"""

from __future__ import annotations

from ufm_jax.data import synthetic
from ufm_jax.data.registry import register


@register("synthetic")
class SyntheticSource:
  has_backward = True
  static_scene = False   # moving objects; its own backward labels cover every pair type

  def __init__(self, root=None, split: str = "train", num_pairs: int | None = None, seed: int = 0,
               size=(112, 112), pair_type: str = "mixed", moving_object_prob: float = 0.5,
               max_view_angle_deg: float = 90.0, subpixel_search: float = 0.0,
               max_shift: int = 10, aligned_shift_frac: float = 0.0):
    del root  # generated, not read
    if num_pairs is None:
      num_pairs = 10000 if split == "train" else 200
    if int(num_pairs) <= 0:
      raise ValueError(f"synthetic: num_pairs must be positive, got {num_pairs}")
    synthetic.pair_seed(seed, split, 0)  # validates split
    self.split, self.seed, self.num_pairs = split, int(seed), int(num_pairs)
    self.config = synthetic.SyntheticConfig(
        size=synthetic.parse_size(size), pair_type=pair_type,
        moving_object_prob=moving_object_prob, max_view_angle_deg=max_view_angle_deg,
        subpixel_search=subpixel_search, max_shift=int(max_shift),
        aligned_shift_frac=float(aligned_shift_frac))

  def __len__(self):
    return self.num_pairs

  def _check(self, index):
    index = int(index)
    if not -self.num_pairs <= index < self.num_pairs:
      raise IndexError(f"synthetic[{self.split}]: index {index} out of range ({self.num_pairs})")
    return index % self.num_pairs

  def _generate(self, index, directions):
    index = self._check(index)
    samples = synthetic.generate_pair(synthetic.pair_seed(self.seed, self.split, index),
                                      self.config, directions)
    for sample in samples:
      sample["meta"].update(scene=f"{self.split}_{self.seed}_{index:06d}", index=index)
    return samples

  def __getitem__(self, index):
    return self._generate(index, (0,))[0]

  def backward(self, index):
    return self._generate(index, (1,))[0]

  def both(self, index):
    """(forward, backward) from a single rendering."""
    return self._generate(index, (0, 1))
