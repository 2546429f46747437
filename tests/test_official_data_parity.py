"""Parity of our readers of the official processed layouts with the official dataset classes:
every sample that processed/samples.json of UFM_TRAINING_FIXTURES lists is read from the
fixture's tree by our reader, put through the official no-augmentation transform
(`augment.official_no_aug`, augmentation off, at the fixture's resolution) and compared with what
the official class and its batch post-processing returned (`<dataset>_samples.npz`): images
within one grey level (the official antialiased resize truncates), flow within 1e-3 px, masks
equal, static cameras and depth as the official crop leaves them."""

import json

import numpy as np
import pytest

from ufm_jax import data, testing
from ufm_jax.data import augment

pytestmark = pytest.mark.official_data

_MEAN = np.array([0.485, 0.456, 0.406], np.float32)   # data_norm_type 'dinov2' (ImageNet)
_STD = np.array([0.229, 0.224, 0.225], np.float32)


def _tree(folder, name, ctor, key="ROOT"):
  return str(folder / name / ctor[key].replace("<tree>/", ""))


def _by_field(src, want, field):
  hits = [i for i, p in enumerate(field(src)) if p == want]
  assert len(hits) == 1, f"{want} matches pairs {hits} of {type(src).__name__}"
  return hits[0]


def _blendedmvs(folder, name, spec, s):
  c = spec["constructor"]
  src = data.get_source("blendedmvs_official", _tree(folder, name, c), split=c["split"],
                        pair_metadata_path=_tree(folder, name, c, "pair_metadata_path"))
  seqh, seql, a, b = s["pair"][:4]
  return "static", src, _by_field(src, (f"{seqh:08x}{seql:016x}", f"{a:08d}", f"{b:08d}"),
                                  lambda x: x.pairs)


def _megadepth(folder, name, spec, s):
  c = spec["constructor"]
  return "static", data.get_source(
      "megadepth_official", _tree(folder, name, c), split=c["split"],
      pair_metadata_path=_tree(folder, name, c, "pair_metadata_path")), s["dataset_index"]


def _by_index(reader, kind, **fixed):
  def open_(folder, name, spec, s):
    c = spec["constructor"]
    return kind, data.get_source(reader, _tree(folder, name, c), split=c["split"], **fixed), \
        s["dataset_index"]
  return open_


def _by_npz_file(reader):
  def open_(folder, name, spec, s):
    c = spec["constructor"]
    src = data.get_source(reader, _tree(folder, name, c), split=c["split"])
    want = str(folder / name / s["npz_file"])
    return "flow", src, _by_field(src, want, lambda x: x.files)
  return open_


def _sceneflow(reader):
  def open_(folder, name, spec, s):
    c = spec["constructor"]
    cameras = ("left", "right") if c.get("aug_left_right") else ("left",)
    passes = (c.get("dstype", "clean"),) + (
        (("final" if c.get("dstype", "clean") == "clean" else "clean"),)
        if c.get("aug_clean_final") else ())
    src = data.get_source(reader, _tree(folder, name, c), split=c["split"], cameras=cameras,
                          passes=passes)
    _, cam, dpass = s["views"][0]["label"].rsplit("_", 2)   # "<division>_<seq>_<cam>_<pass>"
    variant = cameras.index(cam) * len(passes) + passes.index(dpass)
    return "flow", src, s["dataset_index"] * len(cameras) * len(passes) + variant
  return open_


# samples.json dataset key -> opener(folder, key, spec, sample) -> (kind, our source, index).
OPENERS = {
    "blendedmvs": _blendedmvs,
    "megadepth": _megadepth,
    "scannetpp": _by_index("scannetpp_official", "static"),
    "kubric4d": _by_index("kubric4d_official", "kubric"),
    "tartanair_assembled": _by_index("tartanair_assembled", "flow"),
    "flyingthings3d": _sceneflow("flyingthings_official"),
    "monkaa": _sceneflow("monkaa_official"),
    "spring": _by_npz_file("spring_official"),
    "hd1k": _by_npz_file("hd1k_official"),
}


def _fixtures():
  folder = testing.training_fixtures("processed")
  with open(folder / "samples.json") as f:
    return folder, json.load(f)


def _cases():
  try:
    _, spec = _fixtures()
  except BaseException:  # pylint: disable=broad-except  # skip/fail is raised inside the test
    return [("<fixtures>", "")]
  return [(d, k) for d, v in spec.items() if isinstance(v, dict) and "samples" in v
          for k in v["samples"]]


@pytest.mark.parametrize("dataset,sample", _cases())
def test_reader_plus_official_no_aug_equals_official_dataset(dataset, sample):
  folder, spec = _fixtures()
  assert dataset in OPENERS, f"samples.json lists {dataset!r}, which no reader here is mapped to"
  s = spec[dataset]["samples"][sample]
  kind, src, index = OPENERS[dataset](folder, dataset, spec[dataset], s)
  W, H = spec["resolution_WH"]
  fwd, bwd = src.both(index) if src.has_backward else (src[index], None)
  rows = augment.official_no_aug(fwd, (H, W), kind, backward=bwd)
  z = np.load(folder / f"{dataset}_samples.npz")
  for v, row in enumerate(rows):
    batch = lambda k: z[f"{sample}_batch_v{v}_{k}"][0]
    image = np.moveaxis(z[f"{sample}_v{v}_img"], 0, -1) * (255 * _STD) + 255 * _MEAN
    err = np.abs(image - row["image0"])
    assert err.max() < 1.01 and (err > 0.5).mean() < 0.05, (v, err.max(), (err > 0.5).mean())
    flow = np.moveaxis(batch("flow"), 0, -1)
    np.testing.assert_array_equal(np.isnan(row["flow"]), np.isnan(flow))
    np.testing.assert_allclose(np.nan_to_num(row["flow"]), np.nan_to_num(flow), atol=1e-3, rtol=0)
    np.testing.assert_array_equal(row["covisibility"], batch("non_occluded_mask"))
    np.testing.assert_array_equal(row["covis_valid"], batch("occlusion_supervision_mask"))
    np.testing.assert_array_equal(row.get("fov_mask", row["flow_valid"]), batch("fov_mask"))
    if kind == "static":
      np.testing.assert_allclose(row["meta"]["K0"], z[f"{sample}_v{v}_camera_intrinsics"],
                                 atol=1e-4, rtol=0)
      np.testing.assert_allclose(row["meta"]["cam2world0"], z[f"{sample}_v{v}_camera_pose"],
                                 atol=1e-6, rtol=0)
      np.testing.assert_array_equal(row["meta"]["depth0"], z[f"{sample}_v{v}_depthmap"])
  # A source without backward labels: the official's second view carries no supervision.
  if len(rows) == 1:
    assert not z[f"{sample}_batch_v1_non_occluded_mask"].any()
