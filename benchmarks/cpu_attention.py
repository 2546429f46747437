"""The CPU attention path (layers.cpu_attention) at UFM-Base's 420x560 shapes, and its parts;
with --conv, the bf16 convolution path (layers.conv_as_dots) at the heads' and U-Net's shapes.

  python benchmarks/cpu_attention.py                    # tile sweep + per-head dot / softmax times
  python benchmarks/cpu_attention.py --tiles 2,4,8      # logits tiles in Mi logits (x4 bytes)
  taskset -c 0 python benchmarks/cpu_attention.py       # the same on one core
  python benchmarks/cpu_attention.py --compare          # current loop vs the head-major one, interleaved
  python benchmarks/cpu_attention.py --conv --conv_tiles 128,256,512,1024   # tiles in Ki values

Tile sweep: the whole attention core (no projections) of the encoder ([2, 1201, 16, 64]: two
images, cls + 30x40 patches, 16 heads) and of the fusion transformer ([1, 2400, 12, 64]) for each
logits tile size; GFLOP/s counts q.k and p.v. Parts: one head and a 401-query chunk (the
encoder's [2, 401, 64] x [2, 1201, 64]; at the default tile the loop takes all 1201 queries),
its two dots and the softmax pieces alone.
--compare instead times layers.cpu_attention against the head-major formulation it replaced
(q, k, v and the output transposed to [heads, ...] around a lax.map over heads), alternating the
two --runs times on each shape so load from other processes hits both alike.
--conv times, on each 3x3 convolution shape of the DPT heads and the U-Net at 420x560, XLA's
float32 convolution, XLA's bf16 one (compiled as float32 between converts) and conv_as_dots in
bf16 at each --conv_tiles size (values of a step's column matrix), interleaved --runs times.
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


def head_major_attention(q, k, v, scale, tile=layers.CPU_ATTENTION_TILE):
  """The CPU attention loop before it sliced heads in place (for --compare): head-major copies
  of q, k, v, lax.map over heads and query chunks, the output transposed back."""
  b, n, h, d = q.shape
  m = k.shape[1]
  q = q * jnp.asarray(scale, q.dtype)
  chunks = max(1, -(-b * n * m // tile))
  cq = -(-n // chunks)
  pad = chunks * cq - n
  if pad:
    q = jnp.pad(q, ((0, 0), (0, pad), (0, 0), (0, 0)))
  qs = jnp.moveaxis(q.reshape(b, chunks, cq, h, d), (3, 1), (0, 1))  # [h, chunks, b, cq, d]
  ks, vs = jnp.moveaxis(k, 2, 0), jnp.moveaxis(v, 2, 0)  # [h, b, m, d]

  def head(args):
    qh, kh, vh = args

    def chunk(qc):
      s = jnp.einsum("bqd,bkd->bqk", qc, kh, preferred_element_type=jnp.float32)
      p = jnp.exp(s - jnp.max(s, axis=-1, keepdims=True))
      o = jnp.einsum("bqk,bkd->bqd", p.astype(vh.dtype), vh, preferred_element_type=jnp.float32)
      return (o / jnp.sum(p, axis=-1, keepdims=True)).astype(q.dtype)
    return jax.lax.map(chunk, qh)

  o = jax.lax.map(head, (qs, ks, vs))  # [h, chunks, b, cq, d]
  o = jnp.moveaxis(o, (0, 1), (3, 1)).reshape(b, chunks * cq, h, d)
  return o[:, :n] if pad else o


def compare(shapes, normal, runs):
  for shape in shapes:
    b, n, h, d = shape
    q, k, v = normal(*shape), normal(*shape), normal(*shape)
    fns = {
        "head-major": jax.jit(lambda q, k, v: head_major_attention(q, k, v, d ** -0.5)),
        "in place": jax.jit(lambda q, k, v: layers.cpu_attention(q, k, v, d ** -0.5)),
    }
    fns = {name: f.lower(q, k, v).compile() for name, f in fns.items()}
    outs = [jax.block_until_ready(f(q, k, v)) for f in fns.values()]
    times = {name: [] for name in fns}
    for _ in range(runs):
      for name, f in fns.items():
        t = time.perf_counter()
        jax.block_until_ready(f(q, k, v))
        times[name].append(time.perf_counter() - t)
    diff = float(jnp.max(jnp.abs(outs[0] - outs[1])))
    print(f"  {str(shape):18s} max |difference| {diff:.1e}")
    for name, ts in times.items():
      ms = 1e3 * np.array(ts)
      print(f"    {name:10s} min {ms.min():7.1f} ms  median {np.median(ms):7.1f} ms  "
            f"{4 * b * n * n * h * d / ms.min() / 1e6:6.0f} GFLOP/s", flush=True)


# (label, [b, h, w, c_in], c_out) of the 3x3 convolutions that carry the heads' and U-Net's FLOPs.
CONV_SHAPES = (
    ("DPT layer_rn 96->256 @120x160", (1, 120, 160, 96), 256),
    ("DPT residual unit @60x80", (1, 60, 80, 256), 256),
    ("DPT residual unit @120x160", (1, 120, 160, 256), 256),
    ("DPT regression conv1 @240x320", (1, 240, 320, 256), 128),
    ("DPT regression conv2_0 @420x560", (1, 420, 560, 128), 128),
    ("U-Net downs_0 conv_0 (3 ch)", (2, 420, 560, 3), 64),
    ("U-Net downs_0 conv_2", (2, 420, 560, 64), 64),
    ("U-Net ups_7 conv_0", (2, 420, 560, 128), 64),
    ("U-Net downs_1 conv_0 @210x280", (2, 210, 280, 64), 128),
    ("U-Net ups_5 conv_0 @210x280", (2, 210, 280, 256), 128),
    ("U-Net ups_3 conv_0 @105x140", (2, 105, 140, 512), 256),
    ("U-Net downs_3 conv_2 @52x70", (2, 52, 70, 512), 512),
    ("U-Net bottleneck conv_2 @26x35", (2, 26, 35, 1024), 1024),
)


def conv_sweep(tiles, runs, normal, shapes=CONV_SHAPES):
  dn = ("NHWC", "HWIO", "NHWC")
  pad = ((1, 1), (1, 1))
  for label, shape, o in shapes:
    x, k = normal(*shape), normal(3, 3, shape[-1], o) * 0.05
    xb, kb = x.astype(jnp.bfloat16), k.astype(jnp.bfloat16)
    xla = lambda x, k: jax.lax.conv_general_dilated(x, k, (1, 1), pad, dimension_numbers=dn)  # noqa: E731
    fns = {"XLA f32": (xla, x, k), "XLA bf16": (xla, xb, kb)}
    for t in tiles:
      fns[f"dots bf16 {t}Ki"] = (
          lambda x, k, t=t: layers.conv_as_dots(x, k, (1, 1), pad, tile=t * 1024 or 2**62,
                                                dtype=x.dtype), xb, kb)
    compiled = {n: (jax.jit(f).lower(*a).compile(), a) for n, (f, *a) in fns.items()}
    for f, a in compiled.values():
      jax.block_until_ready(f(*a))
    times = {n: [] for n in compiled}
    cpu = {n: [] for n in compiled}
    for _ in range(runs):
      for n, (f, a) in compiled.items():
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(f(*a))
        times[n].append(time.perf_counter() - t0)
        cpu[n].append(time.process_time() - c0)
    gflop = 2 * np.prod(shape) * 9 * o / 1e9
    print(f"  {label} {shape} -> {o}: {gflop:.1f} GFLOP   (load {os.getloadavg()[0]:.1f})")
    for n, ts in times.items():
      # CPU seconds of this process (all threads): steadier than wall time on a busy machine.
      print(f"    {n:22s} min {1e3 * min(ts):8.1f} ms  {gflop / min(ts):6.0f} GFLOP/s   "
            f"CPU min {1e3 * min(cpu[n]):8.1f} ms", flush=True)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument("--tiles", default="0.25,0.5,1,2,4,8",
                 help="logits tile sizes in Mi logits (4 bytes each in float32)")
  p.add_argument("--runs", type=int, default=7)
  p.add_argument("--compare", action="store_true",
                 help="time the current loop against the head-major one it replaced, interleaved")
  p.add_argument("--conv", action="store_true",
                 help="time the bf16 convolution path (layers.conv_as_dots) instead")
  p.add_argument("--conv_tiles", default="256,1024,4096,0",
                 help="conv_as_dots tiles in Ki values of a step's column matrix (0: no loop)")
  p.add_argument("--conv_shapes", default=None,
                 help="indices into CONV_SHAPES to time (default all)")
  args = p.parse_args(argv)
  rng = np.random.default_rng(0)
  normal = lambda *s: jnp.asarray(rng.standard_normal(s), jnp.float32)  # noqa: E731
  print(f"load average {os.getloadavg()[0]:.2f}, {len(os.sched_getaffinity(0))} usable cores; "
        f"default tile {layers.CPU_ATTENTION_TILE / 2**20:g} Mi logits")
  shapes = ((2, 1201, 16, 64), (1, 2400, 12, 64))
  if args.conv:
    shapes = (CONV_SHAPES if args.conv_shapes is None
              else [CONV_SHAPES[int(i)] for i in args.conv_shapes.split(",")])
    return conv_sweep([int(t) for t in args.conv_tiles.split(",")], args.runs, normal, shapes)
  if args.compare:
    return compare(shapes, normal, args.runs)
  for shape in shapes:
    b, n, h, d = shape
    q, k, v = normal(*shape), normal(*shape), normal(*shape)
    for mib in (float(t) for t in args.tiles.split(",")):
      ms = _best_ms(lambda q, k, v, t=int(mib * 2**20): layers.cpu_attention(q, k, v, d ** -0.5, tile=t),
                    q, k, v, runs=args.runs)
      print(f"  {str(shape):18s} tile {mib:5g} Mi  {ms:7.1f} ms  "
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
  print("  one encoder head and a 401-query chunk (the loop at the default tile takes all 1201):")
  for label, (fn, *a) in parts.items():
    print(f"    {label:34s} {_best_ms(fn, *a, runs=3 * args.runs):6.2f} ms", flush=True)


if __name__ == "__main__":
  main()
