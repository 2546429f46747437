"""TPU planning from a CPU host (ufm_jax.planning.topologies, benchmarks/train_step.py --topology): the
slice table, the batch search, and (where libtpu is installed) the tiny model's step compiled for
a v5e-4."""

import json
import pathlib
import re
import subprocess
import sys

import pytest

from ufm_jax.planning import topologies

REPO = pathlib.Path(__file__).resolve().parents[1]
GIB = 2 ** 30


def test_slice_table():
  for name, s in topologies.SLICES.items():
    gen, n = name.split("-")[:2]
    # v5e/v6e (and GPU nodes) are named by chips, v4/v5p by TensorCores (two per chip).
    assert s.chips * (2 if s.chip_config == "megacore" else 1) == int(n), name
    assert s.chip == gen and s.chip in topologies.CHIPS
  with pytest.raises(ValueError, match="GPU"):
    topologies.devices("h100-8")
  assert topologies.get("v5e-8").topology == "v5e:2x4"
  assert topologies.get("v5p-128").topology == "v5:4x4x4" and topologies.get("v5p-128").chips == 64
  with pytest.raises(KeyError, match="v5e-8"):
    topologies.get("v5e-9")
  assert topologies.chip_of("TPU v5") is topologies.CHIPS["v5p"]
  assert topologies.chip_of("TPU v5 lite") is topologies.CHIPS["v5e"]
  assert topologies.chip_of("NVIDIA H100 80GB HBM3") is topologies.CHIPS["h100"]
  assert topologies.chip_of("cpu") is None


def test_v5e_hosts_follow_the_cloud_tpu_vm_shapes():
  """v5e-1/4/8 are one VM with all their chips (ct5lp-hightpu-1t/4t/8t), multi-host slices 4-chip
  VMs; v5e-8-gke4 is the 2x4 slice on two 4-chip GKE nodes. `--fit`'s sbatch line asks for as
  many nodes as the slice has hosts."""
  from ufm_jax.planning import planner
  hosts = {n: topologies.get(n).hosts for n in
           ("v5e-1", "v5e-4", "v5e-8", "v5e-8-gke4", "v5e-16", "v5e-64", "v5e-256")}
  assert hosts == {"v5e-1": 1, "v5e-4": 1, "v5e-8": 1, "v5e-8-gke4": 2, "v5e-16": 4,
                   "v5e-64": 16, "v5e-256": 64}
  assert topologies.get("v5e-8-gke4").topology == topologies.get("v5e-8").topology
  assert topologies.get("v5e-8-gke4").accelerator_type == "v5litepod-8"
  vm, gke = planner.target("v5e-8", compile=False), planner.target("v5e-8-gke4", compile=False)
  assert (vm.hosts, vm.host_vcpus) == (1, 224) and (gke.hosts, gke.host_vcpus) == (2, 112)
  plan = {"mesh_config": "data:1,fsdp:-1", "global_batch": 96, "grad_accum": 3}
  assert planner.launch_lines({**plan, "hosts": vm.hosts}, "c.py")[1].startswith(
      "sbatch --nodes=1 ")
  assert planner.launch_lines({**plan, "hosts": gke.hosts}, "c.py")[2].startswith(
      "export CONFIG=c.py HOSTS=2 ")


def _affine_probe(base, per_row, capacity, log):
  def probe(b):
    log.append(b)
    m = base + per_row * b
    return {"fits": m <= capacity, "hbm_bytes_per_chip": int(m)}
  return probe


@pytest.mark.parametrize("start", [2, 4, 32])
def test_fit_search_finds_the_largest_batch(start):
  cap = topologies.CHIPS["v5e"].hbm_bytes
  base, per_row = 3.1 * GIB, 1.3 * GIB
  expected = max(b for b in range(2, 200, 2) if base + per_row * b <= cap)
  log = []
  best, fails, probes = topologies.fit_search(_affine_probe(base, per_row, cap, log), start, 2,
                                              cap, max_probes=8)
  assert (best, fails) == (expected, expected + 2)
  assert len(log) == len(set(log)) <= 5       # each batch compiled once, few compiles
  assert set(probes) == set(log)


@pytest.mark.parametrize("start", [24, 8, 1])
def test_fit_search_predicts_from_one_probe_and_the_train_state(start):
  """A compile's argument bytes (the train state) bound the intercept from below: one probe
  predicts the next, so a v5p-like search (2.9 GiB fixed of which 1.3 GiB state, 5 GiB per row)
  needs a few compiles from any start."""
  cap = topologies.CHIPS["v5p"].hbm_bytes
  base, per_row, state = 2.9 * GIB, 5.0 * GIB, 1.3 * GIB
  expected = max(b for b in range(1, 100) if base + per_row * b <= cap)
  log = []
  affine = _affine_probe(base, per_row, cap, log)
  probe = lambda b: {**affine(b), "argument_bytes_per_device": int(state)}
  best, fails, probes = topologies.fit_search(probe, start, 1, cap, max_probes=8)
  assert (best, fails) == (expected, expected + 1)
  assert len(log) == len(set(log)) <= 4, log


def test_fit_search_none_fits_and_probes_run_out():
  cap = 10 * GIB
  best, fails, _ = topologies.fit_search(_affine_probe(11 * GIB, GIB, cap, []), 8, 2, cap, 8)
  assert (best, fails) == (0, 2)
  # Every probe fits: doubling, then the prediction, at most 16x the batch that fit.
  best, fails, probes = topologies.fit_search(_affine_probe(0, 1, cap, []), 2, 2, cap, 3)
  assert (best, fails, sorted(probes)) == (64, None, [2, 4, 64])


def _libtpu_hbm_limit_gib(name):
  """The HBM XLA:TPU compiles against, from its refusal of a program that cannot fit."""
  code = f"""
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from ufm_jax.planning import topologies
devices = topologies.devices({name!r})
s = NamedSharding(Mesh(np.array(devices), ("x",)), P("x"))
f = jax.jit(lambda a: jnp.sin(a) + jnp.cos(a)[::-1], in_shardings=s, out_shardings=s)
try:
  f.lower(jax.ShapeDtypeStruct((len(devices) * 1024, 2 ** 25), jnp.float32, sharding=s)).compile()
except Exception as e:
  print(e)
"""
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       cwd=REPO, env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"})
  m = re.search(r"available HBM \(([\d.]+)G\)", out.stdout + out.stderr)
  assert m, (out.stdout + out.stderr)[-2000:]
  return float(m.group(1))


@pytest.mark.tpu
@pytest.mark.slow
def test_plan_tiny_model_on_v5e_4(tmp_path):
  if not topologies.has_libtpu():
    pytest.skip("libtpu is not installed: pip install 'ufm_jax[tpu]' (in its own virtualenv)")
  assert _libtpu_hbm_limit_gib("v5e-4") == pytest.approx(
      topologies.CHIPS["v5e"].hbm_bytes / GIB, abs=0.006)
  hlo = tmp_path / "step.hlo.txt"
  cmd = [sys.executable, str(REPO / "benchmarks" / "train_step.py"), "--config", "synthetic",
         "--model", "tiny", "--scan", "true", "--remat", "true", "--topology", "v5e-4",
         "--mesh", "data:1,fsdp:-1", "--per_chip_batch", "2", "--size", "56x56",
         "--hlo_out", str(hlo)]
  out = subprocess.run(cmd, capture_output=True, text=True, timeout=1200, cwd=REPO)
  assert out.returncode == 0, out.stderr[-3000:]
  res = json.loads(out.stdout.strip().splitlines()[-1])
  for key in ("chips", "device_kind", "hbm_bytes_per_chip", "hbm_capacity_bytes", "flops_per_step",
              "collective_bytes", "compile_s"):
    assert key in res, key
  assert res["chips"] == 4 and res["device_kind"] == "TPU v5 lite"
  assert res["mesh"] == {"data": 1, "fsdp": 4} and res["global_batch"] == 8
  assert res["hbm_bytes_per_chip"] == (res["temp_bytes_per_device"] +
                                       res["argument_bytes_per_device"] +
                                       res["output_bytes_per_device"] -
                                       res["alias_bytes_per_device"])
  assert 0 < res["hbm_bytes_per_chip"] < res["hbm_capacity_bytes"]
  # Per-layer FSDP on the TPU: weights all-gathered, gradients reduce-scattered, and the whole
  # traffic within the suite's 3x-the-parameters guard.
  assert res["collective_bytes"]["all-gather"] > 0 and res["collective_bytes"]["reduce-scatter"] > 0
  assert sum(res["collective_bytes"].values()) <= 3 * res["param_bytes"]
  scan_loops = re.findall(r"\bwhile\(", hlo.read_text())
  assert scan_loops, "the scanned blocks compiled to no loop"
  # Step time from the FLOP count at the assumed MFU of four v5e chips' peak.
  assert res["executed_flops_per_step"] > res["flops_per_step"] > 0   # remat recomputes
  assert res["step_s_estimate"] == pytest.approx(
      res["flops_per_step"] / (4 * 197e12 * res["mfu_assumed"]))
  # The host feed: the synthetic config's own pipeline timed here, turned into busy cores.
  assert res["host_feed"]["source"] == "measured" and res["host_ms_per_row"] > 0
  assert res["host_cores_per_host"] == pytest.approx(
      res["rows_per_s_per_host"] * res["host_ms_per_row"] / 1000)
