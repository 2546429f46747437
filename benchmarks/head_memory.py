r"""Memory of the DPT heads in float32 (the official choice) vs bfloat16 (`head_dtype`).

  python benchmarks/head_memory.py --config ufm_base --size 420x560 --batch 2 [--compile]

Only the heads change with `head_dtype` (their inputs are float32 either way), so the heads alone
are measured on abstract inputs: the activations the backward pass keeps (JAX saved residuals of
flow + covisibility loss, traced abstractly: nothing is allocated or run) and, with --compile,
XLA's memory analysis of the compiled forward + backward on one device. Per-device batch
`--batch`; at full scale multiply by the pairs each device holds. Prints figures and one JSON
line; asserts nothing.

Measured (CPU, ufm_base, 420x560, 2 pairs): kept for backward 3.11 GiB (f32) -> 1.75 GiB (bf16),
-44% (the ReLU masks are bool either way); XLA:CPU temp 4.98 -> 4.85 GiB only, because XLA:CPU
runs bf16 convolutions in float32 buffers: the compiled figure needs a GPU to mean anything.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp


def head_inputs(cfg, batch: int, hw):
  """Abstract [encoder last, fusion inter 0, inter 1, fusion final] float32 maps."""
  p = cfg.encoder.patch_size
  h, w = hw[0] // p, hw[1] // p
  dims = (cfg.encoder.embed_dim,) + (cfg.info_sharing.dim,) * 3
  return [jax.ShapeDtypeStruct((batch, h, w, c), jnp.float32) for c in dims]


def measure(name: str, head_dtype: str, batch: int, hw, compile_step: bool) -> dict:
  from jax._src.ad_checkpoint import saved_residuals
  from ufm_jax.models import variants
  from ufm_jax.models import ufm
  model = variants.build_model(name, head_dtype=head_dtype)
  params = ufm.param_shapes(model)
  feats = head_inputs(model.config, batch, hw)

  def loss(p, f):
    out = model.apply({"params": p}, f, tuple(hw), method=lambda m, f, hw: m.heads(f, hw))
    return jnp.mean(out["flow"] ** 2) + jnp.mean(out["covisibility_logits"])

  res = saved_residuals(loss, params, feats)
  line = {"head_dtype": head_dtype,
          "saved_bytes": sum(int(a.size) * a.dtype.itemsize for a, why in res
                             if not why.startswith("from the argument"))}
  if compile_step:
    t0 = time.perf_counter()
    ma = jax.jit(jax.value_and_grad(loss)).lower(params, feats).compile().memory_analysis()
    line.update(temp_bytes=ma.temp_size_in_bytes, compile_s=round(time.perf_counter() - t0, 1))
  return line


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  ap.add_argument("--config", default="ufm_base", help="model variant name")
  ap.add_argument("--size", default="420x560", help="HxW (multiples of 14)")
  ap.add_argument("--batch", type=int, default=2, help="pairs per device")
  ap.add_argument("--compile", action="store_true", help="also XLA memory analysis (compiles)")
  args = ap.parse_args(argv)
  hw = tuple(int(x) for x in args.size.lower().split("x"))
  lines = [measure(args.config, d, args.batch, hw, args.compile) for d in ("float32", "bfloat16")]
  gib = lambda n: f"{n / 2**30:.2f} GiB"  # noqa: E731
  print(f"DPT heads of {args.config} at {hw[0]}x{hw[1]}, {args.batch} pairs/device "
        f"({jax.devices()[0].platform})")
  for line in lines:
    extra = (f"; XLA temp {gib(line['temp_bytes'])} (compiled in {line['compile_s']} s)"
             if "temp_bytes" in line else "")
    print(f"  head_dtype={line['head_dtype']:8s} kept for backward {gib(line['saved_bytes'])}{extra}")
  f32, bf16 = lines
  summary = {"config": args.config, "size_hw": list(hw), "pairs_per_device": args.batch,
             "saved_bytes_f32": f32["saved_bytes"], "saved_bytes_bf16": bf16["saved_bytes"],
             "saved_fraction": round(1 - bf16["saved_bytes"] / f32["saved_bytes"], 3)}
  if args.compile:
    summary.update(temp_bytes_f32=f32["temp_bytes"], temp_bytes_bf16=bf16["temp_bytes"])
  print(f"  saved by bf16 heads: {gib(f32['saved_bytes'] - bf16['saved_bytes'])} "
        f"({100 * summary['saved_fraction']:.0f}% of the heads' kept activations)")
  print(json.dumps(summary))
  return summary


if __name__ == "__main__":
  main()
