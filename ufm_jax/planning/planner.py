"""Planning a training run before renting it: the step a run would compile, compiled without data.

`setup` builds what train.py builds from a config (the mesh from config.mesh, the shardings,
grad_accum, the jitted step: `trainer.setup`) with every input the data would give taken from
the config instead: the image size is the largest of the recipe's training shapes (the most
memory), the epoch is the sum of the quotas, the dataset order is the config's. `plan` compiles
that step at a global batch, on the devices at hand or on the abstract devices of a TPU slice
(`ufm_jax.planning.topologies`, through libtpu: no TPU needed), and returns the figures a team needs
before renting: HBM per chip against the chip's, the collectives per step, the FLOPs of the
whole step (`ufm_jax.planning.flops`), the step time at an assumed MFU, the days of the recipe's epochs,
and the host CPU that feeding the chips at that speed takes. `fit` searches the largest per-chip
batch that fits and the plan that trains the recipe's own batch.

`python train.py --config=... --compile_only [--topology NAME]` and
`python benchmarks/train_step.py --topology NAME [--fit]` both run `plan` (docs/scale.md).

Planning inputs that are assumptions, not compiler output (each a flag of the planner):
- `MFU`: the model FLOPs utilisation the step time assumes: a goal, not a prediction (no train
  step of this code has been timed on an accelerator, docs/gpu.md). Every plan prints beside it
  the MFU that the one training run of known length implies (`paper_run`: the paper's 560 run,
  "4 days on 8 H100 GPUs", by our FLOP count), and `mfu="calibrated"` plans at that one.

Measured by the plan command, not here: the host CPU milliseconds per training row, a `host_feed`
dict the callers pass in (`ufm_jax.testing.host_feed.for_plan`: a short run of the recipe's own
input pipeline on this host, or `--host_ms_per_row`), carried into the plan's JSON with the load
average it was measured under. None: no host feed figure.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import os
import pathlib
import time

MFU = 0.4
# The one training run whose length is known, from the paper (ufm_paper.tex, Training Details):
# the 560 recipe, 48 epochs at 96 rows per step, "The training takes 4 days on 8 H100 GPUs".
PAPER_RUN = {"recipe": "configs/ufm560.py", "epochs": 48, "batch": 96, "days": 4.0,
             "slice": "h100-8"}
REPO = pathlib.Path(__file__).resolve().parents[2]

GIB = 2 ** 30


def gib(n) -> str:
  return f"{n / GIB:.3f} GiB"


# ----------------------------------------------------------------------------- the config's data


def training_shapes(config) -> list:
  """The (H, W) training shapes of the config's input: the pipeline's rule
  (input_block.training_shapes), or `input.shape` for a config with its own `data_fn`."""
  from ufm_jax.data import input_block
  inp = config.input
  if inp.get("data_fn"):
    if inp.get("shape") is None:
      raise ValueError("config.input has a data_fn and no `shape`: the planner cannot tell the "
                       "training image size")
    return [tuple(int(x) for x in inp.shape)]
  return [tuple(s) for s in input_block.training_shapes(inp)]


def largest_shape(config) -> tuple:
  """The training shape with the most pixels: the one that needs the most memory."""
  return max(training_shapes(config), key=lambda s: s[0] * s[1])


def pairs_per_epoch(config) -> int | None:
  """Batch rows of one epoch as the pipeline counts them (every dataset of the mixture present:
  the sum of the quotas, both directions when symmetrized); None for a `data_fn` config."""
  inp = config.input
  if inp.get("data_fn") or "datasets" not in inp:
    return None
  quotas = sum(int(d.quota) for d in inp.datasets.values() if int(d.quota) > 0)
  return quotas * (2 if inp.get("symmetrize", True) else 1)


def dataset_names(config):
  """The pipeline's dataset order (its dataset_id), every dataset of the mixture present."""
  inp = config.input
  if inp.get("data_fn") or "datasets" not in inp:
    return None
  return tuple(n for n, d in inp.datasets.items() if int(d.quota) > 0)


def quantum(config) -> int:
  """Rows per device come in multiples of this: a symmetrized pair's (a, b), (b, a) rows stay on
  one device, and each of grad_accum microbatches takes whole pairs from every device."""
  from ufm_jax.training import accumulation
  return accumulation.pair_rows(config.get("apply_kwargs")) * int(config.get("grad_accum", 1))


# ----------------------------------------------------------------------------- devices


@dataclasses.dataclass
class Target:
  """What the step is compiled for: devices, the memory one device may use (a chip's HBM, a
  GPU's bytes_limit, host RAM shared by the CPU devices; None: unknown), peak bf16 FLOP/s,
  hosts, the platform whose branch of platform-dependent code runs."""
  name: str
  devices: list | None     # None: a slice only estimated, never compiled for (--time_only)
  chips: int
  device_kind: str
  capacity: int | None
  peak_flops: float | None
  hosts: int
  platform: str
  host_vcpus: int | None = None   # per host (None: unknown)
  capacity_is: str = ""           # what the capacity is, in words ("HBM", "host RAM over 8 ...")


def target(topology: str | None = None, compile: bool = True) -> Target:  # noqa: A002
  """The devices at hand (jax.devices()), or the abstract devices of slice `topology` (a TPU
  slice through libtpu; `compile=False`: only its chips, for an estimate without a compile, GPU
  nodes too)."""
  import jax
  from ufm_jax.planning import topologies
  if topology:
    slc = topologies.get(topology)
    chip = topologies.CHIPS[slc.chip]
    devices = list(topologies.devices(topology)) if compile else None
    per_host = slc.chips // slc.hosts
    vcpus = chip.host_vcpus_per_chip and int(chip.host_vcpus_per_chip * per_host)
    return Target(topology, devices, slc.chips, chip.device_kind, chip.hbm_bytes,
                  chip.peak_bf16_flops, slc.hosts,
                  "tpu" if slc.topology else "gpu", vcpus, "HBM")
  devices = jax.devices()
  chip = topologies.chip_of(devices[0].device_kind)
  return Target(f"{len(devices)} x {devices[0].device_kind}", list(devices), len(devices),
                devices[0].device_kind, device_capacity(devices, chip),
                chip.peak_bf16_flops if chip else None, jax.process_count(), devices[0].platform,
                os.cpu_count(), capacity_source(devices))


def host_ram_bytes() -> int:
  """This host's RAM (MemTotal of /proc/meminfo, else sysconf's pages), or the cgroup's memory
  limit where that is lower (a container)."""
  try:
    with open("/proc/meminfo") as f:
      ram = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemTotal:"))
  except (OSError, StopIteration):
    ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
  for limit in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
    try:
      text = pathlib.Path(limit).read_text().strip()
    except OSError:
      continue
    if text.isdigit():
      ram = min(ram, int(text))
  return ram


def _local_cpus(devices) -> int:
  return sum(1 for d in devices if d.process_index == devices[0].process_index)


def _bytes_limit(device) -> int | None:
  """A device's allocator limit (GPUs state one in memory_stats), None where it states none."""
  try:
    return (device.memory_stats() or {}).get("bytes_limit") or None
  except Exception:  # noqa: BLE001 - a backend without memory statistics
    return None


def device_capacity(devices, chip=None) -> int | None:
  """The memory one of `devices` (this process's) may use: host CPU devices share the host's RAM,
  each an equal part; a GPU its allocator's limit, else its chip's HBM (topologies.CHIPS)."""
  if devices[0].platform == "cpu":
    return host_ram_bytes() // max(_local_cpus(devices), 1)
  limit = _bytes_limit(devices[0])
  return int(limit) if limit else (chip.hbm_bytes if chip else None)


def capacity_source(devices) -> str:
  """`device_capacity`'s source in words."""
  if devices[0].platform == "cpu":
    local = _local_cpus(devices)
    return "host RAM" + (f" over {local} CPU devices" if local > 1 else "")
  return "the allocator's bytes_limit" if _bytes_limit(devices[0]) else "HBM"


# ----------------------------------------------------------------------------- build and compile


def setup(config, devices, image_shape=None):
  """(mesh, trainer.TrainSetup, image shape): train.py's mesh and step for `config` on `devices`,
  at `image_shape` (default: the largest training shape), from the config alone."""
  from ufm_jax.training import sharding, trainer
  mesh = sharding.make_mesh(config.mesh, devices)
  hw = tuple(image_shape or largest_shape(config))
  total_steps, steps_per_epoch = trainer.schedule_steps(config, pairs_per_epoch(config))
  from ufm_jax.training import teacher as teacher_lib
  ts = trainer.setup(config, mesh, hw, total_steps, steps_per_epoch=steps_per_epoch,
                     dataset_names=dataset_names(config),
                     teacher=teacher_lib.from_config(config, mesh))
  return mesh, ts, hw


def _tree_bytes(tree) -> int:
  import jax
  return sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(tree))


def _per_device_bytes(tree, shardings) -> int:
  """Bytes one device holds of `tree` under `shardings` (the largest shard per leaf)."""
  import jax
  total = 0
  for x, s in zip(jax.tree.leaves(tree), jax.tree.leaves(shardings)):
    shape = s.shard_shape(x.shape) if len(x.shape) else ()
    total += math.prod(shape) * x.dtype.itemsize
  return total


def state_bytes(ts) -> dict:
  """Parameter bytes (total, per device) and the train state's per device; a distillation
  step's teacher variables too (a step argument beside the state, sharded by the same rules)."""
  import jax
  out = {"param_count": sum(int(x.size) for x in jax.tree.leaves(ts.abstract_params)),
         "param_bytes": _tree_bytes(ts.abstract_params),
         "param_bytes_per_device": _per_device_bytes(ts.abstract_params, ts.param_sh),
         "opt_state_bytes_per_device": _per_device_bytes(ts.abstract_state.opt_state,
                                                         ts.state_sh.opt_state),
         "state_bytes_per_device": _per_device_bytes(ts.abstract_state, ts.state_sh)}
  if ts.teacher is not None:
    t = ts.teacher
    out.update(teacher=t.source, teacher_resolution=list(t.resolution),
               teacher_param_count=sum(int(x.size) for x in jax.tree.leaves(t.abstract["params"])),
               teacher_bytes_per_device=_per_device_bytes(t.abstract, t.shardings))
  return out


def compile_step(ts, batch: int, image_shape, row_ids: bool = True) -> dict:
  """Compile (never run) the train step at global `batch`: XLA's memory analysis per device
  (HBM = temp + arguments + outputs - aliases), the collectives of the compiled HLO
  (ufm_jax.planning.hlo_stats), compile time. "refused" (and no figures but the error) when XLA:TPU
  refuses the program for want of HBM. "_text" is the compiled HLO."""
  from ufm_jax.planning import hlo_stats
  t0 = time.perf_counter()
  lowered = ts.train_step.lower(ts.sharded_abstract_state(),
                                ts.abstract_batch(batch, image_shape, row_ids=row_ids))
  lower_s = time.perf_counter() - t0
  t0 = time.perf_counter()
  try:
    compiled = lowered.compile()
  except Exception as e:  # noqa: BLE001 - jaxlib's XlaRuntimeError
    if "RESOURCE_EXHAUSTED" not in str(e):
      raise
    return {"refused": str(e).splitlines()[0][:300],
            "compile_s": round(time.perf_counter() - t0, 1), "lower_s": round(lower_s, 1)}
  compile_s = time.perf_counter() - t0
  text = compiled.as_text()
  colls = hlo_stats.collectives(text)
  summ = hlo_stats.summary(colls)
  ma = compiled.memory_analysis()
  return {"hbm_bytes_per_chip": (ma.temp_size_in_bytes + ma.argument_size_in_bytes +
                                 ma.output_size_in_bytes - ma.alias_size_in_bytes),
          "temp_bytes_per_device": ma.temp_size_in_bytes,
          "argument_bytes_per_device": ma.argument_size_in_bytes,
          "output_bytes_per_device": ma.output_size_in_bytes,
          "alias_bytes_per_device": ma.alias_size_in_bytes,
          "compile_s": round(compile_s, 1), "lower_s": round(lower_s, 1),
          "collective_bytes": {k: v["bytes"] for k, v in summ.items()},
          "collective_count": {k: v["count"] for k, v in summ.items()},
          "collective_bytes_total": hlo_stats.total_bytes(colls),
          "collective_link_bytes": {k: v["link_bytes"] for k, v in summ.items()},
          "collective_link_bytes_total": hlo_stats.total_link_bytes(colls), "_summary": summ,
          "_text": text}


def check_batch(config, mesh, batch: int):
  """ValueError naming the sizes unless `batch` splits over the mesh's batch shards (and into
  config.grad_accum microbatches of whole pairs on every device), as train.py refuses it."""
  from ufm_jax.training import accumulation, losses, sharding
  shards = sharding.batch_divisor(mesh)
  if batch % shards:
    raise ValueError(f"global batch {batch} does not split over the mesh's {shards} batch "
                     f"shards (config.mesh={config.mesh!r})")
  accumulation.check_divisible(batch, int(config.get("grad_accum", 1)), shards,
                               accumulation.pair_rows(config.get("apply_kwargs")))
  if config.get("loss"):
    losses.check_groups(batch, int(config.loss.get("groups", 1)),
                        int(config.get("grad_accum", 1)),
                        accumulation.pair_rows(config.get("apply_kwargs")))


# ----------------------------------------------------------------------------- FLOPs and time


def model_flops_per_row(config, shapes, rows: int, platform: str) -> dict:
  """{(H, W): model FLOPs of the whole step per row} at `rows` global rows: the jaxpr count of
  `ufm_jax.planning.flops` (every loop body times its trip count, so grad_accum's K microbatches and the
  scanned blocks all count), remat's recomputation left out (MFU counts model FLOPs)."""
  from ufm_jax.planning import flops
  return {s: flops.model_flops(config, s, rows, platform).flops / rows for s in shapes}


@functools.lru_cache(maxsize=None)
def paper_run(count: str = "analytic") -> dict:
  """The paper's 560 run (PAPER_RUN) by our FLOP count, and the MFU it implies: the recipe's rows
  (its epochs x rows per epoch) in steps of its batch, the model FLOPs of those steps (the mean
  over the recipe's training shapes, as a plan's days take them, at its batch of 96), over 4 days
  of 8 H100s' dense bf16 peak. `count`: "analytic", flops.analytic_step_flops (from the model's
  dimensions: one trainer.setup, seconds), or "jaxpr", flops.model_flops (the count a plan's
  FLOPs are: a trace per shape, minutes each on a 2-core host); the two agree within 0.1%
  (docs/scale.md)."""
  import jax

  from ufm_jax.planning import flops, topologies
  from ufm_jax.training import config_lib, sharding, trainer
  config = config_lib.load_config(str(REPO / PAPER_RUN["recipe"]))
  batch, shapes = PAPER_RUN["batch"], training_shapes(config)
  if count == "jaxpr":
    per_row = model_flops_per_row(config, shapes, batch, "gpu")
  elif count == "analytic":
    mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
    ts = trainer.setup(config, mesh, shapes[0], total_steps=1000)
    per_row = {s: flops.analytic_step_flops(config, ts, s, batch)["total"] / batch
               for s in shapes}
  else:
    raise ValueError(f"count={count!r}: 'analytic' or 'jaxpr'")
  mean_row = sum(per_row[s] for s in shapes) / len(shapes)
  rows = PAPER_RUN["epochs"] * pairs_per_epoch(config)
  steps = math.ceil(rows / batch)
  slc = topologies.get(PAPER_RUN["slice"])
  peak = slc.chips * topologies.CHIPS[slc.chip].peak_bf16_flops
  seconds = PAPER_RUN["days"] * 86400
  return {"mfu": steps * batch * mean_row / (seconds * peak), "mean_flops_per_row": mean_row,
          "rows": rows, "steps": steps, "count": count, **PAPER_RUN}


def mfu_value(mfu) -> float:
  """A planner's --mfu: a fraction, or "calibrated" (the paper's run's, `paper_run`)."""
  if isinstance(mfu, str):
    if mfu.strip().lower() == "calibrated":
      return paper_run()["mfu"]
    try:
      return float(mfu)
    except ValueError:
      raise ValueError(f"--mfu {mfu!r}: a fraction (0.4) or 'calibrated'") from None
  return float(mfu)


def estimate(config, tgt: Target, per_row: dict, hw, batch: int, mfu: float,
             host_ms_per_row: float | None, executed: float | None = None,
             calibrated: float | None = None) -> dict:
  """Step time at `hw` on `tgt` at `mfu` of its bf16 peak, the recipe's days (each step draws
  one of its shapes uniformly: the mean FLOPs over them), and the host CPU that feeding the
  chips at that pace takes (rows per second per host x `host_ms_per_row`). `calibrated`: the
  paper's run's MFU (`paper_run`), whose step time and days go beside the assumed ones."""
  out = {"flops_per_step": per_row[hw] * batch, "flops_per_row": per_row[hw],
         "executed_flops_per_step": executed, "mfu_assumed": mfu, "mfu_calibrated": calibrated}
  if not tgt.peak_flops or not mfu:
    return out
  peak = tgt.chips * tgt.peak_flops
  step_s = per_row[hw] * batch / (peak * mfu)
  shapes = training_shapes(config)
  mean_row = sum(per_row[s] for s in shapes) / len(shapes)
  mean_step_s = mean_row * batch / (peak * mfu)
  out.update(step_s_estimate=step_s, mean_flops_per_row=mean_row, mean_step_s_estimate=mean_step_s)
  if calibrated:
    out["mean_step_s_at_calibrated_mfu"] = mean_step_s * mfu / calibrated
  if config.get("num_epochs") and pairs_per_epoch(config):
    rows = config.num_epochs * pairs_per_epoch(config)
    steps = math.ceil(rows / batch)
    out.update(recipe_rows=rows, recipe_steps=steps, days_estimate=steps * mean_step_s / 86400)
    if calibrated:
      out["days_at_calibrated_mfu"] = out["days_estimate"] * mfu / calibrated
  rows_s_host = batch / mean_step_s / tgt.hosts
  out.update(hosts=tgt.hosts, rows_per_s_per_host=rows_s_host, host_ms_per_row=host_ms_per_row,
             host_vcpus=tgt.host_vcpus)
  if host_ms_per_row:
    out["host_cores_per_host"] = rows_s_host * host_ms_per_row / 1000
    if tgt.host_vcpus:
      out["hosts_feed_chips"] = out["host_cores_per_host"] <= tgt.host_vcpus
  return out


# ----------------------------------------------------------------------------- the plan


def plan(config, tgt: Target, *, batch: int | None = None, image_shape=None, mfu=MFU,
         host_feed: dict | None = None, flops: bool = True, log=print) -> dict:
  """The step of `config` (config.mesh, config.grad_accum) compiled for `tgt` at global `batch`
  (default config.input.batch_size): the planner's JSON-able result. "fits" is False where the
  compiled step needs more memory than a device has (tgt.capacity), or XLA refused it. `mfu`: a
  fraction or "calibrated" (`mfu_value`). With `flops`, the FLOPs, step time, days and host feed
  (of `host_feed`, module docstring) too (`add_estimates`). Keys starting with "_" are not for
  JSON (the HLO text, the collectives' summary)."""
  config = copy.deepcopy(config)
  mesh, ts, hw = setup(config, tgt.devices, image_shape)
  batch = int(batch or config.input.batch_size)
  check_batch(config, mesh, batch)
  from ufm_jax.training import sharding
  shards = sharding.batch_divisor(mesh)
  info = state_bytes(ts)
  log(f"config {config.get('model_name', config.get('model_fn'))}: "
      f"{info['param_count'] / 1e6:.1f}M params, global batch {batch} at {hw[0]}x{hw[1]} "
      f"({batch // shards} rows per chip), mesh {dict(mesh.shape)} ({config.mesh}) on "
      f"{tgt.chips} {tgt.device_kind}, grad_accum {config.grad_accum}, "
      f"dtype {config.model.get('dtype', 'float32')}, remat {config.model.get('remat', False)}, "
      f"scan_blocks {config.model.get('scan_blocks', False)}, fsdp_gather {config.fsdp_gather}")
  log(f"  params {gib(info['param_bytes'])} total, {gib(info['param_bytes_per_device'])} per "
      f"chip; train state {gib(info['state_bytes_per_device'])} per chip", flush=True)
  if "teacher" in info:
    log(f"  teacher {info['teacher']}: {info['teacher_param_count'] / 1e6:.1f}M params, "
        f"{gib(info['teacher_bytes_per_device'])} per chip, its forward in the step at "
        f"{info['teacher_resolution'][0]}x{info['teacher_resolution'][1]}", flush=True)
  r = compile_step(ts, batch, hw, row_ids=not config.input.get("data_fn"))
  fits = "refused" not in r and (tgt.capacity is None or r["hbm_bytes_per_chip"] <= tgt.capacity)
  if tgt.capacity is None and "refused" not in r:
    fits = None   # no capacity known for this device (an unknown GPU): the plan cannot tell
  result = {"target": tgt.name, "chips": tgt.chips, "device_kind": tgt.device_kind,
            "hosts": tgt.hosts, "mesh": dict(mesh.shape), "mesh_config": config.mesh,
            "grad_accum": int(config.grad_accum), "global_batch": batch,
            "per_chip_batch": batch // shards, "image_shape": list(hw),
            "hbm_capacity_bytes": tgt.capacity, "capacity_is": tgt.capacity_is, "fits": fits,
            **info, **r}
  if flops:
    add_estimates(result, config, tgt, ts, mfu, host_feed)
  return result


def add_estimates(result: dict, config, tgt: Target, ts=None, mfu=MFU,
                  host_feed: dict | None = None):
  """Adds to a compiled plan (`plan`) the model FLOPs of its step at every training shape, the
  FLOPs the compiled step executes (remat included: its TrainSetup `ts`, set up again if None),
  `estimate`, and `host_feed` (the measured host ms/row and the load it was measured under)."""
  from ufm_jax.planning import flops
  config = copy.deepcopy(config)
  config.grad_accum = result["grad_accum"]
  hw, batch = tuple(result["image_shape"]), result["global_batch"]
  per_row = model_flops_per_row(config, set(training_shapes(config)) | {hw}, batch, tgt.platform)
  ts = ts or setup(config, tgt.devices, hw)[1]
  executed = flops.step_flops(ts, batch, hw, tgt.platform).flops
  host_ms_per_row = host_feed and host_feed["host_ms_per_row"]
  result.update(estimate(config, tgt, per_row, hw, batch, mfu_value(mfu), host_ms_per_row,
                         executed, paper_run()["mfu"]))
  result["mfu_is"] = "calibrated" if str(mfu).strip().lower() == "calibrated" else "assumed"
  if host_feed:
    result["host_feed"] = dict(host_feed)
  return result


def report(result: dict, log=print):
  """The plan in words (the JSON line follows it)."""
  from ufm_jax.planning import hlo_stats
  r = result
  if "refused" in r:
    log(f"  XLA refused the step: {r['refused']}; compile {r['compile_s']:.0f} s")
  else:
    log(f"  XLA memory per chip: temp {gib(r['temp_bytes_per_device'])}, arguments "
        f"{gib(r['argument_bytes_per_device'])}, outputs {gib(r['output_bytes_per_device'])}, "
        f"aliased {gib(r['alias_bytes_per_device'])}; trace+lower {r['lower_s']:.1f} s, "
        f"compile {r['compile_s']:.1f} s")
    total, link = r["collective_bytes_total"], r["collective_link_bytes_total"]
    per_param = link / max(r["param_bytes"], 1)
    log(f"  collectives per chip per step: {gib(link)} sent over the links under ideal rings "
        f"({per_param:.2f}x the parameter bytes" +
        (f", {per_param / r['grad_accum']:.2f}x per microbatch" if r["grad_accum"] > 1 else "") +
        f"); results {gib(total)}")
    if "_summary" in r:   # a variadic collective's shapes can run to thousands of characters
      log("\n".join(line if len(line) <= 160 else line[:157] + "..."
                     for line in hlo_stats.format_summary(r["_summary"]).splitlines()))
    cap = r["hbm_capacity_bytes"]
    what = r.get("capacity_is") or "HBM"
    log(f"  memory per device: {gib(r['hbm_bytes_per_chip'])}" +
        (f" of {gib(cap)} ({what}; {100 * r['hbm_bytes_per_chip'] / cap:.0f}%)" if cap else
         " (no capacity known for this device)") +
        {True: ": fits", False: ": does not fit", None: ""}[r["fits"]])
  if "flops_per_step" in r:
    ex = r.get("executed_flops_per_step")
    log(f"  model FLOPs per step: {r['flops_per_step'] / 1e12:.4g} TFLOP "
        f"({r['flops_per_row'] / 1e9:.0f} GFLOP per row at {r['image_shape'][0]}x"
        f"{r['image_shape'][1]}, {r['grad_accum']} microbatch(es))" +
        (f"; executed with remat's recomputation {ex / 1e12:.4g} TFLOP" if ex else ""))
  if r.get("mfu_calibrated"):
    calibrated = (f"the paper's 560 run (\"4 days on 8 H100 GPUs\") implies "
                  f"{100 * r['mfu_calibrated']:.1f}% by our FLOP count")
    if r.get("mfu_is") == "calibrated":
      log(f"  MFU {100 * r['mfu_assumed']:.1f}%, calibrated: {calibrated}")
    else:
      log(f"  MFU {100 * r['mfu_assumed']:.0f}% assumed (a goal, not a prediction); {calibrated}")
  if "step_s_estimate" in r:
    log(f"  at {100 * r['mfu_assumed']:.1f}% MFU ({r.get('mfu_is', 'assumed')}): "
        f"{r['step_s_estimate']:.3g} s per step at the largest shape, {r['mean_step_s_estimate']:.3g}"
        f" s on average over the training shapes ({r['mean_flops_per_row'] / 1e9:.0f} GFLOP per "
        f"row)")
    if "days_estimate" in r:
      other = ""
      if r.get("days_at_calibrated_mfu") and r.get("mfu_is") != "calibrated":
        other = (f"; {r['days_at_calibrated_mfu']:.2f} days at the paper's run's "
                 f"{100 * r['mfu_calibrated']:.1f}%")
      log(f"  recipe: {r['recipe_rows']} rows = {r['recipe_steps']} steps of {r['global_batch']}:"
          f" {r['days_estimate']:.2f} days at {100 * r['mfu_assumed']:.1f}% MFU{other}")
    feed = (f"{r['rows_per_s_per_host']:.0f} rows/s per host ({r['hosts']} hosts)")
    if r.get("host_cores_per_host") is not None:
      have = (f"; the hosts have {r['host_vcpus']} vCPUs: they "
              f"{'can' if r['hosts_feed_chips'] else 'can NOT'} feed the chips"
              if "hosts_feed_chips" in r else "; host vCPUs unknown")
      log(f"  host feed: {feed} x {r['host_ms_per_row']} ms/row ({host_feed_source(r)}) = "
          f"{r['host_cores_per_host']:.1f} busy cores per host{have}")
    else:
      why = (r.get("host_feed") or {}).get("source") or "not measured"
      log(f"  host feed: {feed}; no host ms/row ({why}; --host_ms_per_row gives one)")
  else:
    if "flops_per_step" in r:
      log(f"  no step time: no peak FLOP/s known for {r['device_kind']} (plan for an accelerator: "
          "--topology, or benchmarks/train_step.py --time_only)")
    if (r.get("host_feed") or {}).get("host_ms_per_row"):
      log(f"  host feed: {r['host_feed']['host_ms_per_row']} ms/row ({host_feed_source(r)}); no "
          f"step time on this target, so no rows/s to feed")

def host_feed_source(result: dict) -> str:
  """Where a plan's host ms/row comes from, in words: measured here (rows, load average) or
  given."""
  f = result.get("host_feed") or {}
  if f.get("source") == "measured":
    return (f"measured here on {f['rows']} rows of the recipe's pipeline, load average "
            f"{f['load_avg_1m']}")
  return f"given: {f.get('source', '?')}"


def public(result: dict) -> dict:
  return {k: v for k, v in result.items() if not k.startswith("_")}


def to_json(result: dict) -> str:
  return json.dumps(public(result))


# ----------------------------------------------------------------------------- fit


def fit(config, tgt: Target, start_per_chip: int, *, image_shape=None, max_probes: int = 6,
        mfu=MFU, host_feed: dict | None = None, log=print) -> dict:
  """The largest per-chip batch whose step fits `tgt` (one compile per probe,
  topologies.fit_search), then the plan that trains the recipe's own batch
  (config.input.batch_size) with the fewest microbatches (grad_accum, from the config's) whose
  per-chip microbatch is at most the largest that fit, compiled to confirm (the gradient sum
  takes a little more HBM; the next grad_accum is tried where it does not fit, up to 3
  compiles). Where the recipe's batch does not split so, the plan is the largest batch that fit.
  Returns that plan, with FLOPs and estimates, plus "max_per_chip_batch", "search_exact" and
  "probes"."""
  from ufm_jax.planning import topologies
  from ufm_jax.training import sharding
  if tgt.capacity is None:
    raise ValueError(f"{tgt.name}: no memory capacity known for {tgt.device_kind}: nothing to fit")
  mesh = sharding.make_mesh(config.mesh, tgt.devices)
  shards = sharding.batch_divisor(mesh)
  q = quantum(config)
  k0 = int(config.grad_accum)
  probed = {}

  def probe(per_chip):
    r = plan(config, tgt, batch=per_chip * shards, image_shape=image_shape, flops=False,
             log=lambda *a, **k: None)
    probed[per_chip] = r
    state = f"{gib(r['hbm_bytes_per_chip'])} per chip" if "hbm_bytes_per_chip" in r else "refused"
    log(f"  probe {per_chip} rows per chip ({per_chip * shards} global, grad_accum {k0}): "
        f"{state}{'' if r['fits'] else ', does not fit'}, compile {r['compile_s']:.0f} s",
        flush=True)
    return r

  best, fails, _ = topologies.fit_search(probe, start_per_chip, q, tgt.capacity, max_probes)
  exact = fails is not None and fails - best <= q
  listed = ", ".join(f"{b} {'fits' if r['fits'] else 'no'}" for b, r in sorted(probed.items()))
  log(f"  largest per-chip batch that fits at grad_accum {k0}: {best or 'none'}"
      f"{'' if exact else f' or more ({max_probes} probes ran out)'} (probes: {listed})")
  summary = {"max_per_chip_batch": best, "search_exact": exact,
             "probes": {b: {"fits": p["fits"], "hbm_bytes_per_chip": p.get("hbm_bytes_per_chip"),
                            "compile_s": p["compile_s"]} for b, p in sorted(probed.items())}}
  recipe, pair = int(config.input.batch_size), q // k0
  micro = best // k0 if best else 0          # rows per chip per microbatch that fit
  candidates = [k for k in range(k0, recipe // pair + 1)
                if recipe % (shards * k * pair) == 0 and recipe // (shards * k) <= micro]
  result = None
  for k in candidates[:3]:
    if k == k0 and recipe // shards in probed:
      result = probed[recipe // shards]
    else:
      trial = copy.deepcopy(config)
      trial.grad_accum = k
      log(f"  the recipe's batch {recipe} with grad_accum {k} ({recipe // shards // k} rows per "
          f"chip per microbatch): compiling it", flush=True)
      result = plan(trial, tgt, batch=recipe, image_shape=image_shape, flops=False,
                    log=lambda *a, **kw: None)
      log(f"    {gib(result['hbm_bytes_per_chip']) if 'hbm_bytes_per_chip' in result else 'refused'}"
          f"{'' if result['fits'] else ', does not fit'}")
    if result["fits"]:
      break
    result = None
  if result is None:
    log(f"  the recipe's batch {recipe} does not train on {tgt.name} at grad_accum "
        f"{', '.join(map(str, candidates[:3])) or 'any'}: the plan is the largest batch that fit")
    result = probed.get(best) or probed[min(probed)]
  result = dict(result)
  add_estimates(result, config, tgt, None, mfu, host_feed)
  result.update(summary)
  return result


def overrides(result: dict) -> dict:
  """The --config overrides that reproduce a plan: mesh, global batch, grad_accum."""
  return {"mesh": result["mesh_config"], "input.batch_size": result["global_batch"],
          "grad_accum": result["grad_accum"]}


def launch_lines(result: dict, config_spec: str) -> list:
  """train.py, sbatch and JobSet command lines that run the plan (docs/launch.md)."""
  o = overrides(result)
  flags = " ".join(f"--config.{k}={v}" for k, v in o.items())
  hosts = result.get("hosts") or 1
  return [
      f"python train.py --config={config_spec} --workdir=DIR {flags}",
      f"sbatch --nodes={hosts} launch/slurm/train.sbatch {config_spec} DIR {flags}",
      f"export CONFIG={config_spec} HOSTS={hosts} MESH={o['mesh']} "
      f"GLOBAL_BATCH={o['input.batch_size']} GRAD_ACCUM={o['grad_accum']} ...  "
      f"# then envsubst < launch/kubernetes/jobset-*.yaml | kubectl apply -f -"]
