r"""How XLA:TPU reduces FSDP gradients on a slice: one stage or two (ufm_jax.training.sharding._two_stage).

  python benchmarks/fsdp_reduce.py --topology v5e-8,v5e-64,v5e-128,v5e-256,v5p-128

Compiles (never runs) the train step of a stack of scanned blocks (two bf16 matmuls of
--width x --hidden float32 weights, remat, the weights gathered a layer at a time by
`sharding.layer_gather`, the batch sharded over every chip: FSDP on data:1,fsdp:-1) for each TPU
slice, with the gradients reduced in one stage (straight to the fsdp shard) and in two
(`sharding.TWO_STAGE_MIN_DEVICES`: a shard over fsdp_outer first), and prints the collectives per
chip per step by kind, against the stack's float32 bytes. Per layer an FSDP step gathers the
weights twice in bf16 (forward and remat: 1.0x) and reduce-scatters the gradient (1/chips of its
bf16 bytes); a gradient all-reduced whole adds 0.5x. Seconds per compile; needs libtpu (the
`[tpu]` extra, in its own virtualenv), no TPU. The last line is one JSON object. Prints figures;
asserts nothing. docs/scale.md has the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time


def compile_stack(topology: str, two_stage: bool, width: int, hidden: int, layers: int) -> dict:
  import jax
  import jax.numpy as jnp
  from ufm_jax.planning import hlo_stats, topologies
  from ufm_jax.training import sharding
  mesh = sharding.make_mesh("data:1,fsdp:-1", topologies.devices(topology))
  sharding.TWO_STAGE_MIN_DEVICES = 2 if two_stage else mesh.size + 1
  rules = [(r".*", "fsdp")]
  path = "encoder/blocks"   # a scanned stack's path: its layer axis is never sharded
  shapes = {"w1": (layers, width, hidden), "w2": (layers, hidden, width)}
  param_sh = {k: jax.sharding.NamedSharding(mesh, sharding.spec_for(f"{path}/{k}", s, rules, mesh))
              for k, s in shapes.items()}
  batch_sh = sharding.batch_sharding(mesh)
  gather = sharding.layer_gather(mesh, rules)

  def loss(stack, x):
    layer = gather(path, stack)

    def block(h, w):
      w = layer(w)
      y = jax.nn.gelu(h.astype(jnp.bfloat16) @ w["w1"].astype(jnp.bfloat16))
      return jax.lax.with_sharding_constraint(
          h + (y @ w["w2"].astype(jnp.bfloat16)).astype(jnp.float32), batch_sh), None

    h, _ = jax.lax.scan(jax.checkpoint(block), x, stack)
    return jnp.mean(h ** 2)

  def step(stack, x):
    grads = jax.grad(loss)(stack, x)
    return jax.tree.map(lambda p, g: p - 1e-3 * g, stack, grads)

  abstract = {k: jax.ShapeDtypeStruct(s, jnp.float32, sharding=param_sh[k])
              for k, s in shapes.items()}
  x = jax.ShapeDtypeStruct((2 * mesh.size, 256, width), jnp.float32, sharding=batch_sh)
  t0 = time.perf_counter()
  compiled = jax.jit(step, in_shardings=(param_sh, batch_sh), out_shardings=param_sh).lower(
      abstract, x).compile()
  colls = hlo_stats.collectives(compiled.as_text())
  stack_bytes = sum(4 * layers * width * hidden for _ in shapes)
  summary = hlo_stats.summary(colls)
  return {"topology": topology, "chips": mesh.size, "two_stage": two_stage,
          "compile_s": round(time.perf_counter() - t0, 1), "stack_bytes": stack_bytes,
          "collective_bytes": {k: v["bytes"] for k, v in summary.items()},
          "ratio": round(hlo_stats.total_bytes(colls) / stack_bytes, 3)}


def main():
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  ap.add_argument("--topology", default="v5e-8,v5e-64,v5e-128,v5e-256,v5p-128",
                  help="TPU slices of ufm_jax.planning.topologies, comma-separated")
  ap.add_argument("--width", type=int, default=1024, help="block width (UFM-Base's encoder: 1024)")
  ap.add_argument("--hidden", type=int, default=4096, help="MLP width (UFM-Base's encoder: 4096)")
  ap.add_argument("--layers", type=int, default=4)
  args = ap.parse_args()
  os.environ.setdefault("JAX_PLATFORMS", "cpu")   # the TPU is only compiled for
  rows = []
  for name in args.topology.split(","):
    for two_stage in (False, True):
      r = compile_stack(name, two_stage, args.width, args.hidden, args.layers)
      kinds = ", ".join(f"{k} {v / r['stack_bytes']:.3f}x" for k, v in r["collective_bytes"].items())
      print(f"{name} ({r['chips']} chips), {'two stages' if two_stage else 'one stage '}: "
            f"{r['ratio']:.3f}x the stack's float32 bytes ({kinds}); compile {r['compile_s']} s",
            flush=True)
      rows.append(r)
  print(json.dumps(rows))


if __name__ == "__main__":
  main()
