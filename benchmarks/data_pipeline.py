"""Input-pipeline throughput: samples/s and batches/s of the training mixture.

  python benchmarks/data_pipeline.py                       # synthetic mixture, tiny + 560 shapes
  python benchmarks/data_pipeline.py --longest_side 560 --workers 0,2,4 --batch_size 16
  python benchmarks/data_pipeline.py --config configs/ufm560.py --data_root /data/ufm  # real mixture
  python benchmarks/data_pipeline.py --table1 --longest_side 560 [--native] [--no_keep_heap]  # Table 1 formats
  python benchmarks/data_pipeline.py --table1 --layouts official  # the official processed layouts

Source per shape: up to --render_max_side the synthetic source renders pairs on the fly at 3:4 of
the training side; above it (rendering a 420x560 pair takes seconds, far more than reading one), the
synthetic pairs are rendered at 84x112, upsampled to 3:4 of the side with consistent labels and
written once in the pairs_folder format under --cache_dir, so the figure covers PNG/.flo/npz decoding
plus augmentation at that size, as for a real dataset read from disk.

""samples" are pairs as the train step sees them (both directions when symmetrized). "host CPU
ms/row" (workers=0 only, read synchronously) is the process CPU time per such row: what sizing
the grain workers of a host needs. Prints figures, asserts nothing about timings; the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from ufm_jax.data import mixture, pipeline


def _upsampled_pairs(cache_dir, side, n):
  """n synthetic pairs upsampled to (3/4 side, side), written as a pairs_folder tree (cached)."""
  import cv2  # pylint: disable=g-import-not-at-top
  import numpy as np  # pylint: disable=g-import-not-at-top
  from ufm_jax.data import get_source, synthetic  # pylint: disable=g-import-not-at-top
  h, w = 3 * side // 4, side
  root = os.path.join(cache_dir, f"synthetic_pairs_{h}x{w}_{n}")
  if os.path.isdir(root) and len([d for d in os.listdir(root) if not d.startswith(".")]) >= n:
    return root
  src = get_source("synthetic", None, split="train", num_pairs=n, size=(84, 112))
  sy, sx = h / 84, w / 112

  def up(sample):
    out = {k: cv2.resize(sample[k], (w, h), interpolation=cv2.INTER_LINEAR)
           for k in ("image0", "image1")}
    for k in ("covisibility", "flow_valid", "covis_valid"):
      out[k] = cv2.resize(sample[k].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST_EXACT) > 0
    flow = cv2.resize(sample["flow"], (w, h), interpolation=cv2.INTER_LINEAR)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)   # flow of the resized grid (pixel centres)
    x0, y0 = (x + 0.5) / sx - 0.5, (y + 0.5) / sy - 0.5
    flow[..., 0] = (x0 + flow[..., 0] + 0.5) * sx - 0.5 - x
    flow[..., 1] = (y0 + flow[..., 1] + 0.5) * sy - 0.5 - y
    out["flow"] = flow
    meta = dict(sample["meta"])
    for k in ("depth0", "depth1"):
      meta[k] = cv2.resize(meta[k], (w, h), interpolation=cv2.INTER_NEAREST_EXACT)
    for k in ("K0", "K1"):
      kk = np.array(meta[k], np.float64)
      kk[0] *= sx
      kk[1] *= sy
      kk[0, 2] += 0.5 * sx - 0.5
      kk[1, 2] += 0.5 * sy - 0.5
      meta[k] = kk
    meta.pop("segmentation0", None)
    out["meta"] = meta
    return out

  os.makedirs(root, exist_ok=True)
  for i in range(n):
    fwd, bwd = src.both(i)
    synthetic.write_pair(os.path.join(root, f"{i:06d}"), up(fwd), up(bwd))
  return root


def _table1_trees(root, side, native):
  """One-pair trees of the 12 Table 1 datasets in their on-disk formats under root/<name>
  (benchmarks/source_load.py's writers); returns {name: get_source options}."""
  import source_load  # beside this file  # pylint: disable=g-import-not-at-top
  hw = (3 * side // 4, side)
  options = {}
  for name, writer, kwargs, _ in source_load.all_trees(hw, native):
    if name in mixture.QUOTAS:
      writer(os.path.join(root, name))
      options[name] = kwargs
  missing = sorted(set(mixture.QUOTAS) - set(options))
  if missing:
    raise SystemExit(f"--table1: no test-tree writer for {missing}")
  return options


def _input_block(args, longest_side, workers):
  """The input block to measure: --config's, else the synthetic data's."""
  if args.config:
    import importlib.util  # pylint: disable=g-import-not-at-top
    spec = importlib.util.spec_from_file_location("bench_config", args.config)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    block = mod.get_config(args.config_arg).input
    if args.data_root:
      block.data_root = args.data_root
  elif longest_side <= args.render_max_side:
    options = {"size": (3 * longest_side // 4, longest_side), **json.loads(args.source_options)}
    block = pipeline.input_config(mixture.synthetic_mixture(args.quota, **options),
                                symmetrize=args.symmetrize)
  else:
    root = _upsampled_pairs(args.cache_dir, longest_side, args.disk_pairs)
    datasets = {"pairs_folder": {"quota": args.quota, "root": root, "options": {}}}
    block = pipeline.input_config(datasets, symmetrize=args.symmetrize)
  return _measured(block, args, longest_side, workers)


def _measured(block, args, longest_side, workers):
  """`block` with the benchmark's batch, shape, worker and read settings."""
  from ufm_jax.data import augment  # pylint: disable=g-import-not-at-top
  block.batch_size = args.batch_size
  block.longest_side = longest_side
  official = {560: augment.SHAPES_560, 980: augment.SHAPES_980}.get(longest_side)
  # The recipes' shapes at 560 and 980 (input.shapes), else W = longest_side with aspect_ratios.
  block.shapes = official if official and not args.config else block.get("shapes", ())
  block.num_workers = workers
  block.read_threads = args.read_threads
  block.keep_heap = args.keep_heap
  block.augment = {**dict(block.get("augment", {})), **json.loads(args.augment)}
  if not workers:
    # Synchronous: each timed batch is made inside the timed window. With read threads a
    # prefetch buffer fills during the warm-up and the CPU time of those rows goes uncounted.
    block.read_threads = block.prefetch_buffer_size = 0
  return block


def measure(block, num_batches, warmup):
  pipe = pipeline.create(block, seed=0, process_index=0, process_count=1)
  it = iter(pipe)
  try:
    t0 = time.perf_counter()
    for _ in range(warmup):
      next(it)
    t_first = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    pairs = 0
    for _ in range(num_batches):
      pairs += next(it)["image0"].shape[0]
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
  finally:
    if hasattr(it, "close"):
      it.close()
  # With worker processes the work happens in children this process cannot time while they run.
  cpu_ms = 1e3 * cpu / pairs if not block.num_workers else None
  return pairs / dt, num_batches / dt, t_first, cpu_ms


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--longest_side", default="112,560", help="comma list; 112 = the tiny shape")
  p.add_argument("--workers", default="0,2", help="comma list of worker process counts")
  p.add_argument("--batch_size", type=int, default=8, help="pairs per batch (both directions)")
  p.add_argument("--batches", type=int, default=10, help="timed batches per setting")
  p.add_argument("--warmup", type=int, default=2, help="untimed batches (worker start-up)")
  p.add_argument("--read_threads", type=int, default=1)
  p.add_argument("--no_symmetrize", dest="symmetrize", action="store_false")
  p.add_argument("--no_keep_heap", dest="keep_heap", action="store_false",
                 help="input.keep_heap=False: glibc's default malloc trimming (what it saves)")
  p.add_argument("--quota", type=int, default=1000, help="pairs per epoch")
  p.add_argument("--source_options", default="{}", help="JSON options of the synthetic source")
  p.add_argument("--render_max_side", type=int, default=224,
                  help="largest side rendered on the fly; larger ones read upsampled pairs from disk")
  p.add_argument("--disk_pairs", type=int, default=32, help="pairs written for the disk mixture")
  p.add_argument("--cache_dir", default="/tmp/ufm_bench_data")
  p.add_argument("--config", default=None, help="a training config file: benchmark its mixture")
  p.add_argument("--config_arg", default=None)
  p.add_argument("--data_root", default=None)
  p.add_argument("--per_dataset", action="store_true",
                 help="also print every reader's CPU ms per sample on 560-shape test trees "
                      "(benchmarks/source_load.py)")
  p.add_argument("--table1", action="store_true",
                 help="host CPU ms/row of each Table 1 dataset read from a one-pair tree in its "
                      "real on-disk format (workers=0), and their mean weighted by the epoch quotas")
  p.add_argument("--native", action="store_true",
                 help="with --table1: the flow datasets' trees at their native frame sizes")
  p.add_argument("--layouts", default="raw,official",
                 help="with --table1: which on-disk layouts to measure (raw: the datasets' own "
                      "releases; official: the official processed layouts, weighted by the "
                      "official 560 recipe's samples per epoch)")
  p.add_argument("--augment", default="{}",
                 help="JSON of input.augment keys (ufm_jax.data.augment.AugmentConfig), e.g. "
                      "'{\"fast_image_ops\": true}' (OpenCV's image operations, a deviation)")
  args = p.parse_args(argv)
  if args.table1:
    return table1(args)
  if args.per_dataset:
    import source_load  # beside this file
    print("CPU ms per sample, single thread, 420x560 test trees (budget < 50 ms)")
    source_load.measure((420, 560))
  print(f"{'longest':>7} {'workers':>7} {'batch':>5} {'pairs/s':>9} {'batches/s':>9} "
        f"{'startup+warmup s':>16} {'host CPU ms/row':>15}")
  rows = []
  for side in (int(s) for s in args.longest_side.split(",")):
    for workers in (int(w) for w in args.workers.split(",")):
      block = _input_block(args, side, workers)
      sps, bps, t_first, cpu_ms = measure(block, args.batches, args.warmup)
      cpu = f"{cpu_ms:>15.1f}" if cpu_ms is not None else f"{'(workers)':>15}"
      print(f"{side:>7} {workers:>7} {args.batch_size:>5} {sps:>9.1f} {bps:>9.2f} {t_first:>16.1f} "
            f"{cpu}", flush=True)
      rows.append({"longest_side": side, "workers": workers, "batch_size": args.batch_size,
                   "pairs_per_s": round(sps, 2), "host_cpu_ms_per_row": cpu_ms and round(cpu_ms, 2)})
  print("host CPU ms/row: process CPU time per training row with workers=0 (all decoding, labels "
        "and augmentation in this process); a host feeding R rows/s needs about R x ms / 1000 cores")
  print(json.dumps({"load_avg_1m": round(os.getloadavg()[0], 2), "settings": rows}))


def table1(args):
  """Per-dataset host CPU ms/row through the whole pipeline (reader, backward labels, checks,
  augmentation, batching) and the quota-weighted mean: raw layouts weighted by Table 1, the
  official processed layouts by the official 560 recipe."""
  import tempfile  # pylint: disable=g-import-not-at-top
  import cv2  # pylint: disable=g-import-not-at-top
  cv2.setNumThreads(1)  # a grain worker's share of the host: one core
  side = int(args.longest_side.split(",")[-1])
  layouts = args.layouts.split(",")
  print(f"host CPU ms per training row, workers=0, longest side {side}, batch {args.batch_size}, "
        f"{'symmetrized' if args.symmetrize else 'one direction'}; one-pair trees at "
        f"{3 * side // 4}x{side}{' (flow sets at native sizes)' if args.native else ''}")
  out = {"load_avg_1m": None, "longest_side": side, "native": args.native,
         "augment": json.loads(args.augment)}
  if "raw" in layouts:
    with tempfile.TemporaryDirectory() as root:
      options = _table1_trees(root, side, args.native)
      rows, mean = _table1_rows(args, side, root, mixture.QUOTAS, options, "raw, Table 1")
    out.update(ms_per_row=rows, table1_mean_ms_per_row=mean)
  if "official" in layouts:
    from ufm_jax.testing import official_trees  # pylint: disable=g-import-not-at-top
    quotas = {n: q for n, (q, _) in mixture.RECIPES["ufm560"].items()}
    with tempfile.TemporaryDirectory() as root:
      official_trees.write_official_root(root, (3 * side // 4, side),
                                         official_trees.NATIVE if args.native else None)
      rows, mean = _table1_rows(args, side, root, quotas, {}, "official, ufm560 recipe")
    out.update(official_ms_per_row=rows, official_mean_ms_per_row=mean)
  out["load_avg_1m"] = round(os.getloadavg()[0], 2)
  print(json.dumps(out))
  return out


def _table1_rows(args, side, root, quotas, options, what):
  print(f"  [{what}]")
  rows = {}
  for name in quotas:
    block = _measured(pipeline.input_config(
        mixture.mixture([name], quotas, options={name: options.get(name, {})}),
        symmetrize=args.symmetrize, data_root=root), args, side, 0)
    _, _, _, cpu_ms = measure(block, args.batches, args.warmup)
    rows[name] = cpu_ms
    print(f"  {name:14s} {quotas[name]:>8d} pairs/epoch {cpu_ms:8.1f} ms/row", flush=True)
  total = sum(quotas.values())
  mean = sum(quotas[n] * ms for n, ms in rows.items()) / total
  print(f"  {'mean':14s} {total:>8d} pairs/epoch {mean:8.1f} ms/row (weighted by quota)")
  return rows, mean


if __name__ == "__main__":
  main()
