"""Time of `trainer.random_params` (random init from scratch) with and without XLA's backend
optimisations, per model variant: the figures behind `trainer.init_compiler_options`.

  python benchmarks/init_time.py
  python benchmarks/init_time.py --variants fixture_small,ufm_base,ufm_refine

For each variant: trace, compile and run seconds of `trainer.init_params` compiled with
`trainer._INIT_COMPILER_OPTIONS` (unoptimised) and with XLA's defaults (optimised), and which of
the two `random_params` picks for the variant's parameter count. Figures are printed, never
asserted.
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import jax

from ufm_jax.training import optim, trainer
from ufm_jax.models import variants


def time_init(model, compiler_options: dict) -> dict:
  key = jax.random.PRNGKey(0)
  image_shape = (2 * model.config.encoder.patch_size,) * 2
  t0 = time.perf_counter()
  lowered = jax.jit(functools.partial(trainer.init_params, model, image_shape)).lower(key)
  t1 = time.perf_counter()
  compiled = lowered.compile(compiler_options=compiler_options)
  t2 = time.perf_counter()
  params = jax.block_until_ready(compiled(key))
  t3 = time.perf_counter()
  return {"trace_s": round(t1 - t0, 2), "compile_s": round(t2 - t1, 2), "run_s": round(t3 - t2, 2),
          "total_s": round(t3 - t0, 2),
          "params": optim.count_params(params)["total"]}


def main(argv=None) -> list[dict]:
  ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  ap.add_argument("--variants", default="fixture_small,ufm_base,ufm_refine",
                  help=f"comma-separated names from {sorted(variants.VARIANTS)}")
  args = ap.parse_args(argv)
  rows = []
  for name in args.variants.split(","):
    model = variants.build_model(name)
    res = {"variant": name}
    for label, opts in (("unoptimised", trainer._INIT_COMPILER_OPTIONS), ("optimised", {})):
      res[label] = time_init(model, opts)
    n = res["optimised"]["params"]
    picked = "unoptimised" if trainer.init_compiler_options(n) else "optimised"
    print(f"{name:14s} {n / 1e6:8.1f}M params   "
          + "   ".join(f"{label}: trace {r['trace_s']:.1f} + compile {r['compile_s']:.1f} "
                       f"+ run {r['run_s']:.1f} = {r['total_s']:.1f} s"
                       for label, r in ((k, res[k]) for k in ("unoptimised", "optimised")))
          + f"   random_params uses: {picked}", flush=True)
    rows.append(dict(res, picked=picked))
  print(json.dumps(rows))
  return rows


if __name__ == "__main__":
  main()
