"""Input-pipeline throughput: samples/s and batches/s of the training mixture.

  python benchmarks/data_pipeline.py                       # synthetic mixture, tiny + 560 shapes
  python benchmarks/data_pipeline.py --longest_side 560 --workers 0,2,4 --batch_size 16
  python benchmarks/data_pipeline.py --config configs/ufm560.py --data_root /data/ufm  # real mixture

"samples" are pairs as the train step sees them (both directions when symmetrized). Prints figures,
asserts nothing about timings.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ufm_jax.data import pipeline  # pylint: disable=g-import-not-at-top
from configs import common  # pylint: disable=g-import-not-at-top


def _input_block(args, longest_side, workers):
  if args.config:
    import importlib.util  # pylint: disable=g-import-not-at-top
    spec = importlib.util.spec_from_file_location("bench_config", args.config)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    block = mod.get_config(args.config_arg).input
    if args.data_root:
      block.data_root = args.data_root
  else:
    options = json.loads(args.source_options)
    datasets = {"synthetic": {"quota": args.quota, "root": None, "options": options}}
    block = common.input_config(datasets, symmetrize=args.symmetrize)
  block.batch_size = args.batch_size
  block.longest_side = longest_side
  block.num_workers = workers
  block.read_threads = args.read_threads
  return block


def measure(block, num_batches, warmup):
  pipe = pipeline.create(block, seed=0, process_index=0, process_count=1)
  it = iter(pipe)
  try:
    t0 = time.perf_counter()
    for _ in range(warmup):
      next(it)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    pairs = 0
    for _ in range(num_batches):
      pairs += next(it)["image0"].shape[0]
    dt = time.perf_counter() - t0
  finally:
    if hasattr(it, "close"):
      it.close()
  return pairs / dt, num_batches / dt, t_first


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--longest_side", default="112,560", help="comma list; 112 = the tiny shape")
  p.add_argument("--workers", default="0,2", help="comma list of worker process counts")
  p.add_argument("--batch_size", type=int, default=8, help="pairs per batch (both directions)")
  p.add_argument("--batches", type=int, default=10, help="timed batches per setting")
  p.add_argument("--warmup", type=int, default=2, help="untimed batches (worker start-up)")
  p.add_argument("--read_threads", type=int, default=1)
  p.add_argument("--no_symmetrize", dest="symmetrize", action="store_false")
  p.add_argument("--quota", type=int, default=10_000, help="synthetic pairs per epoch")
  p.add_argument("--source_options", default="{}", help="JSON options of the synthetic source")
  p.add_argument("--config", default=None, help="a training config file: benchmark its mixture")
  p.add_argument("--config_arg", default=None)
  p.add_argument("--data_root", default=None)
  args = p.parse_args(argv)
  print(f"{'longest':>7} {'workers':>7} {'batch':>5} {'pairs/s':>9} {'batches/s':>9} "
        f"{'startup+warmup s':>16}")
  for side in (int(s) for s in args.longest_side.split(",")):
    for workers in (int(w) for w in args.workers.split(",")):
      block = _input_block(args, side, workers)
      sps, bps, t_first = measure(block, args.batches, args.warmup)
      print(f"{side:>7} {workers:>7} {args.batch_size:>5} {sps:>9.1f} {bps:>9.2f} {t_first:>16.1f}",
            flush=True)


if __name__ == "__main__":
  main()
