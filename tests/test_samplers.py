"""Pair samplers and miners: Kubric-4D sampler statistics, covisibility mining (ScanNet++ rule)."""

import json

import numpy as np
import pytest

from ufm_jax import data
from ufm_jax.data.sources import kubric4d
from ufm_jax.data.sources.exr import write_exr
from ufm_jax import testing
from ufm_jax.testing import wide_trees as trees


def test_kubric_camera_weight_closed_form():
  a = np.array([0.0, 0.5, np.pi / 3 - 1e-9, np.pi / 3, 1.3, np.pi / 2 - 1e-9, np.pi / 2, 3.0])
  expect = [1.0, 1.5, 1 + np.pi / 3, 1 + np.pi / 3, 1 + np.pi / 3, 1 + np.pi / 3, 0.0, 0.0]
  np.testing.assert_allclose(kubric4d.camera_pair_weight(a), expect, atol=1e-8)


def test_kubric_frame_difference_linear_twice():
  p = kubric4d.frame_difference_probs(40)
  assert len(p) == 41 and abs(p.sum() - 1) < 1e-12
  assert abs(p[40] / p[0] - 2) < 1e-12
  np.testing.assert_allclose(np.diff(p), np.full(40, p[0] / 40))


def _ring_cameras(angles_deg):
  """Cameras on a circle looking at the origin; their relative rotation = angle difference."""
  out = []
  for a in np.deg2rad(angles_deg):
    eye = (5 * np.sin(a), 0.0, -5 * np.cos(a))
    out.append(trees.look_at(eye, (0, 0, 0)))
  return np.stack(out)


def test_kubric_sampler_statistics():
  angles = [0, 20, 50, 75, 100, 170]
  c2w = _ring_cameras(angles)
  rng = np.random.default_rng(0)
  pairs = kubric4d.sample_scene_pairs(c2w, 60, 40000, rng)
  counts = np.zeros((6, 6))
  diffs = []
  for v0, t0, v1, t1 in pairs:
    counts[v0, v1] += 1
    assert 0 <= t0 < 60 and 0 <= t1 < 60
    diffs.append(abs(t1 - t0))
  alpha = np.deg2rad(np.abs(np.subtract.outer(angles, angles)))
  w = np.where(alpha < np.pi / 3, 1 + alpha, np.where(alpha < np.pi / 2, 1 + np.pi / 3, 0))
  np.fill_diagonal(w, 0)
  expect = w / w.sum() * len(pairs)
  assert counts[w == 0].sum() == 0  # no pair at >= 90 degrees, no camera paired with itself
  np.testing.assert_allclose(counts[w > 0], expect[w > 0], rtol=0.12)
  hist = np.bincount(diffs, minlength=41)
  assert hist[41:].sum() == 0 if len(hist) > 41 else True
  lo, hi = hist[:5].mean(), hist[36:41].mean()
  assert 1.6 < hi / lo < 2.4  # rises linearly to twice as likely


def test_kubric_sampler_tool_end_to_end(tmp_path):
  scene = trees.KubricScene(num_frames=6)
  trees.write_kubric4d(str(tmp_path), scene, name="scn00007")
  tool = testing.load_script("data/kubric4d/sample_pairs.py")
  out = tool.main(["--root", str(tmp_path), "--split", "train", "--pairs_per_scene", "20",
                   "--seed", "1", "--no_progress"])
  lines = [l.split() for l in open(out) if not l.startswith("#")]
  assert len(lines) == 20 and all(l[0] == "scn00007" for l in lines)
  src = data.get_source("kubric4d", str(tmp_path))
  assert len(src) == 20
  s = src[3]
  assert s["flow"].shape == scene.hw + (2,)
  again = tool.main(["--root", str(tmp_path), "--split", "train", "--pairs_per_scene", "20",
                     "--seed", "1", "--no_progress", "--out", str(tmp_path / "again.txt")])
  assert open(again).read().split("\n", 3)[-1] == open(out).read().split("\n", 3)[-1]


def test_mine_pairs_scannetpp_rule(tmp_path):
  """Two views of the plane are kept with the closed-form covisible fraction; a view looking
  away (no valid depth towards the plane) is paired with nothing."""
  scene = trees.PlaneScene(hw0=(36, 48), inv0=(), inv1=())
  name, f0, f1 = trees.write_scannetpp(str(tmp_path), scene)
  meta_path = tmp_path / name / "scene_meta.json"
  meta = json.loads(meta_path.read_text())
  away = trees.look_at((0, 0, 0), (0.0, 0.0, -5.0), up=(0, -1, 0))
  extra = dict(meta["frames"][0], frame_name="DSC00002", file_path="images/DSC00000.jpg",
               rendered_depth="rendered_depth/DSC00002.exr", transform_matrix=away.tolist())
  write_exr(str(tmp_path / name / "rendered_depth" / "DSC00002.exr"), np.zeros((36, 48)))
  meta["frames"].append(extra)
  meta_path.write_text(json.dumps(meta))
  tool = testing.load_script("data/mine_pairs.py")
  out = tool.main(["--dataset", "scannetpp", "--root", str(tmp_path), "--max_side", "64"])
  lines = [l.split() for l in open(out) if not l.startswith("#")]
  assert [l[:3] for l in lines] == [[name, f0, f1]]
  fwd = scene.expected()["inside"].mean()
  rev = trees.PlaneScene(hw0=(36, 48), K0=scene.K[1], K1=scene.K[0], c2w0=scene.c2w[1],
                         c2w1=scene.c2w[0], inv0=(), inv1=()).expected()["inside"].mean()
  assert abs(float(lines[0][3]) - min(fwd, rev)) < 0.01
  src = data.get_source("scannetpp", str(tmp_path))
  trees.check_plane_sample(src[0], scene)
  with pytest.raises(SystemExit):
    tool.main(["--dataset", "scannetpp", "--root", str(tmp_path), "--min_covis", "x"])
