"""Accelerator slices by their Cloud names (`v5e-8`, `v5p-128`, ...) and the chips they are made of:
what JAX needs to compile for a TPU slice on a machine without one, and each chip's memory and
peak speed, for planning a run before renting it (benchmarks/train_step.py --topology).

  from ufm_jax.planning import topologies
  devices = topologies.devices("v5e-8")     # 8 abstract TPU v5e devices (needs libtpu)
  mesh = sharding.make_mesh("data:1,fsdp:-1", devices)

The slice layouts follow MaxText's `accelerator_to_spec_map.py` (topology name, wrap-around links);
the v5e/v6e hosts follow the Cloud TPU VM shapes (below). A slice name counts chips for v5e/v6e
and TensorCores for v4/v5p (two per chip, compiled as one "megacore" device), so v5p-8 is 4
chips.

Compiling for a slice needs libtpu (`pip install "ufm_jax[tpu]"`), never a TPU: jax's
`jax.experimental.topologies.get_topology_desc` describes the slice and XLA:TPU compiles for it.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import os

GIB = 2 ** 30


@dataclasses.dataclass(frozen=True)
class Chip:
  device_kind: str         # jax's Device.device_kind
  hbm_bytes: int           # memory one device may use
  peak_bf16_flops: float   # dense bf16 FLOP/s (vendor datasheet, no sparsity)
  host_vcpus_per_chip: float | None = None   # the host VM's vCPUs over its chips (None: unknown)


# TPU HBM: the limit XLA:TPU compiles against (libtpu 0.0.42 names it when a program does not
# fit: "exceeds available HBM (15.75G)"), a little under the datasheet's 16/32/95 GB.
# GPU HBM: the datasheet's. Peaks: Cloud TPU and NVIDIA datasheets.
# Host vCPUs (what feeds the chips, ufm_jax.planning.planner): Cloud TPU's VM tables, v5e 112 per 4-chip
# VM (ct5lp-hightpu-4t; 224 per 8-chip VM), v5p 208 per 4-chip VM (half of them within one NUMA
# node); Google Cloud's a3-highgpu-8g, 208 for 8 H100s.
CHIPS = {
    "v4": Chip("TPU v4", int(30.75 * GIB), 275e12),
    "v5e": Chip("TPU v5 lite", int(15.75 * GIB), 197e12, 28),
    "v5p": Chip("TPU v5", int(95.74 * GIB), 459e12, 52),
    "v6e": Chip("TPU v6 lite", int(31.25 * GIB), 918e12),
    "h100": Chip("NVIDIA H100", 80 * 10 ** 9, 989e12, 26),
    "h200": Chip("NVIDIA H200", 141 * 10 ** 9, 989e12),
    "a100": Chip("NVIDIA A100", 80 * 10 ** 9, 312e12),
    "l4": Chip("NVIDIA L4", 24 * 10 ** 9, 121e12),
    "a10": Chip("NVIDIA A10", 24 * 10 ** 9, 125e12),
}


@dataclasses.dataclass(frozen=True)
class Slice:
  name: str                # Cloud accelerator type, e.g. "v5e-8"; GPU nodes: "h100-8"
  chip: str                # key of CHIPS
  topology: str = ""       # libtpu's topology name, e.g. "v5e:2x4" ("" for GPU nodes)
  chip_config: str = ""    # "default" (a device per chip) or "megacore" (v4/v5p)
  host_bounds: tuple = ()  # chips per host along each axis
  wrap: tuple = ()         # wrap-around links along each axis (a full torus)

  @property
  def chips(self) -> int:
    if not self.topology:
      return int(self.name.split("-")[1])
    return math.prod(int(d) for d in self.topology.split(":")[1].split("x"))

  @property
  def hosts(self) -> int:
    """Hosts (VMs, or GKE nodes) of the slice: its chips over the chips per host."""
    per_host = math.prod(self.host_bounds) if self.host_bounds else self.chips
    return max(1, self.chips // per_host)

  @property
  def accelerator_type(self) -> str:
    """The name a TPU VM of this slice reports (TPU_ACCELERATOR_TYPE)."""
    gen, n = self.name.split("-")[:2]
    return f"v5litepod-{n}" if gen == "v5e" else f"{gen}-{n}"


# Chips per host of the v5e and v6e slices as Cloud TPU VMs (cloud.google.com/tpu/docs/v5e and
# .../v6e, their system architecture tables): a slice of 1, 4 or 8 chips is one VM holding all
# of them (v5e: ct5lp-hightpu-1t, -4t, -8t, with 24, 112 and 224 vCPUs; v6e: ct6e-standard-1t,
# -4t, -8t); a slice of 16 chips or more is multi-host, 4 chips per VM. GKE runs the same slices
# on node pools of those machine types; on 4-chip nodes (ct5lp-hightpu-4t) a 2x4 slice is two
# nodes: the named option "v5e-8-gke4" (launch/kubernetes/jobset-tpu.yaml's example).
_HOST_BOUNDS_2D = {1: (1, 1, 1), 4: (2, 2, 1), 8: (2, 4, 1)}
FOUR_CHIP_HOSTS = (2, 2, 1)


def _slices():
  out = {}
  # v5e, v6e: 2-D; 16x8 and 16x16 close the torus.
  shapes_2d = {1: "1x1", 4: "2x2", 8: "2x4", 16: "4x4", 32: "4x8", 64: "8x8", 128: "8x16",
               256: "16x16"}
  wraps_2d = {128: (False, True, False), 256: (True, True, False)}
  for gen, prefix in (("v5e", "v5e"), ("v6e", "v6e")):
    for n, shape in shapes_2d.items():
      out[f"{gen}-{n}"] = Slice(f"{gen}-{n}", gen, f"{prefix}:{shape}", "default",
                                _HOST_BOUNDS_2D.get(n, FOUR_CHIP_HOSTS),
                                wraps_2d.get(n, (False, False, False)))
    out[f"{gen}-8-gke4"] = dataclasses.replace(out[f"{gen}-8"], name=f"{gen}-8-gke4",
                                               host_bounds=FOUR_CHIP_HOSTS)
  # v4, v5p: 3-D, named by TensorCores (2 per chip); a full 4x4x4 cube and up wrap around.
  shapes_3d = {4: "2x2x1", 8: "2x2x2", 16: "2x2x4", 32: "2x4x4", 64: "4x4x4", 128: "4x4x8",
               256: "4x8x8", 512: "8x8x8"}
  for gen, prefix in (("v4", "v4"), ("v5p", "v5")):
    for chips, shape in shapes_3d.items():
      name = f"{gen}-{2 * chips}"
      out[name] = Slice(name, gen, f"{prefix}:{shape}", "megacore", (2, 2, 1),
                        (True,) * 3 if chips >= 64 else (False,) * 3)
  # GPU nodes of 8: nothing to compile for without the GPUs, but their step time can be estimated.
  for gpu in ("h100", "h200", "a100"):
    out[f"{gpu}-8"] = Slice(f"{gpu}-8", gpu)
  return out


SLICES = _slices()


def get(name: str) -> Slice:
  try:
    return SLICES[name]
  except KeyError:
    raise KeyError(f"unknown slice {name!r}; known: {', '.join(SLICES)}") from None


def chip_of(device_kind: str) -> Chip | None:
  """The CHIPS entry of a jax device kind: exact for TPUs ("TPU v5" is not "TPU v5 lite"), by
  model name for GPUs ("NVIDIA H100 80GB HBM3" -> H100)."""
  for chip in CHIPS.values():
    if chip.device_kind == device_kind:
      return chip
  for chip in CHIPS.values():
    if chip.device_kind.startswith("NVIDIA") and chip.device_kind.lower() in device_kind.lower():
      return chip
  return None


def has_libtpu() -> bool:
  return importlib.util.find_spec("libtpu") is not None


def devices(name: str, num_slices: int = 1):
  """The abstract devices of slice `name` (`num_slices` of them joined by the data-center
  network), to build a mesh on and compile for; nothing runs on them."""
  s = get(name)
  if not s.topology:
    raise ValueError(f"{name} is a GPU node: XLA compiles for GPUs only on the GPUs themselves")
  if not has_libtpu():
    raise RuntimeError(f"compiling for {name} needs libtpu: pip install 'ufm_jax[tpu]' "
                       "(no TPU needed)")
  # Off a TPU VM libtpu looks for the VM's metadata and logs errors when there is none: say
  # what a VM of this slice would.
  os.environ.setdefault("TPU_SKIP_MDS_QUERY", "1")
  os.environ.setdefault("TPU_WORKER_HOSTNAMES", "localhost")
  os.environ.setdefault("TPU_ACCELERATOR_TYPE", s.accelerator_type)
  # libtpu locks the host's TPUs for one process; compiling opens none, so several may plan.
  os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")
  from jax.experimental import topologies  # pylint: disable=g-import-not-at-top
  desc = topologies.get_topology_desc(
      platform="tpu", topology_name=s.topology, chip_config_name=s.chip_config,
      chips_per_host_bounds=s.host_bounds, num_slices=num_slices, wrap=s.wrap)
  return desc.devices


def fit_search(probe, start: int, quantum: int, capacity: int, max_probes: int):
  """The largest per-chip batch (a multiple of `quantum`) whose step fits in `capacity` bytes of
  HBM, by compiling: `probe(b)` compiles at per-chip batch b and returns {"fits": bool,
  "hbm_bytes_per_chip": int (when it compiled), "argument_bytes_per_device": int (optional)}.
  HBM is close to affine in the batch, so each next probe is the batch the compiled probes predict:
  the two largest, or a single one whose argument bytes (the train state) stand in for the
  intercept (too low an intercept overstates the cost of a row, so that prediction errs towards
  the compiled batch); without a prediction the batch doubles while it fits and halves while it
  does not.
  Returns (largest batch found to fit, 0 if none; smallest found not to, None if every probe fit;
  {batch: probe result}): the answer is exact when the two differ by `quantum`, else
  `max_probes` ran out first."""
  results = {}

  def fits(b):
    if b not in results:
      results[b] = probe(b)
    return results[b]["fits"]

  def predicted():
    known = sorted(k for k, v in results.items() if v.get("hbm_bytes_per_chip"))[-2:]
    if len(known) == 2:
      (b1, b2), (m1, m2) = known, [results[k]["hbm_bytes_per_chip"] for k in known]
    elif len(known) == 1 and results[known[0]].get("argument_bytes_per_device"):
      b1, b2 = 0, known[0]
      m1, m2 = results[b2]["argument_bytes_per_device"], results[b2]["hbm_bytes_per_chip"]
    else:
      return None
    if m2 <= m1:
      return None
    return int(b2 + (capacity - m2) * (b2 - b1) / (m2 - m1)) // quantum * quantum

  lo, hi, b = 0, None, start   # largest batch known to fit, smallest known not to
  while lo == 0 or hi is None:
    if len(results) >= max_probes:
      return lo, hi, results
    if fits(b):
      lo = b
      b, guess = 2 * b, predicted()
      if guess is not None:   # up, past the batch that fit; a compile at most 16x as large
        b = min(max(guess, lo + quantum), 16 * lo)
    else:
      hi = b
      if lo == 0:
        if b <= quantum:
          return 0, hi, results
        b, guess = max(quantum, b // 2 // quantum * quantum), predicted()
        if guess is not None:   # down, below the batch that failed
          b = max(min(guess, hi - quantum), quantum)
  while hi - lo > quantum and len(results) < max_probes:
    guess = predicted()
    guess = (lo + hi) // 2 if guess is None else guess
    guess = min(max(guess // quantum * quantum, lo + quantum), hi - quantum)
    if fits(guess):
      lo = guess
    else:
      hi = guess
  return lo, hi, results
