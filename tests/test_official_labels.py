"""Static-pair labels equal the official training code's `flow_occlusion_post_processing`
(fixtures: labels/ of UFM_TRAINING_FIXTURES, made by running the official function; every case
that labels/static_pairs.json lists is checked, in both directions)."""

import json

import numpy as np
import pytest

from ufm_jax import geometry, testing

pytestmark = pytest.mark.official_training

# The official function's defaults (flow_postprocessing.py:544-546): used for kwargs a case leaves
# out when its views carry no covisible_rendering_parameters.
_DEFAULTS = {"depth_error_threshold": 0.1, "depth_error_temperature": 0.1,
             "relative_depth_error_threshold": 0.005}
MAX_MISMATCH = 1e-3   # fraction of pixels (depth discontinuities, threshold and fov-bound ties)
FLOW_ATOL = 1e-3      # px


def _cases():
  folder = testing.training_fixtures("labels")
  with open(folder / "static_pairs.json") as f:
    meta = json.load(f)
  return folder, meta["cases"], np.load(folder / "static_pairs.npz")


def _case_names():
  try:
    folder = testing.training_fixtures("labels")
  except BaseException:  # pylint: disable=broad-except  # skip/fail is raised inside the test
    return ["<fixtures>"]
  with open(folder / "static_pairs.json") as f:
    return sorted(json.load(f)["cases"])


@pytest.mark.parametrize("case", _case_names())
def test_static_labels_match_official(case):
  folder, cases, z = _cases()
  spec = cases[case]
  kwargs = {**_DEFAULTS, **spec.get("kwargs", {})}
  total, mismatched = 0, 0
  for view, other in ((0, 1), (1, 0)):
    get = lambda v, k: z[f"{case}_v{v}_{k}"]
    uv_all, uv_ours = get(view, "valid_uv"), []
    for b in range(spec["B"]):
      key = f"{case}_v{view}_covisible_rendering_parameters"
      params = (z[key][b] if key in z.files else
                (kwargs["depth_error_threshold"], kwargs["depth_error_temperature"],
                 kwargs["relative_depth_error_threshold"]))
      ours = geometry.official_labels(
          get(view, "depthmap")[b], get(view, "camera_intrinsics")[b], get(view, "camera_pose")[b],
          get(other, "depthmap")[b], get(other, "camera_intrinsics")[b],
          get(other, "camera_pose")[b], params)
      want = {"covisibility": get(view, "non_occluded_mask")[b],
              "flow_valid": get(view, "fov_mask")[b],
              "covis_valid": get(view, "occlusion_supervision_mask")[b],
              "valid": get(view, "depth_validity")[b],
              "valid_other": get(view, "other_view_depth_validity")[b]}
      flow = np.moveaxis(get(view, "flow")[b], 0, -1)
      bad = np.zeros(flow.shape[:2], bool)
      for k, w in want.items():
        bad |= ours[k] != w
      good = ~bad
      np.testing.assert_allclose(ours["flow"][good], flow[good], atol=FLOW_ATOL, rtol=0,
                                 err_msg=f"{case} view {view} sample {b}: flow")
      bad |= np.abs(ours["flow"] - flow).max(-1) > FLOW_ATOL
      # valid_uv: the projections of fov_pre's pixels (row-major over b, y, x), those without
      # depth (projecting their camera centre) included.
      grid = np.stack(np.meshgrid(np.arange(flow.shape[1]), np.arange(flow.shape[0])), -1)
      uv_ours.append((grid + ours["flow"])[ours["fov_pre"]])
      total += bad.size
      mismatched += int(bad.sum())
    uv_ours = np.concatenate(uv_ours)
    if len(uv_ours) == len(uv_all):
      np.testing.assert_allclose(uv_ours, uv_all, atol=FLOW_ATOL, rtol=0,
                                 err_msg=f"{case} view {view}: valid_uv")
    else:   # a fov-bound tie shifts the row-major list: only counted
      mismatched += abs(len(uv_ours) - len(uv_all))
  assert mismatched <= MAX_MISMATCH * total, (case, mismatched, total)


def test_crop_labels_cut_matches_leaving_the_crop():
  """Cropping before labelling (the official order): labelling the cropped views makes a pixel
  whose match leaves the other view's crop out of fov and not covisible, although it is
  covisible in the uncropped render."""
  folder, cases, z = _cases()
  if "crop" not in cases or "crop_full" not in cases:
    pytest.skip("no crop / crop_full cases in this fixture folder")

  def labels(case):
    views = [[z[f"{case}_v{v}_{k}"][0] for k in ("depthmap", "camera_intrinsics", "camera_pose")]
             for v in (0, 1)]
    return geometry.official_labels(*views[0], *views[1],
                                    z[f"{case}_v0_covisible_rendering_parameters"][0])

  (l0, t0, r0, b0), (l1, t1, r1, b1) = z["crop_box_ltrb"]
  full = labels("crop_full")
  crop = labels("crop")
  flow = full["flow"][t0:b0, l0:r0]
  y, x = np.mgrid[t0:b0, l0:r0]
  leaves = ((x + flow[..., 0] < l1 - 0.5) | (x + flow[..., 0] >= r1 - 0.5)
            | (y + flow[..., 1] < t1 - 0.5) | (y + flow[..., 1] >= b1 - 0.5))
  assert (full["covisibility"][t0:b0, l0:r0] & leaves).sum() > 50   # the case exercises it
  assert not (crop["covisibility"] & leaves).any()
  assert not (crop["flow_valid"] & leaves).any()
