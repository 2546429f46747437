"""Static wide-baseline readers on tiny trees in each dataset's real layout (see
test_sources_wide_trees.py for the plane scene whose flow is a closed-form homography)."""

import os

import numpy as np
import pytest

from ufm_jax import data
import test_sources_wide_trees as trees


def test_blendedmvs_plane(tmp_path):
  scene = trees.PlaneScene()
  trees.write_blendedmvs(str(tmp_path), scene)
  src = data.get_source("blendedmvs", str(tmp_path), split="train")
  assert len(src) == 2  # both directions from cams/pair.txt
  trees.check_plane_sample(src[0], scene)
  assert data.get_source("blendedmvs", str(tmp_path), split="val").scenes() == []
