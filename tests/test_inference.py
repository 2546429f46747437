"""`ufm_jax.runtime.inference` against the official `predict_correspondences_batched` fixtures.

The resize, the region bookkeeping and the unmap are checked on their own against the official
arrays (no model needed); `test_predict_vs_reference` runs the whole thing with `load_official`.
"""

import numpy as np
import pytest

from ufm_jax.data import resize
from ufm_jax.runtime import inference

PAIRS = ("hl0", "hl1", "hl2")
INF_HW = (168, 224)  # config.json inference_resolution (W, H) = [224, 168]


@pytest.fixture(scope="module")
def io(reference_dir):
  return dict(np.load(reference_dir / "base" / "io.npz"))


def _hwc(x):  # [1, C, H, W] -> [H, W, C]
  return np.asarray(x)[0].transpose(1, 2, 0)


@pytest.mark.parametrize("pair", PAIRS)
@pytest.mark.parametrize("view,scaled", [("src", "src_scaled"), ("tgt", "tgt_scaled")])
def test_normalised_antialiased_resize(io, pair, view, scaled):
  got = resize.resize_bilinear_aa(inference.normalize(io[f"{pair}_{view}_uint8"]), INF_HW)
  np.testing.assert_allclose(got, _hwc(io[f"{pair}_{scaled}"]), rtol=0, atol=5e-5)


def test_normalise_matches_fixture(io):
  got = inference.normalize(io["img1_uint8"])
  np.testing.assert_allclose(got, io["img1_norm"].transpose(0, 2, 3, 1), rtol=0, atol=1e-6)
  back = inference.denormalize(got)
  np.testing.assert_allclose(back, io["img1_uint8"].astype(np.float32), rtol=0, atol=1e-4)


@pytest.mark.parametrize("pair", PAIRS)
def test_region_bookkeeping(io, pair):
  for view, key in (("src", "img0"), ("tgt", "img1")):
    hw = io[f"{pair}_{view}_uint8"].shape[:2]
    np.testing.assert_array_equal(inference.representation_region(hw, INF_HW),
                                  io[f"{pair}_{key}_region_representation"])


def test_region_truncation_hand_case():
  # float32(168 / 131) * 131 = 167.99998... -> 167; exact ratios stay exact.
  assert list(inference.representation_region((131, 270), (168, 224))) == [0, 167, 0, 223]
  assert list(inference.representation_region((200, 300), (168, 224))) == [0, 168, 0, 224]


@pytest.mark.parametrize("pair", PAIRS)
def test_unmap_vs_reference(io, pair):
  src_hw = io[f"{pair}_src_uint8"].shape[:2]
  tgt_hw = io[f"{pair}_tgt_uint8"].shape[:2]
  region = io[f"{pair}_img0_region_representation"]
  flow = inference.unmap_flow(_hwc(io[f"{pair}_fwd_flow"]), region, src_hw, tgt_hw)
  np.testing.assert_allclose(flow, _hwc(io[f"{pair}_flow"]), rtol=0, atol=1e-3)
  covis = inference.unmap_channels(io[f"{pair}_fwd_covisibility_mask"][0, 0], region, src_hw)
  np.testing.assert_allclose(covis, io[f"{pair}_covisibility"][0], rtol=0, atol=5e-5)


def test_resize_hand_cases():
  # 4 -> 2 with antialias: output pixel 0 covers input [0, 2] (centre 1.0), the triangle has
  # half-width 2, so input centres 0.5, 1.5, 2.5 get 0.75, 0.75, 0.25 (renormalised); output 1
  # mirrors it on 1.5, 2.5, 3.5.
  x = np.arange(4, dtype=np.float32).reshape(1, 4, 1)
  got = resize.resize_bilinear_aa(x, (1, 2))[0, :, 0]
  expect = [(0.75 * 0 + 0.75 * 1 + 0.25 * 2) / 1.75, (0.25 * 1 + 0.75 * 2 + 0.75 * 3) / 1.75]
  np.testing.assert_allclose(got, expect, atol=1e-6)
  # Upsampling 2 -> 4 is plain bilinear with edge clamping: 0, 0.25, 0.75, 1.
  got = resize.resize_bilinear_aa(np.array([[[0.0], [1.0]]], np.float32), (1, 4))[0, :, 0]
  np.testing.assert_allclose(got, [0, 0.25, 0.75, 1], atol=1e-7)
  # Legacy nearest: 3 -> 5 picks floor(i * 0.6).
  np.testing.assert_array_equal(resize.resize_nearest(np.arange(3)[:, None], (5, 1))[:, 0],
                                [0, 0, 1, 1, 2])


def test_select_resolution_closest_aspect():
  res = [(420, 560), (560, 420), (280, 560)]
  assert inference.select_resolution(res, (300, 400), (300, 400)) == (420, 560)
  assert inference.select_resolution(res, (400, 300), (400, 300)) == (560, 420)
  assert inference.select_resolution(res, (100, 200), (110, 200)) == (280, 560)


class _Replay:
  """Stand-in model: returns the official raw forward outputs for a given pair (jittable)."""

  def __init__(self, flow, covis, inference_resolution):
    self.flow, self.covis = flow, covis
    self.inference_resolution = inference_resolution

  def apply(self, variables, source, target):
    del variables
    assert source.shape[1:3] == self.flow.shape[1:3]
    zero = 0.0 * (source.mean() + target.mean())
    return {"flow": self.flow + zero, "covisibility": self.covis + zero}


@pytest.mark.parametrize("pair", PAIRS)
def test_predict_plumbing_with_replayed_forward(io, pair):
  model = _Replay(_hwc(io[f"{pair}_fwd_flow"])[None], io[f"{pair}_fwd_covisibility_mask"][:, 0],
                  [INF_HW])
  out = inference.predict(model, {}, io[f"{pair}_src_uint8"], io[f"{pair}_tgt_uint8"])
  assert out["flow"].shape == io[f"{pair}_src_uint8"].shape[:2] + (2,)
  np.testing.assert_allclose(out["flow"], _hwc(io[f"{pair}_flow"]), atol=1e-3)
  np.testing.assert_allclose(out["covisibility"], io[f"{pair}_covisibility"][0], atol=5e-5)
  # lists of pairs give one dict per pair
  outs = inference.predict(model, {}, [io[f"{pair}_src_uint8"]], [io[f"{pair}_tgt_uint8"]])
  np.testing.assert_array_equal(outs[0]["flow"], out["flow"])


def test_predict_input_errors():
  model = _Replay(np.zeros((1, 14, 14, 2), np.float32), np.zeros((1, 14, 14), np.float32), [(14, 14)])
  img = np.zeros((20, 20, 3), np.uint8)
  with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
    inference.predict(model, {}, img[..., :2], img)
  with pytest.raises(ValueError, match="dtype"):
    inference.predict(model, {}, img.astype(np.int32), img)
  with pytest.raises(ValueError, match="2 source images but 1"):
    inference.predict(model, {}, [img, img], [img])


def test_too_small_an_image_is_refused_by_every_tool(tmp_path, monkeypatch, capsys):
  """One rule (min_image_side: one image pixel per encoder patch at the inference resolution,
  30 px for 420x560) in predict, so the CLI refuses what the demo refuses."""
  from ufm_jax.tools import cli
  from ufm_jax.data import io as image_io
  model = _Replay(np.zeros((1, 420, 560, 2), np.float32), np.zeros((1, 420, 560), np.float32),
                  [(420, 560)])
  assert inference.min_image_side(model) == 30
  ok = np.zeros((30, 40, 3), np.uint8)
  with pytest.raises(ValueError, match=r"target\[0\] is 29x64 px \(HxW\), under this model's "
                                       r"minimum of 30 px"):
    inference.predict(model, {}, ok, np.zeros((29, 64, 3), np.uint8))
  image_io.write_image(tmp_path / "a.png", ok)
  image_io.write_image(tmp_path / "dot.png", np.zeros((1, 1, 3), np.uint8))
  monkeypatch.setattr(cli, "load_model", lambda *a, **k: (model, {}))
  rc = cli.main(["infer", str(tmp_path / "a.png"), str(tmp_path / "dot.png"), "--checkpoint", "x",
                 "--out", str(tmp_path / "out")])
  assert rc == 2 and "1x1 px (HxW), under this model's minimum of 30 px" in capsys.readouterr().err
  (tmp_path / "text.png").write_text("not an image")
  with pytest.raises(ValueError, match="not a readable image .expected PNG, JPEG, WebP"):
    image_io.read_image(tmp_path / "text.png")


def _load_official(reference_dir):
  from ufm_jax.official import snapshot
  return snapshot.load_official(reference_dir / "base")


@pytest.mark.slow
def test_predict_vs_reference(io, reference_dir):
  model, variables = _load_official(reference_dir)
  outs = inference.predict(model, variables, [io[f"{p}_src_uint8"] for p in PAIRS],
                           [io[f"{p}_tgt_uint8"] for p in PAIRS])
  for p, out in zip(PAIRS, outs):
    np.testing.assert_allclose(out["flow"], _hwc(io[f"{p}_flow"]), rtol=0, atol=1e-3, err_msg=p)
    np.testing.assert_allclose(out["covisibility"], io[f"{p}_covisibility"][0], rtol=0, atol=5e-5,
                               err_msg=p)


@pytest.mark.slow
def test_predict_refine_vs_reference(reference_dir):
  """The same high-level path on the refine fixture. Its flow tolerance is the refiner's own
  forward tolerance (5e-3, see test_refine_parity.py): the resize and unmap add < 1e-4."""
  from ufm_jax.official import snapshot
  io = dict(np.load(reference_dir / "refine" / "io.npz"))
  model, variables = snapshot.load_official(reference_dir / "refine")
  outs = inference.predict(model, variables, [io[f"{p}_src_uint8"] for p in PAIRS],
                           [io[f"{p}_tgt_uint8"] for p in PAIRS])
  for p, out in zip(PAIRS, outs):
    np.testing.assert_allclose(out["flow"], _hwc(io[f"{p}_flow"]), rtol=0, atol=5e-3, err_msg=p)
    np.testing.assert_allclose(out["covisibility"], io[f"{p}_covisibility"][0], rtol=0, atol=5e-5,
                               err_msg=p)
