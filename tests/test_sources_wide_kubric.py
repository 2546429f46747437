"""Kubric-4D: rigid posed objects across viewpoint and time on a tiny tree in GCD's layout."""

import numpy as np
import pytest

from ufm_jax import data
from ufm_jax.testing import wide_trees as trees


@pytest.fixture(scope="module")
def kubric_tree(tmp_path_factory):
  root = tmp_path_factory.mktemp("kubric")
  scene = trees.KubricScene()
  name = trees.write_kubric4d(str(root), scene)
  return root, scene, name


def test_kubric4d_moving_object_across_view_and_time(kubric_tree):
  root, scene, name = kubric_tree
  (root / "pairs_train.txt").write_text(f"{name} 0/1 1/4\n{name} 1/5 0/0\n")
  # The exact geometry (principal point shifted to the pixel-centre convention); the default is
  # the official code's unshifted one (test_kubric4d_official_principal_point below).
  src = data.get_source("kubric4d", str(root), principal_point_shift=True)
  for i, (v0, t0, v1, t1) in enumerate([(0, 1, 1, 4), (1, 5, 0, 0)]):
    s = src[i]
    e = scene.expected(v0, t0, v1, t1)
    assert (e["seg0"] == 1).sum() > 30, "the moving object must be visible"
    ok = ~e["ambiguous"]
    m = e["inside"] & ok
    err = np.abs(s["flow"] - e["flow"]).max(-1)
    assert err[m].max() < 0.02, f"flow error {err[m].max():.4f} px"
    assert (err[m & (e["seg0"] == 1)] < 0.02).all()
    bad = (s["covisibility"] != e["covis"]) & ok
    assert bad.sum() == 0, f"{bad.sum()} pixels with wrong covisibility"
    assert (~e["covis"] & e["inside"] & ok).sum() > 5, "the scene should contain occlusions"
    np.testing.assert_allclose(s["meta"]["K0"], scene.K[v0], atol=1e-4)
    np.testing.assert_allclose(s["meta"]["cam2world0"], scene.c2w[v0], atol=1e-5)
    assert (s["meta"]["time0"], s["meta"]["time1"]) == (t0, t1)


def test_kubric4d_backward_is_the_reversed_dynamic_pair(kubric_tree):
  root, scene, name = kubric_tree
  (root / "pairs_test.txt").write_text(f"{name} 0/1 1/4\n")
  src = data.get_source("kubric4d", str(root), split="all", pairs=str(root / "pairs_test.txt"),
                        principal_point_shift=True)
  b = src.backward(0)
  e = scene.expected(1, 4, 0, 1)
  m = e["inside"] & ~e["ambiguous"]
  assert np.abs(b["flow"] - e["flow"]).max(-1)[m].max() < 0.02
  assert ((b["covisibility"] != e["covis"]) & ~e["ambiguous"]).sum() == 0
  assert (b["meta"]["time0"], b["meta"]["time1"]) == (4, 1)


def test_kubric4d_official_principal_point(kubric_tree):
  """By default K keeps Kubric's corner-origin principal point, as the official training code
  (its -0.5 goes to a discarded copy, kubric4d.py:55-60): half a pixel off the exact one."""
  root, scene, name = kubric_tree
  (root / "pairs_train.txt").write_text(f"{name} 0/1 1/4\n")
  official = data.get_source("kubric4d", str(root)).lazy_pair(0)
  exact = data.get_source("kubric4d", str(root), principal_point_shift=True).lazy_pair(0)
  np.testing.assert_allclose(official.v0.K[:2, 2] - exact.v0.K[:2, 2], [0.5, 0.5], atol=1e-9)
  np.testing.assert_allclose(official.v0.K[[0, 1], [0, 1]], exact.v0.K[[0, 1], [0, 1]])
  # The depth is converted from the range with the same K.
  assert not np.array_equal(official.v0.depth, exact.v0.depth)


def test_kubric4d_palette_segmentation_roundtrip(tmp_path):
  from ufm_jax.data.sources.kubric4d import read_index_png, write_index_png
  ids = np.arange(12, dtype=np.uint8).reshape(3, 4) % 5
  pal = np.array([[0, 0, 0], [1, 2, 3], [250, 1, 1], [9, 9, 9], [0, 255, 0]], np.uint8)
  write_index_png(str(tmp_path / "s.png"), ids, pal)
  np.testing.assert_array_equal(read_index_png(str(tmp_path / "s.png")), ids)


def test_kubric4d_without_pairs_names_sampler(kubric_tree):
  root, _, _ = kubric_tree
  with pytest.raises(FileNotFoundError, match="pairs_val.txt.*sample_pairs.py"):
    len(data.get_source("kubric4d", str(root), split="val"))


def test_kubric4d_malformed_metadata_names_file(tmp_path):
  name = trees.write_kubric4d(str(tmp_path), trees.KubricScene(num_frames=2))
  (tmp_path / name / f"{name}_p0_v1.json").write_text('{"scene": {}}')
  (tmp_path / "pairs_train.txt").write_text(f"{name} 0/0 1/1\n")
  with pytest.raises(ValueError, match=f"{name}_p0_v1.json.*malformed Kubric metadata"):
    data.get_source("kubric4d", str(tmp_path))[0]
