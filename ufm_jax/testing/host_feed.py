"""The host feed a plan needs, measured on this host: host CPU milliseconds per training row of a
recipe's own input pipeline.

`measure(config)` runs `trainer.build_input` (what train.py runs) on the config's input block
with its datasets, quotas, training shapes, augmentation and image operations, reading stand-in
trees in each dataset's official on-disk layout (`official_trees`, at the recipe's largest
training shape; TA-WB square at its width) instead of the real data, which a planning host does
not have. Only what a measurement needs differs from the run: workers=0 and no read threads (each
row is made inside the timed window, in this process, with one OpenCV thread: a grain worker's
share of the host), a small batch, and the trees' one or few pairs per dataset. Rows are drawn
by the recipe's quotas, so the figure is the quota-weighted mean the table of
docs/host_input.md reports. A config with its own `data_fn` is timed as it is (no trees).

The figure is process CPU time per row, which load on the host inflates: the load average is
recorded beside it. Trees are written once per (dataset, size) under `cache_dir` (each written
aside and renamed into place: never half-written) and reused by later plans.

`train.py --compile_only` and `benchmarks/train_step.py` call `for_plan` before planning;
`--host_ms_per_row` replaces the measurement.
"""

from __future__ import annotations

import copy
import os
import tempfile
import time
import types

DEFAULT_ROWS = 96
DEFAULT_CACHE = os.path.join(tempfile.gettempdir(), "ufm_jax_host_feed")
# Rows per measured batch: a symmetrized pair's two rows, twice (each batch draws one shape).
BATCH = 4
WARMUP_BATCHES = 2   # sources opening, numba's first calls, the heap growing


def stand_in_root(name: str, hw, cache_dir: str = DEFAULT_CACHE) -> str:
  """The folder of dataset `name` in its official layout at (H, W) `hw` (written once)."""
  from ufm_jax.testing import official_trees
  h, w = (int(x) for x in hw)
  root = os.path.join(cache_dir, f"{name}_{h}x{w}")
  if not os.path.isdir(root):
    from ufm_jax.data import io
    os.makedirs(cache_dir, exist_ok=True)
    try:
      with io.atomic_dir(root) as tmp:
        official_trees.write_official_dataset(str(tmp), name, (h, w))
    except OSError:          # another plan wrote it first
      if not os.path.isdir(root):
        raise
  return os.path.join(root, official_trees.FOLDERS[name])


def measured_config(config, cache_dir: str = DEFAULT_CACHE):
  """A copy of `config` whose input block reads stand-in trees at the recipe's largest training
  shape, synchronously (workers=0, no read threads), BATCH rows per batch."""
  from ufm_jax.data import input_block, mixture
  config = copy.deepcopy(config)
  config.unlock()
  inp = config.input
  inp.batch_size = BATCH
  if inp.get("data_fn"):
    return config
  shapes = input_block.training_shapes(inp)
  hw = max(shapes, key=lambda s: s[0] * s[1])
  for name, spec in inp.datasets.items():
    if int(spec.quota) > 0 and name in mixture.LAYOUTS:
      spec.root = stand_in_root(name, hw, cache_dir)
  inp.num_workers = 0
  inp.read_threads = 0
  inp.prefetch_buffer_size = 0
  return config


def _teacher(config):
  """What build_input takes of a distillation teacher: its resolution (config.teacher.resolution,
  else the teacher as train.py loads it, on one device)."""
  if not config.get("teacher"):
    return None
  res = dict(config.teacher).get("resolution")
  if res:
    return types.SimpleNamespace(resolution=tuple(int(v) for v in res))
  import jax
  from ufm_jax.training import sharding
  from ufm_jax.training import teacher as teacher_lib
  spec = ",".join(f"{a}:1" for a in sharding.BATCH_AXES)
  return teacher_lib.from_config(config, sharding.make_mesh(spec, jax.devices()[:1]))


def measure(config, rows: int = DEFAULT_ROWS, cache_dir: str = DEFAULT_CACHE) -> dict:
  """Host CPU ms per row of `config`'s input pipeline on stand-in data (module docstring), over
  at least `rows` rows after WARMUP_BATCHES. -> {host_ms_per_row, wall_ms_per_row, rows,
  load_avg_1m (at the end), load_avg_1m_start, image_shapes (drawn), datasets, dropped (configured
  but absent: a dataset without an official layout whose folder is not on this host), source,
  seconds}. FileNotFoundError when no dataset of the mixture is there."""
  import cv2
  from ufm_jax.training import trainer
  t_all = time.perf_counter()
  load_start = os.getloadavg()[0]
  measured = measured_config(config, cache_dir)
  threads, it = cv2.getNumThreads(), None
  cv2.setNumThreads(1)
  try:
    it, info = trainer.build_input(measured, BATCH, int(config.get("seed", 0)),
                                   _teacher(config))
    for _ in range(WARMUP_BATCHES):
      next(it)
    n, shapes = 0, set()
    t0, c0 = time.perf_counter(), time.process_time()
    while n < rows:
      batch = next(it)
      n += int(batch["image0"].shape[0])
      shapes.add(tuple(int(x) for x in batch["image0"].shape[1:3]))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
  finally:
    cv2.setNumThreads(threads)
    if hasattr(it, "close"):
      it.close()
  return {"host_ms_per_row": round(1e3 * cpu / n, 2), "wall_ms_per_row": round(1e3 * wall / n, 2),
          "rows": n, "load_avg_1m": round(os.getloadavg()[0], 2),
          "load_avg_1m_start": round(load_start, 2), "image_shapes": sorted(shapes),
          "datasets": sorted(info.get("datasets") or ()),
          "dropped": list(info.get("dropped") or ()), "source": "measured",
          "seconds": round(time.perf_counter() - t_all, 1)}


def for_plan(config, host_ms_per_row: float | None = None, rows: int = DEFAULT_ROWS,
             log=print) -> dict:
  """The host feed figure of a plan: `host_ms_per_row` where given (--host_ms_per_row), else
  `measure(config)`; says which in one line. A mixture with nothing to read here (no stand-in,
  no data) gives host_ms_per_row None and the reason as its source."""
  if host_ms_per_row is not None:
    if not host_ms_per_row > 0:
      raise ValueError(f"--host_ms_per_row={host_ms_per_row}: must be a positive number of ms")
    return {"host_ms_per_row": float(host_ms_per_row), "source": "--host_ms_per_row",
            "load_avg_1m": None}
  log(f"host feed: timing {rows} rows of the recipe's input pipeline on stand-in data "
      f"(--host_ms_per_row to skip)", flush=True)
  try:
    feed = measure(config, rows)
  except FileNotFoundError as e:
    # A dataset with no stand-in (no official layout, e.g. video frames) and absent here.
    log(f"host feed: not measured: {e}; give --host_ms_per_row", flush=True)
    return {"host_ms_per_row": None, "source": f"not measured: {e}", "load_avg_1m": None}
  if feed["dropped"]:
    log(f"host feed: measured without {', '.join(feed['dropped'])} (no stand-in, absent "
        f"here)", flush=True)
  return feed
