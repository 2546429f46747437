"""The training config's input block (`config.input`): its defaults, the builder the recipes
call (`input_config`), the grain worker count, and glibc malloc tuning in the processes that make
samples (`keep_heap`). `ufm_jax.data.pipeline.create` reads the block.
"""

from __future__ import annotations

import os

from ufm_jax.data import augment as augment_lib
from ufm_jax.data import mixture


# The one home of the input block's defaults: `input_config` builds a block from them and
# `pipeline.create` fills the keys a block leaves out.
INPUT_DEFAULTS = {
    "data_root": None,
    "split": None,
    "batch_size": 96,
    "symmetrize": True,
    "longest_side": 560,
    "aspect_ratios": augment_lib.DEFAULT_ASPECT_RATIOS,
    "shapes": (),
    "augment": {},
    "num_workers": -1,
    "read_threads": 2,
    "prefetch_buffer_size": 2,
    "worker_buffer_size": 1,
    "max_skip_fraction": 0.01,
    "skip_check_min_samples": 100,
    "backward_fallback": "unsupervised",
    "draw_variants": True,
    "max_retries": 8,
    "keep_heap": True,
    # Distillation (configs/distill.py, ufm_jax.data.distill_rows): (H, W) the teacher sees each
    # pair at, un-augmented; empty: labelled rows (a typed default, as `shapes`, so that the
    # command line can set it). keep_labels: distillation rows also carry the crop's labels (read
    # only when a loss term mixes them in).
    "teacher_shape": (),
    "keep_labels": False,
}


def training_shapes(block) -> tuple[tuple[int, int], ...]:
  """The (H, W) training shapes of an input block, one drawn per global batch: `shapes` when it
  lists them (the recipes' official ones), else W = longest_side with H from aspect_ratios. The
  one rule for the pipeline (`pipeline.create`) and the planner (`ufm_jax.planning.planner`), which
  compiles the step at the largest of them."""
  cfg = {**INPUT_DEFAULTS, **dict(block)}
  if cfg["shapes"]:
    return augment_lib.check_shapes(cfg["shapes"])
  return augment_lib.training_shapes(int(cfg["longest_side"]), tuple(cfg["aspect_ratios"]))


# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_heap(worker_index: int = 0, worker_count: int = 0) -> bool:
  """Makes glibc's malloc keep freed memory for the next sample (this process only).

  A sample's dozens of 0.1-10 MB temporaries are otherwise mmap'd fresh and unmapped again each
  time (or trimmed from the heap top), and the page faults of touching them anew cost ~12% of a
  row's host CPU at 560 (`benchmarks/data_pipeline.py --table1` with and without
  `--no_keep_heap`: 14.3 vs 12.6 ms, docs/host_input.md). Serving them from a heap that is not
  trimmed: mmap threshold at its 32 MiB maximum, trim threshold 512 MiB (freed memory up to that
  stays with the process). Runs in every process that makes samples: the grain workers (as their
  worker_init_fn, hence the signature) or, with num_workers=0, the training process. False where the C library is not glibc."""
  del worker_index, worker_count
  import ctypes  # pylint: disable=g-import-not-at-top
  try:
    mallopt = ctypes.CDLL("libc.so.6").mallopt
  except (OSError, AttributeError):
    return False
  return bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20)) and bool(mallopt(_M_TRIM_THRESHOLD, 512 << 20))


def auto_num_workers(cpu_count: int | None = None) -> int:
  """Grain worker processes for `num_workers=-1`: every core but two (the training process and
  its device feeding), at most 32; 0 (threads in-process) on small hosts."""
  cores = cpu_count or os.cpu_count() or 1
  return max(0, min(cores - 2, 32))


def input_config(datasets, **overrides):
  """The `config.input` block read by `create`: INPUT_DEFAULTS with `overrides`.

  batch_size is the global number of pairs per step, both directions counted when symmetrized
  (the paper's 96 = 48 unique pairs); each process gets batch_size / process_count.
  num_workers: grain worker processes per host (-1: `auto_num_workers()`, from the core count).
  backward_fallback: what symmetrize does for datasets without backward labels ('unsupervised':
  the (b, a) row has all masks False; 'error': refuse to build).
  keep_heap: glibc malloc keeps freed memory in the processes that make samples (`keep_heap`).
  draw_variants: a source whose consecutive indices are `variants` renderings of one official
  sample (cameras, clean / final passes: the official FlyingThings3D, Monkaa and StaticThings
  readers) is drawn as the official dataset class is: the epoch plan counts official samples
  (quotas over len / variants) and each draw takes one rendering at random, from (seed,
  position). False: every rendering is a pair of its own, which keeps the expected frequency of
  each scene but not its spread (a scene drawn 0..4 times where the official draws it evenly).
  shapes: the (H, W) training shapes, one drawn uniformly per global batch (the recipes give
  the official ones, augment.SHAPES_560 / SHAPES_980); empty: W = longest_side and H from
  aspect_ratios.
  augment: `augment.AugmentConfig` keys (empty: the official augmentation).
  teacher_shape: distillation rows (ufm_jax.data.distill_rows) with the teacher's view at this
  (H, W); keep_labels: with the labels of the crop too.
  """
  import ml_collections  # pylint: disable=g-import-not-at-top
  unknown = sorted(set(overrides) - set(INPUT_DEFAULTS))
  if unknown:
    raise KeyError(f"input_config: unknown keys {unknown}; known: {sorted(INPUT_DEFAULTS)}")
  block = {**INPUT_DEFAULTS, **overrides}
  block["aspect_ratios"] = tuple(block["aspect_ratios"])
  block["shapes"] = tuple(tuple(int(x) for x in hw) for hw in block["shapes"])
  block["augment"] = dict(block["augment"] or {})
  block["data_root"] = block["data_root"] or mixture.DEFAULT_DATA_ROOT
  if block["split"] is None:
    del block["split"]
  return ml_collections.ConfigDict({"datasets": ml_collections.ConfigDict(datasets), **block})
