"""The TA-WB geometric sampler over TartanAir V2 environments (supplementary "TA-WB Training &
Testing Dataset"); the algorithm and its filters are documented in
ufm_jax/data/sources/_tawb_sampler.py.

  python data/tawb/sample_pairs.py --tav2 /data/tartanair_v2 --out /data/tawb_own --split test \
      --envs OldScandinavia Sewerage Supermarket DesertGasStation PolarSciFi --pairs_per_env 700

For every trajectory `<Env>/Data_<diff>/P<nnn>` of the chosen environments (all six lcam faces
needed), samples `--pairs_per_env / number of trajectories` pairs split over the angle bins
(equal for 0-30, 30-60, 60-90 degrees, half for 90-120) and writes them in the extracted TA-WB
layout under `<out>/<split>/<Env>/` (read by the `tawb` source), with `pairs_meta.jsonl` holding
each pair's angle, covisibility, SIFT matching error and source poses.

A script, not a module: it imports the installed package (`pip install -e .` at the repository
root) and runs from any directory.
"""

from __future__ import annotations

import argparse
import dataclasses
import os

from ufm_jax import data
from ufm_jax.data.sources import _tawb_sampler as ts


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--tav2", required=True, help="TartanAir V2 root (data/tartanair_v2/README.md)")
  p.add_argument("--out", required=True)
  p.add_argument("--split", default="train")
  p.add_argument("--envs", nargs="*", default=None, help="default: all environments")
  p.add_argument("--pairs_per_env", type=int, default=700)
  p.add_argument("--pose_stride", type=int, default=1, help="use every n-th pose of a trajectory")
  p.add_argument("--seed", type=int, default=0)
  for f in dataclasses.fields(ts.SamplerConfig):
    if f.name != "tau":
      p.add_argument(f"--{f.name}", type=type(f.default), default=f.default)
  p.add_argument("--no_progress", action="store_true")
  args = p.parse_args(argv)
  cfg = ts.SamplerConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(ts.SamplerConfig)
                            if f.name != "tau"})
  src = data.get_source("tartanair_v2", args.tav2, cameras=("lcam_front",))
  trajs = [s for s in src.scenes() if args.envs is None or s.split("/")[0] in args.envs]
  if not trajs:
    raise SystemExit(f"{args.tav2}: no trajectories for environments {args.envs}")
  by_env: dict[str, list[str]] = {}
  for t in trajs:
    by_env.setdefault(t.split("/")[0], []).append(t)
  total = 0
  for e, (env, ts_list) in enumerate(sorted(by_env.items())):
    index = 0
    for k, traj in enumerate(ts_list):
      n = args.pairs_per_env // len(ts_list) + (k < args.pairs_per_env % len(ts_list))
      frames = [int(f.split("/")[1]) for f in src.frames(traj)][::args.pose_stride]
      records, rejected = ts.sample_environment(
          src, traj, frames, os.path.join(args.out, args.split, env), n,
          seed=[args.seed, e, k], cfg=cfg, progress=not args.no_progress,
          start_index=index)
      index += len(records)
      total += len(records)
      print(f"{traj}: {len(records)}/{n} pairs; rejected attempts: {rejected}")
  print(f"wrote {total} pairs under {os.path.join(args.out, args.split)}")
  return total


if __name__ == "__main__":
  main()
