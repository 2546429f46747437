"""The paper's 12-dataset training mixture (Table 1) as `input.datasets` blocks.

  from ufm_jax.data import mixture, pipeline
  config.input = pipeline.input_config(mixture.mixture(mixture.ALL), batch_size=96)

Dataset roots are stored relative to `input.data_root` (resolved by the pipeline), so one override
moves them all: `--config.input.data_root=/data/ufm`. A dataset whose folder is absent is dropped
with a warning and the others keep their quotas.
"""

from __future__ import annotations

import os
from typing import Any, Iterable, Mapping

import ml_collections

# "Pairs in Epoch" of paper Table 1, keyed by the `ufm_jax.data.get_source` names.
QUOTAS = {
    "blendedmvs": 100_000,
    "megadepth": 100_000,
    "tartanair_v2": 100_000,
    "scannetpp": 100_000,
    "habitat": 25_000,
    "staticthings": 10_000,
    "kubric4d": 50_000,
    "flyingthings": 50_000,
    "flyingchairs": 25_000,
    "spring": 25_000,
    "monkaa": 5_000,
    "hd1k": 5_000,
}
ALL = tuple(QUOTAS)
# Table 1's "Wide Baseline" column (Kubric4D is the one dynamic wide-baseline set) ...
WIDE_BASELINE = ("blendedmvs", "megadepth", "tartanair_v2", "scannetpp", "habitat", "staticthings",
                 "kubric4d")
# ... and the small-motion optical-flow sets: the Table 4 "OF" ablation and the 980 bootstrap.
OPTICAL_FLOW = ("flyingthings", "flyingchairs", "spring", "monkaa", "hd1k")
# Sub-pixel-accurate sets the refiner trains on (supplementary "Training the Refinement").
REFINE = ("blendedmvs", "megadepth", "habitat", "scannetpp")

DEFAULT_DATA_ROOT = os.environ.get("UFM_DATA_ROOT", "~/ufm_data")


def mixture(names: Iterable[str] = ALL, quotas: Mapping[str, int] | None = None,
            options: Mapping[str, Mapping[str, Any]] | None = None,
            split: str = "train") -> ml_collections.ConfigDict:
  """`input.datasets`: {name: {quota, root (relative to data_root), options}}."""
  quotas = {**QUOTAS, **(quotas or {})}
  out = ml_collections.ConfigDict()
  for name in names:
    if name not in quotas:
      raise KeyError(f"no quota for dataset {name!r}; pass quotas={{{name!r}: N}}")
    out[name] = ml_collections.ConfigDict({
        "quota": int(quotas[name]), "root": name,
        "options": {"split": split, **dict((options or {}).get(name, {}))}})
  return out


def synthetic_mixture(num_pairs: int = 10_000, size=(112, 112), seed: int = 0,
                      **options) -> ml_collections.ConfigDict:
  """`input.datasets` of the embedded synthetic source alone (rendered on the fly, no files):
  one epoch = `num_pairs` pairs, each rendered at `size` (H, W)."""
  return ml_collections.ConfigDict({"synthetic": {
      "quota": int(num_pairs), "root": None,
      "options": {"split": "train", "num_pairs": int(num_pairs), "size": tuple(size),
                  "seed": int(seed), **options}}})
