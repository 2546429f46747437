"""`frames`: video frames paired at strides, without labels (distillation, configs/distill.py).

  src = get_source("frames", "/path/to/frames", strides=(1, 2, 4))
  src.images(i)   -> (image0, image1) HWC uint8 RGB

`root` is a folder of frames read as `python -m ufm_jax infer --frames` reads one
(`frame_pairs`: image files in natural sort order, frame k paired with frame
k + stride), or a folder of such folders (one recording each). Every stride of `strides` pairs
every frame with the one that many frames later; pair i is (recording, stride, k) in that order.
There are no labels: `src[i]` refuses, so only a run that reads images alone (distillation rows,
ufm_jax.data.distill_rows) can train on it. An unreadable frame raises ValueError naming its path
(the pipeline skips and counts the pair).
"""

from __future__ import annotations

import pathlib
import re

from ufm_jax.data import io
from ufm_jax.data.registry import register


def natural_key(name: str):
  return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", str(name))]


def frame_pairs(folder, stride: int = 1) -> list[tuple[str, str]]:
  files = sorted((p for p in pathlib.Path(folder).iterdir() if p.suffix.lower() in io.IMAGE_SUFFIXES),
                 key=lambda p: natural_key(p.name))
  if len(files) < stride + 1:
    raise ValueError(f"{folder}: {len(files)} images; need at least {stride + 1} for --stride {stride}")
  return [(str(files[i]), str(files[i + stride])) for i in range(len(files) - stride)]


def _has_frames(folder: pathlib.Path) -> bool:
  return any(p.suffix.lower() in io.IMAGE_SUFFIXES for p in folder.iterdir() if p.is_file())


@register("frames")
class Frames:
  has_backward = False
  static_scene = False

  def __init__(self, root, strides=(1,), split: str | None = None):
    del split   # one folder of recordings serves every split
    if root is None or not pathlib.Path(root).is_dir():
      raise FileNotFoundError(f"frames: root {root!r} is not a folder of frames")
    strides = (strides,) if isinstance(strides, int) else tuple(int(s) for s in strides)
    if not strides or min(strides) < 1:
      raise ValueError(f"frames: strides {strides} must be positive frame counts")
    root = pathlib.Path(root)
    folders = [root] if _has_frames(root) else sorted(
        (p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and
         _has_frames(p)), key=lambda p: p.name)
    if not folders:
      raise FileNotFoundError(f"frames: no image files ({', '.join(io.IMAGE_SUFFIXES)}) in {root} "
                              "or its sub-folders")
    self.root = root
    self.pairs = []
    for folder in folders:
      for s in strides:
        try:
          self.pairs += frame_pairs(folder, s)
        except ValueError:   # a recording shorter than the stride gives no pairs at it
          continue
    if not self.pairs:
      raise FileNotFoundError(f"frames: no pairs at strides {strides} in {root}")

  def __len__(self):
    return len(self.pairs)

  def images(self, index):
    a, b = self.pairs[index]
    return io.read_image(a), io.read_image(b)

  def __getitem__(self, index):
    a, b = self.pairs[index]
    raise ValueError(f"frames[{index}] ({a}, {b}): video frames have no labels; train on them "
                     "with configs/distill.py (a teacher's predictions as targets)")
