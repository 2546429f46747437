"""benchmarks/synthetic_learning.py: the translated-texture pairs carry exact labels."""

import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import synthetic_learning  # noqa: E402


def test_shift_pair_labels_are_exact():
  for seed in range(5):
    fwd, bwd = synthetic_learning.shift_pair(seed, (28, 42), max_shift=6)
    for s in (fwd, bwd):
      d = s["flow"][0, 0].astype(int)
      assert (s["flow"] == d).all() and np.abs(d).max() <= 6
      h, w = s["covisibility"].shape
      v, u = np.nonzero(s["covisibility"])
      # Every covisible source pixel reappears at p + d in the target, bit for bit ...
      np.testing.assert_array_equal(s["image1"][v + d[1], u + d[0]], s["image0"][v, u])
      # ... and exactly the pixels whose p + d leaves the image are not covisible.
      assert s["covisibility"].sum() == (h - abs(d[1])) * (w - abs(d[0]))
    np.testing.assert_array_equal(bwd["flow"], -fwd["flow"])
    np.testing.assert_array_equal(bwd["image0"], fwd["image1"])
