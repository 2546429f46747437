"""What every evaluator shares: the model runner, the bench table, prediction files, results.

A bench names a family (flow / dense / pose), one or more dataset sources (one per split, e.g.
Sintel clean and final), the sub-folder of `--data_root` holding the data, the `data/` tool
that prepares it and its protocol: `native` (ours) or `official` (the UFM benchmark branch's;
docs/benchmarks.md). Evaluators take any sequence of sample dicts (see ufm_jax/data/registry.py),
so tests can feed in-memory sources.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import statistics
from typing import Any, Sequence

import numpy as np

from ufm_jax.runtime import inference, outputs


class MissingDataError(FileNotFoundError):
  """A bench's data is absent or not in the expected layout."""


@dataclasses.dataclass(frozen=True)
class Split:
  label: str               # metric prefix: "<label>/<metric>"
  source: str              # ufm_jax.data.get_source name
  options: tuple = ()      # extra (key, value) options for get_source


@dataclasses.dataclass(frozen=True)
class Bench:
  name: str
  family: str                          # "flow" | "dense" | "pose"
  splits: tuple[Split, ...]
  data_subdir: str | tuple[str, ...]   # folder(s) under --data_root, the first present is used
  layout: str                          # expected on-disk layout (for error messages)
  tool: str                            # the data/ tool that prepares it
  options: tuple = ()                  # evaluator options, e.g. (("auc_thresholds", (5, 10, 15)),)
  protocol: str = "native"             # "native" | "official"

  def option(self, key, default=None):
    return dict(self.options).get(key, default)

  @property
  def subdirs(self) -> tuple[str, ...]:
    return (self.data_subdir,) if isinstance(self.data_subdir, str) else tuple(self.data_subdir)


def round_to_multiple(x: float, m: int = 14) -> int:
  return max(m, int(round(x / m)) * m)


def resolution_for(mode, hw: tuple[int, int], patch: int = 14):
  """Inference (H, W) for a pair whose source is `hw`, or None for the model config's own.

  mode None: the model's configured inference resolution (the official `predict`).
  mode int R: the source aspect ratio with the longest side R, sides rounded to multiples of 14
    (the paper's "560" / "980" rows).
  mode "native": the source size rounded to multiples of 14 (the paper's "1K" rows).
  """
  if mode is None:
    return None
  h, w = hw
  if mode == "native":
    return round_to_multiple(h, patch), round_to_multiple(w, patch)
  s = int(mode) / max(h, w)
  return round_to_multiple(h * s, patch), round_to_multiple(w * s, patch)


class Runner:
  """Runs `ufm_jax.predict` on one pair at a time and keeps the forward-pass timings."""

  def __init__(self, model, variables, resolution=None):
    self.model, self.variables, self.resolution = model, variables, resolution
    self.timings: list[tuple[float, int]] = []

  def __call__(self, image0: np.ndarray, image1: np.ndarray) -> dict[str, np.ndarray]:
    res = resolution_for(self.resolution, image0.shape[:2])
    return inference.predict(self.model, self.variables, image0, image1,
                             resolutions=None if res is None else [res], timings=self.timings)

  def warmup(self, image0, image1) -> None:
    """Compiles the forward for this pair's shape outside the timed runs (I/O excluded)."""
    self(image0, image1)

  def ms_per_pair(self, mean: bool = False) -> float:
    """Median (or, with `mean`, mean: the branch's `method_time_avg`) forward time per pair in ms
    over calls that did not compile (NaN if none)."""
    per_pair = [t / n for t, n in self.timings if n]
    if not per_pair:
      return float("nan")
    return 1e3 * (statistics.fmean(per_pair) if mean else statistics.median(per_pair))


def relpath_of(sample: dict, index: int) -> str:
  """The dataset's own GT relative path (meta["gt_relpath"]), or a stable fallback."""
  meta = sample.get("meta", {}) or {}
  rel = meta.get("gt_relpath")
  if rel:
    return str(rel)
  parts = [str(meta[k]) for k in ("scene", "frame0", "frame1") if meta.get(k) not in (None, "")]
  return "/".join(parts[:1] + ["_".join(parts[1:])]) + ".flo" if len(parts) > 1 else f"{index:06d}.flo"


class PredictionWriter:
  """--save_predictions: flow (.flo) + covisibility PNG per pair (when the model predicts
  covisibility) + the flow covariance (`<name>_flow_covariance.npy`, ufm_jax.runtime.outputs, when it
  predicts one), panels for the first N pairs of each bench (with the uncertainty tile for a
  flow covariance model), under <root>/<bench>/<the dataset's GT relative path>."""

  def __init__(self, root: str | os.PathLike | None, num_panels: int = 8):
    self.root = None if root is None else pathlib.Path(root)
    self.num_panels = num_panels
    self.written: dict[str, int] = {}  # per bench

  def __call__(self, bench: str, sample: dict, index: int, pred: dict) -> None:
    if self.root is None:
      return
    from ufm_jax.runtime import viz
    from ufm_jax.data import io

    rel = pathlib.PurePosixPath(relpath_of(sample, index)).with_suffix("")
    base = self.root / bench / rel
    base.parent.mkdir(parents=True, exist_ok=True)
    io.write_flo(base.with_suffix(".flo"), pred["flow"])
    covis = pred.get("covisibility")   # None: a model without an uncertainty head
    if covis is not None:
      io.write_image(base.parent / (base.name + "_covisibility.png"),
                     viz.covisibility_to_image(covis))
    cov = pred.get("flow_covariance")
    if cov is not None:
      io.write_npy(base.parent / (base.name + outputs.SUFFIXES["vnpy"]),
                   np.asarray(cov, np.float32))
    if self.written.get(bench, 0) < self.num_panels:
      panels = self.root / bench / "panels"
      panels.mkdir(parents=True, exist_ok=True)
      io.write_image(panels / (str(rel).replace("/", "__") + ".png"),
                     viz.panel(sample["image0"], sample["image1"], pred["flow"], covis,
                               covariance=pred.get("flow_covariance")))
    self.written[bench] = self.written.get(bench, 0) + 1


def predicted_paths(root, bench: str, sample: dict, index: int) -> tuple[pathlib.Path, pathlib.Path]:
  """Where PredictionWriter puts the flow and covisibility of a sample."""
  rel = pathlib.PurePosixPath(relpath_of(sample, index)).with_suffix("")
  base = pathlib.Path(root) / bench / rel
  return base.with_suffix(".flo"), base.parent / (base.name + "_covisibility.png")


def take(source: Sequence, max_pairs: int | None) -> range:
  n = len(source)
  return range(n if max_pairs is None else min(n, int(max_pairs)))


def evaluate_source(bench: Bench, label: str, source, runner: Runner, family_eval,
                    max_pairs=None, writer: PredictionWriter | None = None, progress=True):
  """Runs one split: warm-up on the first pair, then every pair through `family_eval`.

  family_eval(sample, pred) accumulates; returns (n_pairs, corrupt_count).
  """
  from tqdm import tqdm

  idx = take(source, max_pairs)
  if len(idx) == 0:
    raise MissingDataError(f"bench {bench.name} ({label}): the source has no pairs")
  first = source[0]
  runner.warmup(first["image0"], first["image1"])
  skipped = 0
  for i in tqdm(idx, desc=f"{bench.name}/{label}", disable=not progress, unit="pair"):
    try:
      sample = first if i == 0 else source[i]
    except (ValueError, OSError) as e:  # a corrupt sample is skipped and counted
      print(f"warning: {bench.name}/{label}: skipping pair {i}: {e}")
      skipped += 1
      continue
    pred = runner(sample["image0"], sample["image1"])
    family_eval(sample, pred)
    if writer is not None:
      writer(bench.name, sample, i, pred)
  return len(idx) - skipped, skipped


def summary_versions() -> dict[str, Any]:
  import platform
  import sys

  import cv2
  import flax
  import jax

  import ufm_jax
  return {"ufm_jax": ufm_jax.__version__, "jax": jax.__version__, "flax": flax.__version__,
          "numpy": np.__version__, "opencv": cv2.__version__,
          "python": sys.version.split()[0], "platform": platform.platform(),
          "device": f"{jax.devices()[0].platform}:{jax.devices()[0].device_kind}"}
