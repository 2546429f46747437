"""Kubric's float colour jitter (augment.color_jitter_float) against torchvision's tensor path.

torchvision is not importable beside the venv's torch 2.13.0, so the reference is the hand copy
`ufm_jax.testing.color_reference.torchvision_tensor_jitter` of torchvision's
transforms/_functional_tensor.py (_blend, rgb_to_grayscale, adjust_hue's _rgb2hsv / _hsv2rgb),
run in torch. Prints, over `--draws` jitter draws (ColorJitter's order is a permutation of all
four operations, so every draw shifts the hue; each on a fresh blurred random image, as
tests/test_augment.py builds them): the share of channel values and of pixels that differ, and
the largest difference in grey levels.

  python benchmarks/kubric_hue.py [--draws 200] [--size 60x80] [--blur 1.5]
"""

import argparse

import cv2
import numpy as np

from ufm_jax.data import augment
from ufm_jax.testing import color_reference


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--draws", type=int, default=200)
  p.add_argument("--size", default="60x80", help="HxW of the images")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--blur", type=float, default=1.5,
                 help="Gaussian sigma of the random images (0: unblurred, saturated colours)")
  args = p.parse_args()
  h, w = (int(v) for v in args.size.split("x"))
  rng = np.random.default_rng(args.seed)
  cfg = augment.AugmentConfig()
  n = nd = pd = mx = 0
  shares = []   # per draw: share of the draw's pixels that differ
  for _ in range(args.draws):
    img = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
    if args.blur > 0:
      img = cv2.GaussianBlur(img, (0, 0), args.blur)
    params = augment.draw_color(rng, cfg)   # every draw's order holds the hue (a permutation)
    d = np.abs(augment.color_jitter_float(img, params).astype(int)
               - color_reference.torchvision_tensor_jitter(img, params))
    n += d.size
    nd += int((d > 0).sum())
    pd += int((d > 0).any(-1).sum())
    mx = max(mx, int(d.max()))
    shares.append(float((d > 0).any(-1).mean()))
  px = n // 3
  print(f"{args.draws} draws of {h}x{w}, blur {args.blur:g}: {100 * nd / n:.3f}% of channel "
        f"values and "
        f"{100 * pd / px:.3f}% of pixels differ (per draw: median {100 * np.median(shares):.3f}%, "
        f"max {100 * max(shares):.3f}%), by at most {mx} grey level(s)")


if __name__ == "__main__":
  main()
