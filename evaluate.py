"""Evaluates UFM on the paper's benchmarks and writes results.json.

  python evaluate.py                                    # --bench synthetic on the embedded data
  python evaluate.py --bench sintel --checkpoint DIR --data_root /data
  python evaluate.py --bench all --checkpoint infinity1096/UFM-Base --snapshot --data_root /data
  python evaluate.py --bench all --snapshot UFM-Base/ --data_root /data --out results/
  python evaluate.py --bench eth3d,dtu,tawb --snapshot UFM-Base/ --data_root /data/ufm_benchmarks
  python evaluate.py --bench kitti --checkpoint DIR --data_root /data/kitti2015 \
      --protocol native --resolution native --save_predictions preds/

--protocol (docs/benchmarks.md): `official` (default) reproduces the UFM benchmark branch on the
five benches of the paper's Tables 2 and 3 (sintel, kitti, eth3d, dtu, tawb): its data as the
official download scripts lay it out under --data_root (Sintel/, KITTI/, eth3d_processed/,
dtu_processed/, anymap_data_pairs/, TA-WB/), its pairs, 560x420 crops, labels and masks, the model
at its own inference resolution; compare these numbers with the paper. `native` is ours: the
data/*/ layouts (sintel/, kitti2015/, eth3d/, dtu/, tawb/, scannet1500/), full resolution, any
--resolution. Benches with no official variant (synthetic, the pose benches) always run natively;
results.json records the protocol of each bench.

--checkpoint: a converted checkpoint (`python -m ufm_jax convert`), a training workdir, or an
official snapshot folder; with --snapshot (as every command takes it) an official snapshot, a
folder or a Hugging Face model ID (--revision: branch, tag or commit); `--snapshot X` alone is
`--checkpoint X --snapshot`. results.json records the ID (or the folder's absolute path), the
revision asked for and the Hub commit it resolved to. Without either, the synthetic training
workdir (workdirs/synthetic) is used when present, else a randomly initialised small model (the
numbers are then meaningless, but the whole path runs). --data_root holds one folder per dataset
(see data/*/README.md) or, for a single bench, the dataset folder itself. --resolution (native
protocol only): 560 / 980 (longest side, source aspect kept, sides multiples of 14), `native`
(source size rounded to multiples of 14), or unset (the model config's inference resolution, as
the official predict). Metrics are computed at the resolution of the bench's samples (native:
the dataset's; official: 560x420 for eth3d / dtu / tawb). Runtime = median forward time per pair
after warm-up, excluding I/O, resize and unmap (the mean, the branch's figure, is recorded too).
The synthetic bench renders the task a train.py workdir was trained on (its config.json: pair type,
size, shift) on the test split, at the size that run trained and evaluated at (`native`, unless
--resolution says otherwise: the model config's inference resolution is a size such a model never
saw), so its EPE agrees with the run's held-out eval; it reports `epe_zero`, the EPE of predicting
no motion, beside the model's `epe`: a model that matches is well below it. results.json records
each bench's resolution (`bench_resolutions`) and writes undefined metrics as null.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import sys
import time

from ufm_jax import evaluators
from ufm_jax.runtime import compile_cache
from ufm_jax.data import io
from ufm_jax.evaluators import base, report

DEFAULT_WORKDIR = "workdirs/synthetic"
RANDOM_MODEL = "tiny"  # ufm_jax.models.variants name used when there is no checkpoint at all
def parse_args(argv=None):
  ap = argparse.ArgumentParser(description=__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--bench", default="synthetic",
                  help=f"one of {', '.join(evaluators.BENCHES)}, a comma list, or 'all'")
  ap.add_argument("--checkpoint", default=None, help="converted checkpoint, training workdir or "
                  "snapshot folder; with --snapshot also a Hugging Face model ID")
  ap.add_argument("--snapshot", nargs="?", const=True, default=None,
                  help="the checkpoint is an official snapshot (folder or Hugging Face model "
                  "ID); `--snapshot X` alone: the snapshot X")
  ap.add_argument("--revision", default=None,
                  help="with a Hugging Face model ID: the Hub branch, tag or commit")
  ap.add_argument("--data_root", default=os.environ.get("UFM_DATA"), help="datasets folder ($UFM_DATA)")
  ap.add_argument("--protocol", default="official", choices=evaluators.PROTOCOLS,
                  help="official: the UFM benchmark branch (paper numbers); native: ours")
  ap.add_argument("--resolution", default=None,
                  help="560 | 980 | native (default: model config); native protocol only")
  ap.add_argument("--max_pairs", type=int, default=None, help="evaluate at most N pairs per split")
  ap.add_argument("--save_predictions", default=None,
                  help="write .flo + covisibility PNG (+ flow covariance .npy) per pair, and the "
                  "panels, here (a folder other than --out)")
  ap.add_argument("--num_panels", type=int, default=8, help="panel PNGs for the first N pairs")
  ap.add_argument("--out", default="results", help="results.json goes here; one already there "
                  "is kept, renamed after its date")
  ap.add_argument("--seed", type=int, default=0, help="pose RANSAC/sampling seed")
  ap.add_argument("--no_progress", action="store_true", help="no progress bars (logs, CI)")
  compile_cache.add_argument(ap)
  args = ap.parse_args(argv)
  if args.snapshot is True and not args.checkpoint:
    ap.error("--snapshot without a value needs --checkpoint (a snapshot folder or model ID)")
  if isinstance(args.snapshot, str) and args.checkpoint:
    ap.error("give the snapshot once: --checkpoint X --snapshot, or --snapshot X")
  if args.revision is not None and not args.snapshot:
    ap.error("--revision applies to a Hugging Face model ID: add --snapshot")
  if args.save_predictions and (pathlib.Path(args.save_predictions).resolve()
                                == pathlib.Path(args.out).resolve()):
    ap.error("--save_predictions and --out name the same folder: give the predictions their own")
  if args.resolution is not None and args.resolution != "native":
    try:
      args.resolution = int(args.resolution)
    except ValueError:
      ap.error(f"--resolution must be an integer (560, 980) or 'native', got {args.resolution!r}")
  return args


def model_dir(args) -> str | None:
  """The folder the model comes from under the --checkpoint / --snapshot rules (None: random)."""
  if isinstance(args.snapshot, str):
    return args.snapshot
  if args.checkpoint:
    return args.checkpoint
  return DEFAULT_WORKDIR if os.path.isdir(DEFAULT_WORKDIR) else None


def synthetic_task(path) -> dict:
  """The synthetic pairs a train.py workdir was trained on (pair type, size, shift), so the
  synthetic bench evaluates that task, on its test split; {} for anything else."""
  cfg_file = pathlib.Path(path or "") / "config.json"
  if not path or not cfg_file.is_file():
    return {}
  cfg = json.loads(cfg_file.read_text())
  opts = ((cfg.get("input") or {}).get("datasets") or {}).get("synthetic", {}).get("options")
  if not opts:
    return {}
  return {k: (tuple(v) if isinstance(v, list) else v) for k, v in opts.items()
          if k in ("pair_type", "size", "max_shift")}


def load_model(args):
  """(model, variables, source) following the --checkpoint / --snapshot rules above; source:
  what results.json records of where the model came from ({"checkpoint", "revision",
  "commit"})."""
  from ufm_jax.runtime import model_io
  if args.snapshot:
    name = args.snapshot if isinstance(args.snapshot, str) else args.checkpoint
    return model_io.load_recorded(name, snapshot=True, revision=args.revision)
  if args.checkpoint or os.path.isdir(DEFAULT_WORKDIR):
    return model_io.load_recorded(args.checkpoint or DEFAULT_WORKDIR)
  return (*random_model(), {"checkpoint": f"random-init:{RANDOM_MODEL}"})


def random_model(name: str = None):
  """A randomly initialised small model (no checkpoint on a fresh machine)."""
  from ufm_jax.training import trainer
  from ufm_jax.models import variants
  name = name or RANDOM_MODEL
  print(f"warning: no checkpoint given and no {DEFAULT_WORKDIR}/: evaluating a randomly "
        f"initialised {name!r} model (numbers are meaningless)", file=sys.stderr)
  model = variants.build_model(name)
  return model, {"params": trainer.random_params(model)}


def main(argv=None) -> int:
  args = parse_args(argv)
  compile_cache.enable(args.compile_cache)
  if args.bench == "all":
    names, explicit = list(evaluators.BENCHES), False
  else:
    names, explicit = [b.strip() for b in args.bench.split(",") if b.strip()], True
    unknown = [b for b in names if b not in evaluators.BENCHES]
    if unknown:
      print(f"error: unknown bench {unknown}; known: {', '.join(evaluators.BENCHES)}, all", file=sys.stderr)
      return 2
  benches = {name: evaluators.get_bench(name, args.protocol) for name in names}
  official = [n for n, b in benches.items() if b.protocol == "official"]
  if args.resolution is not None and official:
    print(f"error: --resolution applies to the native protocol only; the official protocol runs "
          f"{', '.join(official)} at the model's own inference resolution (add --protocol native)",
          file=sys.stderr)
    return 2
  # Check data first (cheap), so a missing dataset fails before any model is loaded.
  skipped, sources, resolutions = {}, {}, {}
  for name, bench in benches.items():
    try:
      opts = synthetic_task(model_dir(args)) if name == "synthetic" else {}
      # A synthetic run trains and evaluates at its task's size: score it there.
      resolutions[name] = args.resolution if args.resolution is not None or not opts else "native"
      sources[name] = {s.label: evaluators.open_source(bench, s, args.data_root, **opts)
                       for s in bench.splits}
    except evaluators.MissingDataError as e:
      if explicit:
        print(f"error: {e}", file=sys.stderr)
        return 2
      skipped[name] = str(e)
  if not sources:
    print("error: no bench has data; skipped:\n  " + "\n  ".join(f"{k}: {v}" for k, v in skipped.items()),
          file=sys.stderr)
    return 2

  try:
    model, variables, source = load_model(args)
  except (FileNotFoundError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  writer = base.PredictionWriter(args.save_predictions, args.num_panels) if args.save_predictions else None
  results, counts, runtime, runtime_mean = {}, {}, {}, {}
  t0 = time.time()
  for name, srcs in sources.items():
    runner = base.Runner(model, variables, resolutions[name])
    res, n = evaluators.run_bench(name, runner, args.data_root, args.max_pairs, writer,
                                  progress=not args.no_progress, sources=srcs, seed=args.seed,
                                  protocol=args.protocol)
    results.update(res)
    counts.update(n)
    runtime[name] = runner.ms_per_pair()
    runtime_mean[name] = runner.ms_per_pair(mean=True)
  payload = {
      "bench": args.bench if args.bench == "all" else ",".join(names),
      "benches_run": list(sources), "skipped": skipped,
      "protocol": args.protocol, "bench_protocols": {n: benches[n].protocol for n in sources},
      **source, "resolution": args.resolution if args.resolution is not None else "model",
      "bench_resolutions": {n: resolutions[n] if resolutions[n] is not None else "model"
                            for n in sources},
      "n_pairs": counts, "max_pairs": args.max_pairs,
      "runtime_ms_per_pair": runtime, "runtime_ms_per_pair_mean": runtime_mean,
      "wall_time_s": round(time.time() - t0, 1),
      "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
      "versions": base.summary_versions(),
      "metrics": results,
  }
  out = pathlib.Path(args.out) / "results.json"
  kept = keep_previous(out)
  io.write_json_atomic(out, payload)
  print(f"model: {source['checkpoint']}")
  for name in sources:
    for s in benches[name].splits:
      if s.label in counts:
        split = dict(s.options).get("split")
        print(f"{s.label}: {counts[s.label]} pairs" + (f" of the {split} split" if split else ""))
  print(report.markdown_table(results, list(sources), runtime))
  for name, why in skipped.items():
    print(f"skipped {name}: {why}")
  if kept:
    print(f"kept the previous {out.name} as {kept}")
  print(f"wrote {out}")
  return 0


def keep_previous(out: pathlib.Path) -> pathlib.Path | None:
  """Renames a results.json already at `out` after the date it records (or its file time), so
  that no run replaces another's results; returns the new name (None: there was none)."""
  if not out.is_file():
    return None
  try:
    date = str(json.loads(out.read_text()).get("date") or "")
  except (ValueError, AttributeError):
    date = ""
  stamp = "".join(c for c in date[:19] if c.isalnum()) or time.strftime(
      "%Y%m%dT%H%M%S", time.gmtime(out.stat().st_mtime))
  kept, i = out.with_name(f"results_{stamp}.json"), 1
  while kept.exists():
    i += 1
    kept = out.with_name(f"results_{stamp}_{i}.json")
  out.rename(kept)
  return kept


if __name__ == "__main__":
  sys.exit(main())
