"""Evaluators, one per benchmark family, chosen by bench name (`evaluate.py --bench NAME`).

  family  benches                              metrics (see each module's docstring)
  flow    sintel (clean, final), kitti         epe_all, epe_covis, px1/3/5 (+ breakdowns), fl_all
  dense   eth3d, dtu, tawb, synthetic          epe (covisible), px1/2/5, epe_occluded, epe_all
  pose    eth3d_pose, scannet1500, tawb_pose   auc@{5,10,15} (TA-WB: 10/20/30), acc@T

Two protocols (docs/benchmarks.md): `official` (default for the five benches the paper's Tables 2
and 3 report, OFFICIAL) reproduces the UFM benchmark branch: its data layouts, pairs, 560x420
crops, labels and masks, the model at its own inference resolution; `native` (BENCHES) is ours:
full-resolution data prepared by data/*/, labels by ufm_jax.geometry. Benches without an official
variant (synthetic, the pose benches) always run natively.

`run_bench(name, runner, data_root, protocol=...)` returns the flat metric dict keyed
`<bench>[_<split>]/<metric>`. The metrics themselves (EPE, thresholds, pose AUC, match sampling,
calibration) live in `ufm_jax.evaluators.metrics`; `train_evals` runs them inside train.py.
"""

from __future__ import annotations

import os

from ufm_jax.evaluators.base import (Bench, MissingDataError, PredictionWriter, Runner, Split,
                                     evaluate_source, resolution_for)
from ufm_jax.evaluators.dense import DenseMetrics
from ufm_jax.evaluators.flow import FlowMetrics
from ufm_jax.evaluators.pose import PoseMetrics

BENCHES: dict[str, Bench] = {b.name: b for b in (
    Bench("synthetic", "dense", (Split("synthetic", "synthetic", (("split", "test"),)),),
          data_subdir="", layout="none (generated on the fly)", tool="ufm_jax.data.synthetic"),
    Bench("sintel", "flow", (Split("sintel_clean", "sintel_clean"), Split("sintel_final", "sintel_final")),
          data_subdir="sintel",
          layout="MPI-Sintel-complete: training/{clean,final,flow,occlusions,invalid}/<scene>/frame_%04d.*",
          tool="data/sintel/", options=(("kind", "sintel"),)),
    Bench("kitti", "flow", (Split("kitti", "kitti2015"),), data_subdir="kitti2015",
          layout="training/image_2/%06d_{10,11}.png, training/flow_occ/%06d_10.png, training/flow_noc/",
          tool="data/kitti2015/", options=(("kind", "kitti"),)),
    Bench("eth3d", "dense", (Split("eth3d", "eth3d"),), data_subdir="eth3d",
          layout="<scene>/scene_meta.json, <scene>/images/*.jpg, <scene>/depth/*.exr, pairs_test.txt (prepared by data/eth3d/prepare.py)",
          tool="data/eth3d/"),
    Bench("dtu", "dense", (Split("dtu", "dtu"),), data_subdir="dtu",
          layout="Rectified/scan<N>/, Cameras/*_cam.txt + pair.txt, Depths_raw/scan<N>/depth_map_*.pfm", tool="data/dtu/"),
    Bench("tawb", "dense", (Split("tawb", "tawb"),), data_subdir="tawb",
          layout="test/<Env>/{images,depth,camera_params,poses}/ (prepared by data/tawb/prepare.py)", tool="data/tawb/"),
    Bench("eth3d_pose", "pose", (Split("eth3d_pose", "eth3d"),), data_subdir="eth3d",
          layout="<scene>/scene_meta.json, <scene>/images/*.jpg, <scene>/depth/*.exr, pairs_test.txt (prepared by data/eth3d/prepare.py)",
          tool="data/eth3d/", options=(("auc_thresholds", (5, 10, 15)),)),
    Bench("scannet1500", "pose", (Split("scannet1500", "scannet1500"),), data_subdir="scannet1500",
          layout="scannet_test_pairs_with_gt.txt + scannet_test_1500/<scene>/color/<frame>.jpg",
          tool="data/scannet1500/", options=(("auc_thresholds", (5, 10, 15)),)),
    Bench("tawb_pose", "pose", (Split("tawb_pose", "tawb"),), data_subdir="tawb",
          layout="test/<Env>/{images,depth,camera_params,poses}/ (prepared by data/tawb/prepare.py)", tool="data/tawb/",
          options=(("auc_thresholds", (10, 20, 30)),)),
)}


_BRANCH = "the benchmark branch's dataset_root (benchmarks/dense_correspondence/benchmark.py)"
OFFICIAL: dict[str, Bench] = {b.name: b for b in (
    Bench("sintel", "flow",
          (Split("sintel_clean", "sintel_clean", (("covis_in_image", False),)),
           Split("sintel_final", "sintel_final", (("covis_in_image", False),))),
          data_subdir=("Sintel", "sintel"),
          layout=f"Sintel/ ({_BRANCH}) = MPI-Sintel-complete: "
                 f"training/{{clean,final,flow,occlusions}}/",
          tool="data/sintel/", options=(("kind", "sintel"),), protocol="official"),
    Bench("kitti", "flow", (Split("kitti", "kitti2015"),), data_subdir=("KITTI", "kitti2015"),
          layout=f"KITTI/ ({_BRANCH}): training/image_2/, training/flow_occ/, training/flow_noc/",
          tool="data/kitti2015/", options=(("kind", "kitti"),), protocol="official"),
    Bench("eth3d", "dense", (Split("eth3d", "eth3d_official"),), data_subdir="eth3d_processed",
          layout=f"eth3d_processed/<scene>/{{undistorted_images,undistorted_depths,"
                 f"undistorted_camera_params,poses}}/ + anymap_data_pairs/eth3d_valid_pairs.npz "
                 f"({_BRANCH})", tool="data/eth3d/", protocol="official"),
    Bench("dtu", "dense", (Split("dtu", "dtu_official"),), data_subdir="dtu_processed",
          layout=f"dtu_processed/scan<N>/{{images,depths,camera_params,poses}}/ + "
                 f"anymap_data_pairs/dtu_valid_pairs.npz ({_BRANCH})", tool="data/dtu/",
          protocol="official"),
    Bench("tawb", "dense", (Split("tawb", "tawb_official"),), data_subdir="TA-WB",
          layout=f"TA-WB/data/*.json + *.h5 ({_BRANCH}; download_ta_wb.sh)", tool="data/tawb/",
          protocol="official"),
)}
PROTOCOLS = ("official", "native")


def get_bench(name: str, protocol: str = "official") -> Bench:
  """The bench `name` under `protocol`: its official variant when it has one, else the native."""
  if protocol not in PROTOCOLS:
    raise ValueError(f"unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}")
  if name not in BENCHES:
    raise KeyError(f"unknown bench {name!r}; known: {', '.join(BENCHES)}")
  return OFFICIAL.get(name, BENCHES[name]) if protocol == "official" else BENCHES[name]


def make_metrics(bench: Bench, seed: int = 0):
  if bench.family == "flow":
    return FlowMetrics(kind=bench.option("kind", "sintel"))
  if bench.family == "dense":
    # The synthetic task's absolute numbers mean little alone: report the zero-flow bar beside them.
    return DenseMetrics(baselines=bench.name == "synthetic", official=bench.protocol == "official")
  if bench.family == "pose":
    return PoseMetrics(thresholds=bench.option("auc_thresholds", (5, 10, 15)), seed=seed)
  raise ValueError(f"bench {bench.name}: unknown family {bench.family!r}")


def bench_root(bench: Bench, data_root: str | None) -> str | None:
  """The first `<data_root>/<subdir>` that exists, else `data_root` itself (a single dataset's
  folder)."""
  if not bench.data_subdir:
    return data_root
  if data_root is None:
    return None
  for sub in bench.subdirs:
    if os.path.isdir(os.path.join(data_root, sub)):
      return os.path.join(data_root, sub)
  return data_root


def open_source(bench: Bench, split: Split, data_root: str | None, **options):
  """The split's dataset source, or MissingDataError naming the layout and the data/ tool."""
  from ufm_jax.data import get_source

  root = bench_root(bench, data_root)
  if bench.protocol == "official":
    hint = (f"the official protocol expects under {root or '--data_root'}: {bench.layout}; how to "
            f"get it: {bench.tool}README.md (or evaluate with --protocol native on data prepared "
            f"by {bench.tool})")
  else:
    hint = (f"expected layout under {root or '--data_root'}: {bench.layout}; prepare it with "
            f"{bench.tool} (see its README.md)")
  if bench.data_subdir and root is None:
    raise MissingDataError(f"bench {bench.name}: --data_root is required; {hint}")
  try:
    source = get_source(split.source, root, **dict(split.options), **options)
    n = len(source)  # some readers list their pairs lazily: surface missing files here
  except KeyError as e:
    raise MissingDataError(f"bench {bench.name}: no reader registered for dataset "
                           f"{split.source!r} ({e}); {hint}") from None
  except (FileNotFoundError, NotADirectoryError, ValueError) as e:
    raise MissingDataError(f"bench {bench.name}: no usable data for {split.source} at {root}: "
                           f"{e}; {hint}") from None
  if n == 0:
    raise MissingDataError(f"bench {bench.name}: {split.source} at {root} has no pairs; {hint}")
  return source


def run_bench(name: str, runner: Runner, data_root: str | None = None, max_pairs=None,
              writer: PredictionWriter | None = None, progress: bool = True, sources=None,
              seed: int = 0, protocol: str = "official"):
  """Evaluates bench `name` under `protocol`; returns (metrics, n_pairs) with metrics keyed
  `<label>/<metric>`.

  `sources` ({split label: sequence of samples}) bypasses the dataset readers (tests, notebooks).
  The official protocol runs the model at its own inference resolution (the branch's
  solutions/ufm.py: `predict_correspondences_batched`), so `runner.resolution` must be None.
  """
  bench = get_bench(name, protocol)
  if bench.protocol == "official" and runner.resolution is not None:
    raise ValueError(f"bench {name}: the official protocol runs the model at its own inference "
                     f"resolution; resolution {runner.resolution!r} needs protocol 'native'")
  opened = {s.label: (sources or {}).get(s.label) for s in bench.splits}
  for s in bench.splits:  # open everything first: fail fast before any model work
    if opened[s.label] is None:
      opened[s.label] = open_source(bench, s, data_root)
  results, counts = {}, {}
  for s in bench.splits:
    acc = make_metrics(bench, seed)
    n, _ = evaluate_source(bench, s.label, opened[s.label], runner, acc, max_pairs, writer, progress)
    counts[s.label] = n
    results.update({f"{s.label}/{k}": v for k, v in acc.result().items()})
  return results, counts


__all__ = ["BENCHES", "Bench", "MissingDataError", "OFFICIAL", "PROTOCOLS", "PredictionWriter",
           "Runner", "Split", "bench_root", "get_bench", "make_metrics", "open_source",
           "resolution_for", "run_bench"]
