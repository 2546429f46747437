"""Shared config pieces: the paper's 12-dataset mixture (Table 1) and the `input` block builder.

Plain functions returning ml_collections ConfigDicts, used by configs/ufm560.py and friends:

  import configs.common as cc
  config.input = cc.input_config(cc.mixture(cc.ALL), batch_size=96, longest_side=560)

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
TRAIN_SHAPE_ASPECTS = (3.0, 2.0, 16 / 9, 4 / 3, 1.0)  # width:height, paper sec. 3.3


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


def input_config(datasets: ml_collections.ConfigDict | Mapping[str, Any], *, batch_size: int = 96,
                 longest_side: int = 560, symmetrize: bool = True,
                 data_root: str = DEFAULT_DATA_ROOT, aspect_ratios=TRAIN_SHAPE_ASPECTS,
                 augment: Mapping[str, Any] | None = None, num_workers: int = 8,
                 read_threads: int = 2, prefetch_buffer_size: int = 2, worker_buffer_size: int = 1,
                 max_skip_fraction: float = 0.01, skip_check_min_samples: int = 100,
                 reverse_fallback: str = "unsupervised") -> ml_collections.ConfigDict:
  """The `config.input` block read by `ufm_jax.data.pipeline.create`.

  batch_size is the global number of pairs per step, both directions counted when symmetrized
  (the paper's 96 = 48 unique pairs); each process gets batch_size / process_count.
  reverse_fallback: what symmetrize does for datasets without backward labels ('unsupervised':
  the (b, a) row has all masks False; 'error': refuse to build).
  """
  return ml_collections.ConfigDict({
      "datasets": ml_collections.ConfigDict(datasets),
      "data_root": data_root,
      "batch_size": batch_size,
      "symmetrize": symmetrize,
      "longest_side": longest_side,
      "aspect_ratios": tuple(aspect_ratios),
      "augment": dict(augment or {}),
      "num_workers": num_workers,
      "read_threads": read_threads,
      "prefetch_buffer_size": prefetch_buffer_size,
      "worker_buffer_size": worker_buffer_size,
      "max_skip_fraction": max_skip_fraction,
      "skip_check_min_samples": skip_check_min_samples,
      "reverse_fallback": reverse_fallback,
  })


def parse_arg(arg: str | None, **defaults) -> ml_collections.ConfigDict:
  """big_vision-style `get_config(arg)` parsing: "data=of,res=980" -> ConfigDict over defaults.

  Values are converted to the type of their default (bool accepts true/false/1/0).
  """
  out = ml_collections.ConfigDict(defaults)
  for item in filter(None, (arg or "").split(",")):
    if "=" not in item:
      raise ValueError(f"config arg {item!r} is not key=value (in {arg!r})")
    key, value = item.split("=", 1)
    if key not in defaults:
      raise KeyError(f"unknown config arg {key!r}; known: {sorted(defaults)}")
    default = defaults[key]
    if isinstance(default, bool):
      if value.lower() not in ("true", "false", "1", "0"):
        raise ValueError(f"config arg {key}={value!r} is not a bool")
      value = value.lower() in ("true", "1")
    elif default is not None:
      value = type(default)(value)
    out[key] = value
  return out


def model_options(dtype: str = "bfloat16", remat: bool = True, scan_blocks: bool = True,
                  head_dtype: str = "float32") -> ml_collections.ConfigDict:
  """The `model` block: UFMConfig compute options passed to the variant (train.build_model).

  Every option is present so each can be overridden from the command line (the block is locked):
  `--config.model.attention_impl=cudnn|xla` (typed None = auto: cuDNN on GPU for bf16, XLA
  elsewhere), `--config.model.scan_blocks=False` (unrolled blocks: slower compile, same numbers),
  `--config.model.head_dtype=bfloat16` (DPT heads in bf16; the official heads are float32).
  """
  return ml_collections.ConfigDict({
      "dtype": dtype, "remat": remat, "scan_blocks": scan_blocks, "head_dtype": head_dtype,
      "attention_impl": ml_collections.FieldReference(None, field_type=str)})
