"""The training input pipeline: a quota mixture of datasets as a grain random-access index.

`create` builds it from the config's input block (ufm_jax.data.input_block, `input_config`):

  * ufm_jax.data.sampling_plan: the epoch sampling plan (every dataset exactly its quota per
    epoch, drawn from (seed, epoch)) and each host's random-access index into the global stream;
    grain's iterator state is the whole pipeline state, so a resume yields exactly the remaining
    batches;
  * ufm_jax.data.load_pair: the per-record transform (each pair through its dataset's official
    pathway, ufm_jax.data.augment) with skip-and-retry, and the skip accounting;
  * ufm_jax.data.backward_labels: where the (b, a) rows of symmetrized batches get their labels.

Batches are dicts of numpy arrays with a leading batch axis of the per-host batch size:
image0, image1 [B,H,W,3] uint8; flow [B,H,W,2] float32; covisibility, flow_valid, covis_valid
[B,H,W] bool; dataset_id [B] int32 (index into `Pipeline.names`); epoch [B] int32. With
`teacher_shape` (distillation) the labels give way to the teacher's view of each pair
(ufm_jax.data.distill_rows).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import zlib
from typing import Any, Mapping

import grain
import numpy as np

from ufm_jax.data import augment as augment_lib
from ufm_jax.data import mixture
from ufm_jax.data.backward_labels import backward_mode
from ufm_jax.data.distill_rows import DistillPair
from ufm_jax.data.input_block import (INPUT_DEFAULTS, auto_num_workers, input_config, keep_heap,
                                      training_shapes)
from ufm_jax.data.load_pair import LoadPair, SkipAccounting, SkipLimitExceeded, collate
from ufm_jax.data.registry import get_source
from ufm_jax.data.sampling_plan import MixtureIndex, MixtureLayout

log = logging.getLogger(__name__)

# `input_config` (the recipes' builder) and `SkipLimitExceeded` are part of this module's API.
__all__ = ["Pipeline", "SkipLimitExceeded", "create", "input_config", "make_train_iterator"]


@dataclasses.dataclass
class Pipeline:
  dataset: grain.IterDataset    # iter(dataset) -> checkpointable grain DatasetIterator of batches
  names: tuple[str, ...]        # dataset_id -> name
  quotas: tuple[int, ...]
  sizes: tuple[int, ...]         # samples the epoch plan draws from (official samples)
  dropped: tuple[str, ...]      # configured but absent on disk
  epoch_size: int               # unique pairs per epoch
  steps_per_epoch: float        # global batches per epoch (batches may straddle epochs)
  num_steps: int                # batches this iterator yields before it ends
  batch_size: int               # pairs per host batch
  shapes: tuple[tuple[int, int], ...]
  symmetrize: bool

  def __iter__(self):
    return iter(self.dataset)


def _open_sources(datasets: Mapping[str, Mapping[str, Any]], split: str | None,
                  data_root: str | None):
  present, dropped = {}, []
  for name, spec in datasets.items():
    spec = dict(spec)
    quota = int(spec.pop("quota"))
    root = spec.pop("root", None)
    options = dict(spec.pop("options", {}) or {})
    if spec:
      raise KeyError(f"input.datasets.{name}: unknown keys {sorted(spec)}; "
                     "expected quota, root, options")
    if quota <= 0:
      continue
    reader = name
    if name in mixture.LAYOUTS:
      # The official layout first, else the raw one (mixture.find_layout); LayoutError stops here.
      layout, found, why = mixture.find_layout(name, data_root, root)
      if layout is None:
        dropped.append(f"{name} ({why})")
        continue
      log.info("dataset %s: %s layout at %s, read by %r (%s)", name, layout.kind, found,
               layout.source, why)
      reader, root = layout.source, found
    elif root is not None:
      root = os.path.expanduser(str(root))
      if data_root is not None and not os.path.isabs(root):
        root = os.path.join(os.path.expanduser(str(data_root)), root)
    if root is not None and not os.path.exists(root):
      dropped.append(f"{name} ({root})")
      continue
    if split is not None:
      options.setdefault("split", split)
    try:
      source = get_source(reader, root, **options)
    except FileNotFoundError as e:
      dropped.append(f"{name} ({e})")
      continue
    if len(source) == 0:
      dropped.append(f"{name} (empty at {root})")
      continue
    present[name] = (source, quota)
  if dropped:
    log.warning("datasets absent on disk, dropped from the mixture (the others keep their "
                "quotas): %s", "; ".join(dropped))
  if not present:
    raise FileNotFoundError(f"no dataset of the mixture is available; absent: {'; '.join(dropped)}")
  return present, tuple(d.split(" ")[0] for d in dropped)


def make_train_iterator(config: Mapping[str, Any], *, process_batch: int | None = None,
                        seed: int = 0, num_epochs: int | None = None):
  """(checkpointable grain iterator of host batches, info) for train.py.

  info: pairs_per_epoch (batch rows per epoch: both directions counted when symmetrized, so
  steps per epoch = pairs_per_epoch / input.batch_size), unique_pairs_per_epoch, image_shape
  (the first training shape), shapes, datasets {name: quota}, dropped.
  """
  pipe = create(config, seed=seed, num_epochs=num_epochs)
  if process_batch is not None and int(process_batch) != pipe.batch_size:
    raise ValueError(f"train.py expects {process_batch} pairs per process, the pipeline makes "
                     f"{pipe.batch_size} (input.batch_size / process count)")
  rows = pipe.epoch_size * (2 if pipe.symmetrize else 1)
  info = {"pairs_per_epoch": rows, "unique_pairs_per_epoch": pipe.epoch_size,
          "image_shape": tuple(pipe.shapes[0]), "shapes": [tuple(x) for x in pipe.shapes],
          "datasets": dict(zip(pipe.names, pipe.quotas)), "dropped": list(pipe.dropped)}
  return iter(pipe), info


def create(config: Mapping[str, Any], *, seed: int = 0, num_epochs: int | None = None,
           process_index: int | None = None, process_count: int | None = None) -> Pipeline:
  """Builds the training pipeline from an input block (`input_config`; keys it leaves out take
  INPUT_DEFAULTS).

  Keys: datasets {name: {quota, root, options}} (relative roots are under data_root), data_root,
  batch_size (global pairs per step, counting both directions when symmetrized), symmetrize,
  longest_side, aspect_ratios, shapes, augment {...}, num_workers, worker_buffer_size, read_threads,
  prefetch_buffer_size, max_skip_fraction, skip_check_min_samples, backward_fallback, split,
  keep_heap, draw_variants.
  process_index/count default to jax's (grain ShardByJaxProcess).
  """
  cfg = dict(config.to_dict() if hasattr(config, "to_dict") else config)
  unknown = sorted(set(cfg) - set(INPUT_DEFAULTS) - {"datasets"})
  if unknown:
    raise KeyError(f"input block: unknown keys {unknown}; known: {sorted(INPUT_DEFAULTS)}")
  cfg = {**INPUT_DEFAULTS, **cfg}
  jax_processes = process_index is None or process_count is None
  if jax_processes:
    shard = grain.sharding.ShardByJaxProcess(drop_remainder=True)
    process_index, process_count = shard.shard_index, shard.shard_count
  symmetrize = bool(cfg["symmetrize"])
  global_batch = int(cfg["batch_size"])
  per_host, rem = divmod(global_batch, process_count)
  if rem:
    raise ValueError(f"input.batch_size={global_batch} is not divisible by {process_count} processes")
  if symmetrize and per_host % 2:
    raise ValueError(f"input.batch_size={global_batch}: symmetrized batches need an even per-host "
                     f"batch, got {per_host} on each of {process_count} processes")
  unique_per_host = per_host // 2 if symmetrize else per_host

  present, dropped = _open_sources(cfg["datasets"], cfg.get("split"), cfg.get("data_root"))
  names = tuple(present)
  sources = [present[n][0] for n in names]
  quotas = tuple(present[n][1] for n in names)
  # Renderings of one official sample (`variants` consecutive indices) drawn as one sample.
  variants = tuple(int(getattr(s, "variants", 1)) if cfg["draw_variants"] else 1
                   for s in sources)
  sizes = tuple(len(s) // v for s, v in zip(sources, variants))
  teacher_shape = cfg.get("teacher_shape")
  labelled = not teacher_shape or bool(cfg.get("keep_labels"))
  modes = ()
  if symmetrize and labelled:
    fallback = str(cfg["backward_fallback"])
    if fallback not in ("unsupervised", "error"):
      raise ValueError(f"input.backward_fallback must be 'unsupervised' or 'error', got {fallback!r}")
    modes = tuple(backward_mode(s, n, fallback) for s, n in zip(sources, names))
    unsup = [n for n, m in zip(names, modes) if m == "unsupervised"]
    if unsup:
      log.warning("no backward labels for %s: their (b, a) rows in symmetrized batches carry no "
                  "supervision (all masks False)", ", ".join(unsup))
  shapes = training_shapes(cfg)
  if jax_processes and process_count > 1:
    # Every host derives the same plans only if it sees the same datasets with the same sizes.
    from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
    multihost_utils.assert_equal(
        # int32: jax without x64 would wrap an int64 differently on each side of the comparison.
        np.array([zlib.crc32(repr((names, sizes, quotas)).encode()) & 0x7FFFFFFF], np.int32),
        f"hosts disagree on the mixture (names, sizes, quotas); this host: "
        f"{list(zip(names, sizes, quotas))}")
  layout = MixtureLayout(names, sizes, quotas, int(seed), unique_per_host, int(process_index),
                         int(process_count), num_epochs)
  if layout.num_steps == 0:
    raise ValueError(f"epoch of {layout.epoch_size} pairs is smaller than one global batch of "
                     f"{layout.unique_per_step} unique pairs")
  load_kw = dict(backward_modes=modes, layout=layout, shapes=shapes,
                 augment_cfg=augment_lib.AugmentConfig.from_dict(cfg["augment"]),
                 symmetrize=symmetrize, max_retries=int(cfg["max_retries"]), variants=variants)
  if teacher_shape:
    load = DistillPair(sources, names, teacher_hw=tuple(teacher_shape),
                       keep_labels=bool(cfg.get("keep_labels")), **load_kw)
  else:
    load = LoadPair(sources, names, **load_kw)
  ds = MixtureIndex(layout).map(load).batch(unique_per_host, drop_remainder=True, batch_fn=collate)
  ds = ds.to_iter_dataset(grain.ReadOptions(
      num_threads=int(cfg["read_threads"]),
      prefetch_buffer_size=int(cfg["prefetch_buffer_size"])))
  workers = int(cfg["num_workers"])
  if workers < 0:
    workers = auto_num_workers()
  if workers > 0:
    from absl import flags  # pylint: disable=g-import-not-at-top
    if not flags.FLAGS.is_parsed():
      # grain's worker start-up reads its absl flags; outside an absl app (pytest, notebooks,
      # benchmarks) they keep their defaults.
      flags.FLAGS.mark_as_parsed()
    ds = ds.mp_prefetch(grain.MultiprocessingOptions(
        num_workers=workers, per_worker_buffer_size=int(cfg["worker_buffer_size"])),
        worker_init_fn=keep_heap if cfg["keep_heap"] else None)
  elif cfg["keep_heap"]:
    keep_heap()
  ds = SkipAccounting(ds, float(cfg["max_skip_fraction"]),
                       int(cfg["skip_check_min_samples"]))
  return Pipeline(dataset=ds, names=names, quotas=quotas, sizes=sizes, dropped=dropped,
                  epoch_size=layout.epoch_size,
                  steps_per_epoch=layout.epoch_size / layout.unique_per_step,
                  num_steps=layout.num_steps, batch_size=per_host, shapes=shapes,
                  symmetrize=symmetrize)
