"""ufm_jax.match / matches_from_dense: on an exact synthetic two-view scene (ground-truth flow and
covisibility in place of a prediction) the matches obey the epipolar geometry and give the pose."""

import numpy as np
import pytest

from ufm_jax.evaluators import metrics
from ufm_jax.tools import cli, matching
from ufm_jax.data import io, synthetic


@pytest.fixture(scope="module")
def scene():
  cfg = synthetic.SyntheticConfig(size=(96, 128), pair_type="wide", moving_object_prob=0.0,
                                  min_view_angle_deg=15, max_view_angle_deg=30)
  fwd, bwd = synthetic.generate_pair(3, cfg)
  return fwd, bwd


def _skew(t):
  return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def test_matches_satisfy_epipolar_constraint_and_give_pose(scene):
  fwd, _ = scene
  meta = fwd["meta"]
  covis = fwd["covisibility"].astype(np.float32)
  m = matching.matches_from_dense(fwd["flow"], covis, num=1000, target_hw=fwd["image1"].shape[:2])
  k0, k1 = m["keypoints0"].astype(np.float64), m["keypoints1"].astype(np.float64)
  assert len(k0) == 1000 and (m["confidence"] >= 0.5).all()
  assert covis[k0[:, 1].astype(int), k0[:, 0].astype(int)].all()  # integer source pixel centres
  R, t = metrics.relative_pose(meta["cam2world0"], meta["cam2world1"])
  F = np.linalg.inv(meta["K1"]).T @ _skew(t) @ R @ np.linalg.inv(meta["K0"])
  lines = (F @ np.c_[k0, np.ones(len(k0))].T).T          # epipolar lines in image 1
  dist = np.abs((lines * np.c_[k1, np.ones(len(k1))]).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
  assert np.median(dist) < 0.05 and np.percentile(dist, 99) < 0.5, (np.median(dist), dist.max())
  est = metrics.estimate_pose(k0, k1, meta["K0"], meta["K1"])
  assert est is not None and metrics.pose_error(est[0], est[1], R, t) < 0.5


def test_min_covisibility_and_bidirectional_filter(scene):
  fwd, bwd = scene
  h, w = fwd["flow"].shape[:2]
  covis = np.where(np.arange(w)[None] < w // 2, 0.3, 1.0) * fwd["covisibility"]
  m = matching.matches_from_dense(fwd["flow"], covis, num=300)
  assert (m["keypoints0"][:, 0] >= w // 2).all() and (m["confidence"] == 1.0).all()
  bad_back = bwd["flow"].copy()
  bad_back[:, : bad_back.shape[1] // 2] += 5.0  # inconsistent where the target's left half is hit
  m = matching.matches_from_dense(fwd["flow"], fwd["covisibility"].astype(np.float32), num=300,
                                  backward_flow=bad_back)
  assert len(m["keypoints1"]) and (m["keypoints1"][:, 0] >= bad_back.shape[1] // 2 - 1).all()


class _GroundTruth:
  """Stand-in model whose forward returns the scene's ground truth at the inference resolution."""

  def __init__(self, sample):
    self.inference_resolution = [sample["flow"].shape[:2]]
    self.flow, self.covis = sample["flow"], sample["covisibility"].astype(np.float32)

  def apply(self, variables, source, target):
    zero = 0.0 * source.sum()
    return {"flow": self.flow[None] + zero, "covisibility": self.covis[None] + zero}


def test_match_cli_writes_npz_and_drawing(scene, tmp_path, monkeypatch):
  fwd, _ = scene
  src, tgt = tmp_path / "a.png", tmp_path / "b.png"
  io.write_image(src, fwd["image0"])
  io.write_image(tgt, fwd["image1"])
  monkeypatch.setattr(cli, "load_model", lambda *a, **k: (_GroundTruth(fwd), {}))
  assert cli.main(["match", str(src), str(tgt), "--checkpoint", str(tmp_path), "--out",
                   str(tmp_path / "m.npz"), "--draw", str(tmp_path / "m.png"), "--num", "200"]) == 0
  d = np.load(tmp_path / "m.npz")
  assert d["keypoints0"].shape == (200, 2) and d["confidence"].shape == (200,)
  flow = fwd["flow"][d["keypoints0"][:, 1].astype(int), d["keypoints0"][:, 0].astype(int)]
  np.testing.assert_allclose(d["keypoints1"], d["keypoints0"] + flow, atol=1e-3)
  assert io.read_image(tmp_path / "m.png").shape == (96, 256, 3)


def test_fewer_matches_than_asked_says_why():
  """A 10x10 block of covisible pixels whose flow stays in the target: 100 eligible pixels, so
  500 asked give 100 matches and the message names both counts."""
  flow = np.zeros((32, 32, 2), np.float32)
  covis = np.zeros((32, 32), np.float32)
  covis[4:14, 4:14] = 0.9
  flow[20:, :, 0] = 100.0     # covisible in the input but never: these land outside the target
  covis[20:30, 0:10] = 0.9
  m = matching.matches_from_dense(flow, covis, num=500, min_covisibility=0.5)
  assert len(m["keypoints0"]) == 100 and int(m["eligible"]) == 100
  why = matching.shortfall(m, 500, 0.5)
  assert why.startswith("100 of the 500 asked: only 100 source pixels") and "0.5" in why
  assert matching.shortfall(matching.matches_from_dense(flow, covis, num=50), 50, 0.0) == ""
