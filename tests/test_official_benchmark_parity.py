"""The official benchmark protocol against the `benchmark` branch's own pipeline: ETH3D / DTU trees
at sizes other than 560 x 420, landscape and portrait views, and TA-WB shards of 64 x 64 pairs
(tests/fixtures/benchmark_protocol, made by running the branch's dataset classes and metric code:
its README says how).

  * samples: `eth3d_official` / `dtu_official` / `tawb_official` give the branch's images
    (exactly), flow (1e-3 px: float32 round-off; NaN where the branch has NaN) and masks (exactly)
    of every pair the bench takes (images and flow on the fixture's grid, masks in full);
  * numbers: `evaluators.run_bench` (what `python evaluate.py --protocol official` runs) scores
    the fixture's prediction (`bench_trees.scored_prediction` of the GT) with the numbers the
    branch's `WideBaselineDenseBenchmark.analyze_results` reported.

UFM_BENCHMARK_FIXTURES (a folder of such fixture folders, or one) adds other cases, checked the
same way.
"""

import json
import os
import pathlib

import numpy as np
import pytest

from ufm_jax import evaluators
from ufm_jax.data import get_source
from ufm_jax.testing import bench_trees

IN_REPO = pathlib.Path(__file__).resolve().parent / "fixtures" / "benchmark_protocol"
# The branch's names of the numbers -> ours (`<bench>/<metric>`); its percentages are ours too.
NUMBERS = {"epe_covis": "epe", "px1": "px1", "px2": "px2", "px5": "px5",
           "epe_occluded": "epe_occluded"}


def _folders() -> dict[str, pathlib.Path]:
  out = {"repo": IN_REPO}
  extra = os.environ.get("UFM_BENCHMARK_FIXTURES")
  if extra:
    p = pathlib.Path(extra)
    for f in sorted([p] + [q for q in p.iterdir() if q.is_dir()] if p.is_dir() else []):
      if (f / "benchmark.json").is_file():
        out[f.name] = f
  return out


def _spec(folder):
  return json.loads((folder / "benchmark.json").read_text())


def _source(folder, bench, spec):
  c = spec["benches"][bench]["constructor"]
  if bench == "tawb":   # stored labels: TA-WB/<split>/ shards
    return get_source("tawb_official", str(folder / c["ROOT"]), split=c["split"])
  return get_source(f"{bench}_official", str(folder / c["ROOT"]),
                    pairs=str(folder / c["pair_metadata_path"]),
                    stride=spec["benches"][bench]["stride"])


CASES = [(label, b, k) for label, f in _folders().items() for b, v in _spec(f)["benches"].items()
         for k in range(v["n_samples"])]


@pytest.mark.parametrize("folder,bench,k", CASES)
def test_samples_equal_the_branch_pipeline(folder, bench, k):
  folder = _folders()[folder]
  spec = _spec(folder)
  g = spec["grid"]
  src = _source(folder, bench, spec)
  assert len(src) == spec["benches"][bench]["n_samples"]
  s = src[k]
  z = np.load(folder / "samples.npz")
  want = lambda key: z[f"{bench}_s{k}_{key}"]   # noqa: E731
  assert s["image0"].shape == (420, 560, 3)
  for i in (0, 1):
    np.testing.assert_array_equal(np.moveaxis(s[f"image{i}"], -1, 0)[:, ::g, ::g],
                                  want(f"img{i}_grid"), err_msg=f"image{i}")
  np.testing.assert_array_equal(s["flow_valid"], want("valid_mask"))
  np.testing.assert_array_equal(s["covisibility"], want("covisible_mask"))
  # float32 projection round-off: up to 1.8e-4 px on ~90 px flow measured on the public cases
  np.testing.assert_allclose(np.moveaxis(s["flow"], -1, 0)[:, ::g, ::g], want("flow_gt_grid"),
                             atol=1e-3, rtol=0)


class _Oracle:
  """A runner that answers each pair with the fixture's prediction of its ground truth (looked
  up by the images it is handed), in place of a model."""
  resolution = None

  def __init__(self, src):
    self.truth = {}
    for i in range(len(src)):
      s = src[i]
      self.truth[s["image0"].tobytes() + s["image1"].tobytes()] = s["flow"]

  def __call__(self, image0, image1):
    gt = self.truth[np.ascontiguousarray(image0).tobytes() + np.ascontiguousarray(image1).tobytes()]
    pred = bench_trees.scored_prediction(np.moveaxis(gt, -1, 0))
    return {"flow": np.moveaxis(pred, 0, -1), "covisibility": None}

  def warmup(self, image0, image1):
    pass


@pytest.mark.parametrize("folder,bench", sorted({(f, b) for f, b, _ in CASES}))
def test_run_bench_reports_the_branch_numbers(folder, bench):
  folder = _folders()[folder]
  spec = _spec(folder)
  src = _source(folder, bench, spec)
  root = folder / pathlib.Path(spec["benches"][bench]["constructor"]["ROOT"]).parent
  res, n = evaluators.run_bench(bench, _Oracle(src), str(root), progress=False)
  assert n == {bench: spec["benches"][bench]["n_samples"]}
  for theirs, ours in NUMBERS.items():
    assert res[f"{bench}/{ours}"] == pytest.approx(
        spec["benches"][bench]["numbers"][theirs], rel=1e-5, abs=1e-5), theirs
