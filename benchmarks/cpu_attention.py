"""The CPU attention path (layers.cpu_attention) at UFM-Base's 420x560 shapes, and its parts.

  python benchmarks/cpu_attention.py                    # tile sweep + per-head dot / softmax times
  python benchmarks/cpu_attention.py --tiles 2,4,8      # logits tiles in MiB
  taskset -c 0 python benchmarks/cpu_attention.py       # the same on one core

Tile sweep: the whole attention core (no projections) of the encoder ([2, 1201, 16, 64]: two
images, cls + 30x40 patches, 16 heads) and of the fusion transformer ([1, 2400, 12, 64]) for each
logits tile size; GFLOP/s counts q.k and p.v. Parts: one head and query chunk at the default tile
(the encoder's [2, 401, 64] x [2, 1201, 64]), its two dots and the softmax pieces alone.
Minimum over --runs; prints figures, asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.models import layers


def _best_ms(fn, *args, runs):
  compiled = jax.jit(fn).lower(*args).compile()
  jax.block_until_ready(compiled(*args))
  times = []
  for _ in range(runs):
    t = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    times.append(time.perf_counter() - t)
  return 1e3 * min(times)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--tiles", default="0.25,0.5,1,2,4,8", help="logits tile sizes in MiB")
  p.add_argument("--runs", type=int, default=7)
  args = p.parse_args(argv)
  rng = np.random.default_rng(0)
  normal = lambda *s: jnp.asarray(rng.standard_normal(s), jnp.float32)  # noqa: E731
  print(f"load average {os.getloadavg()[0]:.2f}, {len(os.sched_getaffinity(0))} usable cores; "
        f"default tile {layers.CPU_ATTENTION_TILE / 2**20:g} MiB")
  for shape in ((2, 1201, 16, 64), (1, 2400, 12, 64)):
    b, n, h, d = shape
    q, k, v = normal(*shape), normal(*shape), normal(*shape)
    for mib in (float(t) for t in args.tiles.split(",")):
      ms = _best_ms(lambda q, k, v, t=int(mib * 2**20): layers.cpu_attention(q, k, v, d ** -0.5, tile=t),
                    q, k, v, runs=args.runs)
      print(f"  {str(shape):18s} tile {mib:5g} MiB  {ms:7.1f} ms  "
            f"{4 * b * n * n * h * d / ms / 1e6:6.0f} GFLOP/s", flush=True)
  s, qc, kh = normal(2, 401, 1201), normal(2, 401, 64), normal(2, 1201, 64)
  parts = {
      "q.k dot [2,401,64]x[2,1201,64]": (lambda q, k: jnp.einsum("bqd,bkd->bqk", q, k), qc, kh),
      "p.v dot [2,401,1201]x[2,1201,64]": (lambda p, v: jnp.einsum("bqk,bkd->bqd", p, v), s, kh),
      "row max": (lambda s: jnp.max(s, -1, keepdims=True), s),
      "exp(s - max)": (lambda s: jnp.exp(s - jnp.max(s, -1, keepdims=True)), s),
      "exp(s - max) and its row sum": (
          lambda s: (lambda e: (e, e.sum(-1)))(jnp.exp(s - jnp.max(s, -1, keepdims=True))), s),
  }
  print("  one encoder head and query chunk at the default tile:")
  for label, (fn, *a) in parts.items():
    print(f"    {label:34s} {_best_ms(fn, *a, runs=3 * args.runs):6.2f} ms", flush=True)


if __name__ == "__main__":
  main()
