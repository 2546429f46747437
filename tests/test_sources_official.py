"""Readers of the official processed layouts on tiny trees written in the exact official formats
(ufm_jax/testing/official_trees.py): labels of the static datasets against the plane scene's
closed form (so each dataset's camera conventions are checked), the flow datasets' stored arrays,
splits, pair lists and the official quantities' variants."""

import os

import numpy as np
import pytest

from ufm_jax import data
from ufm_jax.data import mixture
from ufm_jax.data.sources import _official
from ufm_jax.testing import official_trees as ot
from ufm_jax.testing import wide_trees as wide


def _official_meta(sample, refine=False):
  m = sample["meta"]
  assert m["layout"] == "official" and m["suitable_for_refinement"] is refine
  np.testing.assert_array_equal(m["covisible_rendering_parameters"],
                                np.array([0.1, 0.1, 0.005], np.float32))


# ------------------------------------------------------------------------------ static datasets

def test_blendedmvs_processed_split_exclusions_and_plane(tmp_path):
  scene = ot.write_blendedmvs(str(tmp_path))
  src = data.get_source("blendedmvs_official", str(tmp_path / "blendedmvs_processed"))
  # The val-split row and the officially excluded sequence's row are left out.
  assert src.pairs == [(ot.BLENDED_SEQ, "00000000", "00000001"),
                       (ot.BLENDED_SEQ, "00000001", "00000000")]
  s = src[0]
  wide.check_plane_sample(s, scene)
  _official_meta(s, refine=True)
  assert s["meta"]["K0"].dtype == np.float32
  val = data.get_source("blendedmvs_official", str(tmp_path / "blendedmvs_processed"), split="val")
  assert val.pairs == [(ot.BLENDED_VAL_SEQ, "00000000", "00000001")]


def test_blendedmvs_processed_pairs_next_to_root_or_given(tmp_path):
  ot.write_blendedmvs(str(tmp_path))
  root = tmp_path / "blendedmvs_processed"
  moved = tmp_path / "elsewhere.npy"
  os.replace(tmp_path / "dust3r_data_pairs" / "blendedmvs_pairs.npy", moved)
  with pytest.raises(FileNotFoundError, match="dust3r_data_pairs/blendedmvs_pairs.npy"):
    data.get_source("blendedmvs_official", str(root))
  src = data.get_source("blendedmvs_official", str(root), pair_metadata_path=str(moved))
  assert len(src) == 2


def test_megadepth_processed_plane_and_val_scenes(tmp_path):
  scene = ot.write_megadepth(str(tmp_path))
  root = str(tmp_path / "megadepth_processed")
  src = data.get_source("megadepth_official", root, select_scenes=True)
  assert src.pairs == [("0001/0", "img0", "img1"), ("0001/0", "img1", "img0")]
  wide.check_plane_sample(src[0], scene)
  _official_meta(src[0])
  val = data.get_source("megadepth_official", root, split="val", select_scenes=True)
  assert val.pairs == [("0015/0", "img0", "img1")]
  # As the official class: every pair of the file, whatever the split (megadepth.py:19-35).
  for split in ("train", "val"):
    assert data.get_source("megadepth_official", root, split=split).pairs == [
        ("0001/0", "img0", "img1"), ("0015/0", "img0", "img1"), ("0001/0", "img1", "img0")]


def test_megadepth_readers_make_the_same_split_choice_by_default(tmp_path):
  """Both layouts: by default the official choice (every scene in every split, the val scenes
  0015 and 0022 train too); select_scenes=True the intended split, in both alike."""
  ot.write_megadepth(str(tmp_path / "official"))
  processed = str(tmp_path / "official" / "megadepth_processed")
  raw = tmp_path / "raw"
  scene = wide.megadepth_scene()
  for name in ("0001", "0015"):
    wide.write_megadepth(str(raw), scene, name=name)
  np.savez(raw / "megadepth_pairs.npz", scenes=np.array(["0001 0", "0015 0"]),
           images=np.array(["img0.jpg", "img1.jpg"]),
           pairs=np.array([[0, 0, 1, 0.5], [1, 0, 1, 0.5]]))

  def scenes(reader, root, **kw):
    src = data.get_source(reader, root, **kw)
    return sorted({p[0] for p in src.pairs}), src.scenes()

  for split in ("train", "val"):
    official = scenes("megadepth_official", processed, split=split)
    assert official == scenes("megadepth", str(raw), split=split)
    assert official == (["0001/0", "0015/0"], ["0001/0", "0015/0"])
  assert scenes("megadepth", str(raw), select_scenes=True) == (["0001/0"], ["0001/0"])
  assert scenes("megadepth_official", processed, select_scenes=True) == (["0001/0"], ["0001/0"])
  for reader, root in (("megadepth", str(raw)), ("megadepth_official", processed)):
    assert scenes(reader, root, split="val", select_scenes=True) == (["0015/0"], ["0015/0"])


def test_scannetpp_processed_plane_millimetre_png_and_95_percent_split(tmp_path):
  scene = ot.write_scannetpp(str(tmp_path))
  root = str(tmp_path / "scannetpp_anymap_processed" / "train")
  src = data.get_source("scannetpp_official", root)
  assert src.pairs == [("0a5c013435", "0", "1"), ("0a5c013435", "1", "0")]  # int(0.95 * 3) = 2
  # Depth is quantised to millimetres: labels within that of the closed form.
  wide.check_plane_sample(src[0], scene, tol=5e-3, depth_tol=1e-3)
  assert len(data.get_source("scannetpp_official", root, split="val")) == 1


def test_staticthings_processed_every_pass_combination(tmp_path):
  scene = ot.write_staticthings(str(tmp_path))
  root = str(tmp_path / "staticthings3d_processed")
  src = data.get_source("staticthings_official", root)
  assert len(src) == 4
  assert [p[1:] for p in src.pairs] == [("left/0006_clean", "right/0007_clean"),
                                        ("left/0006_clean", "right/0007_final"),
                                        ("left/0006_final", "right/0007_clean"),
                                        ("left/0006_final", "right/0007_final")]
  s = src[0]
  wide.check_plane_sample(s, scene)
  _official_meta(s)
  # The final pass (written 40 grey levels darker) is what variant 1 reads for its second view.
  darker = s["image1"].astype(int) - src[1]["image1"].astype(int)
  assert 30 < np.median(darker) < 50
  assert len(data.get_source("staticthings_official", root, passes=("final",))) == 1


def test_habitat_processed_official_principal_point_and_second_views(tmp_path):
  scene = ot.write_habitat(str(tmp_path))
  src = data.get_source("habitat_official",
                        str(tmp_path / "habitat_processed" / "replica_cad_baked_lighting"))
  assert src.pairs == [("apt_0", "000123_1", f"000123_{j}") for j in (2, 3, 4, 5)]
  for i in (0, 3):   # K stored with +0.5: the official subtraction gives the scene's K back
    wide.check_plane_sample(src[i], scene, tol=0.05, depth_tol=3e-3)   # float16 EXR depth
  _official_meta(src[0])


def test_kubric4d_processed_official_camera_conventions(tmp_path):
  scene = ot.write_kubric4d(str(tmp_path))
  src = data.get_source("kubric4d_official", str(tmp_path / "kubric4d"))
  assert src.pairs == [("scn00042", "0/0", "1/2"), ("scn00042", "1/3", "0/1")]
  for i, (v0, t0, v1, t1) in enumerate([(0, 0, 1, 2), (1, 3, 0, 1)]):
    fwd, bwd = src.both(i)
    for s, e in ((fwd, scene.expected(v0, t0, v1, t1)), (bwd, scene.expected(v1, t1, v0, t0))):
      assert (e["seg0"] == 1).sum() > 30, "the moving object must be visible"
      m = e["inside"] & ~e["ambiguous"]
      err = np.abs(s["flow"] - e["flow"]).max(-1)
      assert err[m].max() < 0.02, f"flow error {err[m].max():.4f} px"
      assert ((s["covisibility"] != e["covis"]) & ~e["ambiguous"]).sum() == 0
    np.testing.assert_allclose(fwd["meta"]["K0"], scene.K[v0], atol=1e-4)
    np.testing.assert_allclose(fwd["meta"]["cam2world1"], scene.c2w[v1], atol=1e-5)
  _official_meta(src[0])
  assert len(data.get_source("kubric4d_official", str(tmp_path / "kubric4d"), split="val")) == 1


# -------------------------------------------------------------------------------- flow datasets

def _check_labels(sample, labels, image0, image1, flow_valid=None):
  np.testing.assert_array_equal(sample["image0"], image0)
  np.testing.assert_array_equal(sample["image1"], image1)
  np.testing.assert_array_equal(sample["flow"], labels["flow"])
  assert sample["flow"].dtype == np.float32 and sample["flow"].shape[-1] == 2
  np.testing.assert_array_equal(sample["covisibility"], labels["non_occluded_mask"])
  np.testing.assert_array_equal(sample["covis_valid"], labels["occlusion_supervision_mask"])
  np.testing.assert_array_equal(sample["fov_mask"], labels["fov_mask"])
  want = np.isfinite(labels["flow"]).all(-1) if flow_valid is None else flow_valid
  np.testing.assert_array_equal(sample["flow_valid"], want)


@pytest.mark.parametrize("dataset,flow_index,layout", [
    ("flyingthings", False, "hwc"), ("flyingthings", True, "chw"), ("monkaa", True, "hwc")])
def test_sceneflow_processed_variants_and_both_directions(tmp_path, dataset, flow_index, layout):
  root = ot.write_sceneflow(str(tmp_path), dataset, flow_index=flow_index, flow_layout=layout)
  c = ot.FLOW_CONTENT[dataset]
  src = data.get_source(f"{dataset}_official", root)
  # The official draws per sample: the camera, and the pass (FlyingThings3D: one for both
  # frames, flyingthings3d.py:66-71; Monkaa: each frame's own, monkaa.py:61-64).
  passes = ([("clean", "clean"), ("final", "final")] if dataset == "flyingthings" else
            [(p0, p1) for p0 in ("clean", "final") for p1 in ("clean", "final")])
  assert src.has_backward and src.variants == 2 * len(passes)
  assert len(src) == 2 * src.variants   # 2 pairs x (left, right) x passes
  for index in range(len(src)):
    pair, r = divmod(index, src.variants)
    cam, (p0, p1) = ("left", "right")[r // len(passes)], passes[r % len(passes)]
    fwd, bwd = src.both(index)
    im0, im1 = c["images"][(cam, p0)], c["images"][(cam, p1)]
    _check_labels(fwd, c["labels"][(cam, 0)][pair], im0[pair], im1[pair + 1])
    _check_labels(bwd, c["labels"][(cam, 1)][pair], im1[pair + 1], im0[pair])
    assert fwd["meta"]["camera"] == cam
    assert fwd["meta"]["dstype"] == (p0 if p0 == p1 else f"{p0}/{p1}")
    assert fwd["meta"]["suitable_for_refinement"] is (dataset == "flyingthings")
  no_aug = data.get_source(f"{dataset}_official", root, cameras=("left",), passes=("clean",))
  assert len(no_aug) == 2
  _check_labels(no_aug[1], c["labels"][("left", 0)][1], c["images"][("left", "clean")][1],
                c["images"][("left", "clean")][2])


def test_spring_processed_sorted_files_nan_flow_and_held_out_sequences(tmp_path):
  root = ot.write_spring(str(tmp_path))
  src = data.get_source("spring_official", root)
  assert [os.path.relpath(f, root) for f in src.files] == [
      "train/0001/left/flow/0001_0002.npz", "train/0001/right/flow/0001_0002.npz"]
  for i, cam in enumerate(("left", "right")):
    c = ot.FLOW_CONTENT["spring"][("train", "0001", cam)]
    fwd, bwd = src.both(i)
    _check_labels(fwd, c["views"][0], *c["images"])
    _check_labels(bwd, c["views"][1], c["images"][1], c["images"][0])
    assert np.isnan(fwd["flow"]).any() and not fwd["flow_valid"].all()
  test = data.get_source("spring_official", root, split="test")
  assert [os.path.relpath(f, root) for f in test.files][0].startswith("test/0040/")


def test_hd1k_processed_invalid_flow_is_4000_and_backward_is_empty(tmp_path):
  root = ot.write_hd1k(str(tmp_path))
  src = data.get_source("hd1k_official", root)
  for i, z in enumerate(ot.FLOW_CONTENT["hd1k"]):
    fwd, bwd = src.both(i)
    flow = np.moveaxis(z["flow"], 0, -1).copy()
    flow[~z["valid"]] = 4000.0
    none = np.zeros_like(z["valid"])
    _check_labels(fwd, dict(flow=flow, non_occluded_mask=z["valid"],
                            occlusion_supervision_mask=none, fov_mask=z["valid"]),
                  z["img0"], z["img1"], flow_valid=z["valid"])
    _check_labels(bwd, dict(flow=np.full_like(flow, 4000.0), non_occluded_mask=none,
                            occlusion_supervision_mask=none, fov_mask=none),
                  z["img1"], z["img0"], flow_valid=none)


@pytest.mark.parametrize("flow_dtype", [np.float32, np.float16])
def test_tawb_shards_list_and_dict_index_maps(tmp_path, flow_dtype):
  root = ot.write_tawb(str(tmp_path), flow_dtype=flow_dtype)
  src = data.get_source("tartanair_assembled", root)
  assert len(src) == 3   # match_errors.json is not an index map
  for i, p in enumerate(ot.FLOW_CONTENT["tartanair_v2"]):
    fwd, bwd = src.both(i)
    views = [dict(v, flow=v["flow"].astype(flow_dtype).astype(np.float32)) for v in p["views"]]
    _check_labels(fwd, views[0], p["img0"], p["img1"])
    _check_labels(bwd, views[1], p["img1"], p["img0"])


def test_flyingchairs_official_folder_is_the_torchvision_layout(tmp_path):
  ot.write_flyingchairs(str(tmp_path))
  layout, folder, _ = mixture.find_layout("flyingchairs", str(tmp_path))
  assert (layout.kind, layout.source, folder) == ("official", "flyingchairs",
                                                  str(tmp_path / "FlyingChairs"))
  src = data.get_source(layout.source, folder)
  assert [int(x) for x in src.ids] == [1, 3]   # pair 2 is in the val split
  s = src[1]
  np.testing.assert_array_equal(s["image0"], ot.texture((30, 40), 61))
  np.testing.assert_allclose(s["flow"], ot.flow_field((30, 40), 60))
  assert not s["covis_valid"].any()


def test_h5_index_maps_name_their_file(tmp_path):
  (tmp_path / "a.json").write_text('{"0": ["x.h5"]}')
  with pytest.raises(ValueError, match="a.json: entry '0'"):
    _official.H5Index(str(tmp_path))
