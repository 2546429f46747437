"""The official hue jitter through lookup tables (ufm_jax.data.hsv_tables) against its
references: Pillow's HSV conversions written from its C code in numpy (every colour, both
directions; ufm_jax.testing.color_reference) and a hand copy of torchvision's adjust_hue of a PIL
image run on Pillow (the split / shifted hue plane / merge it runs; torchvision is not
installed), for every hue shift ColorJitter(hue=0.1) draws."""

import numpy as np
from PIL import Image

from ufm_jax.data import augment, hsv_tables
from ufm_jax.testing import color_reference


def test_tables_are_pillows_conversions_on_every_colour():
  to_hsv, to_rgb = hsv_tables.tables()
  n = (1 << 24) // 16
  for k, px in enumerate(color_reference.all_colours(16)):
    rows = slice(k * n, (k + 1) * n)
    for table, ref in ((to_hsv, color_reference.rgb_to_hsv(px)),
                       (to_rgb, color_reference.hsv_to_rgb(px))):
      got = np.asarray(table[rows]).view(np.uint8).reshape(n, 4)[:, :3]
      bad = np.flatnonzero((got != ref).any(-1))
      assert bad.size == 0, (k, bad[:5], got[bad[:5]], ref[bad[:5]])


def _torchvision_pil(img, hue_factor):
  """A hand copy of torchvision/transforms/_functional_pil.py's adjust_hue (torchvision is not
  installed), run on Pillow."""
  h, s, v = Image.fromarray(img).convert("HSV").split()
  np_h = np.array(h, dtype=np.uint8)
  np_h += np.int32(hue_factor * 255).astype(np.uint8)
  return np.asarray(Image.merge("HSV", (Image.fromarray(np_h, "L"), s, v)).convert("RGB"))


def test_adjust_hue_is_torchvision_adjust_hue():
  rng = np.random.default_rng(0)
  img = rng.integers(0, 256, (37, 53, 3)).astype(np.uint8)
  img[:5] = img[:5, :1]                      # grey and flat pixels too
  for shift in range(-25, 26):               # int8(U(-0.1, 0.1) * 255)
    factor = (shift + 0.5 * np.sign(shift)) / 255
    want = color_reference.adjust_hue(img, factor)
    np.testing.assert_array_equal(hsv_tables.adjust_hue(img, shift), want, err_msg=str(shift))
    np.testing.assert_array_equal(_torchvision_pil(img, factor), want, err_msg=str(shift))
  colours = next(color_reference.all_colours(64)).reshape(512, 512, 3)
  for factor in (-0.1, -0.03, 0.004, 0.0999):
    np.testing.assert_array_equal(augment.color_jitter(colours, ((3,), 1.0, 1.0, 1.0, factor)),
                                  _torchvision_pil(colours, factor))
