"""The compiled FSDP train step moves weights, not activations (ufm_jax.hlo_stats on the HLO).

A batch-sharded FSDP step gathers each weight for the forward and the backward pass and reduces
its gradient: a few times the parameter bytes per device, whatever the batch. Here activations
are far larger than the parameters, so any activation that crosses devices blows the budget;
and no collective may carry the global batch dimension. Compiled for 8 fake CPU devices by the
step benchmark (which sets the device count before jax starts), never run.
"""

import json
import pathlib
import subprocess
import sys

import pytest

from ufm_jax import hlo_stats

REPO = pathlib.Path(__file__).resolve().parents[1]
BATCH = 48  # 6 rows (3 symmetrized pairs) per device; 48 and 96 are no parameter dimension


@pytest.mark.slow
@pytest.mark.parametrize("mesh", ["data:2,fsdp:4", "data:1,fsdp:8"])
def test_fsdp_step_moves_weights_not_activations(tmp_path, mesh):
  hlo = tmp_path / "step.hlo.txt"
  cmd = [sys.executable, str(REPO / "benchmarks" / "train_step.py"), "--config", "synthetic",
         "--model", "tiny", "--mesh", mesh, "--devices", "8", "--batch", str(BATCH),
         "--size", "56x56", "--aot", "--hlo_out", str(hlo)]
  out = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=REPO)
  assert out.returncode == 0, out.stderr[-3000:]
  res = json.loads(out.stdout.strip().splitlines()[-1])
  params = res["param_bytes"]
  # The premise: activations dwarf the weights (XLA's per-device temp buffer).
  assert res["temp_bytes_per_device"] > 5 * params, res
  total = sum(res["collective_bytes"].values())
  assert total <= 4 * params + 2**20, (
      f"{mesh}: {total / 2**20:.1f} MiB of collectives per device for {params / 2**20:.1f} MiB of "
      f"parameters:\n{out.stdout}")
  colls = hlo_stats.collectives(hlo.read_text())
  assert colls, "an FSDP step without collectives: the parameters are not sharded"
  batch_dims = {BATCH, 2 * BATCH, BATCH // 2}  # rows, encoder rows, unique pairs
  for c in colls:
    for dtype, dims in c.shapes:
      assert not (dims and dims[0] in batch_dims), (
          f"{mesh}: {c.kind} of {dtype}{list(dims)} in {c.computation} carries the global batch")
  assert res["param_bytes_per_device"] < params  # FSDP: weights are split, not replicated


def test_collectives_parser_counts_loop_trips():
  # A hand-written HLO: one all-gather in the entry, one all-reduce in a 12-trip while body.
  text = """
%body (p: (s32[], f32[4,8])) -> (s32[], f32[4,8]) {
  %ar = f32[4,8]{1,0} all-reduce(%x), channel_id=1, to_apply=%add
  ROOT %t = (s32[], f32[4,8]) tuple(%i, %ar)
}

%cond (p: (s32[], f32[4,8])) -> pred[] {
  ROOT %lt = pred[] compare(%a, %b), direction=LT
}

ENTRY %main (a: f32[2,8]) -> f32[4,8] {
  %ag = bf16[16,8]{1,0} all-gather(%a), channel_id=2, dimensions={0}
  %w = (s32[], f32[4,8]) while(%init), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"12"}}
  ROOT %r = f32[4,8] get-tuple-element(%w), index=1
}
"""
  colls = hlo_stats.collectives(text)
  by_kind = {c.kind: c for c in colls}
  assert by_kind["all-gather"].bytes == 16 * 8 * 2 and by_kind["all-gather"].count == 1
  assert by_kind["all-reduce"].bytes == 4 * 8 * 4 and by_kind["all-reduce"].count == 12
  s = hlo_stats.summary(colls)
  assert s["all-reduce"]["bytes"] == 12 * 128 and s["all-gather"]["bytes"] == 256


def test_collectives_parser_reads_xla_tpu_forms():
  # XLA:TPU's while ops carry no known_trip_count (the bound is the condition's constant), its
  # reduce-scatter is a custom fusion around an all-reduce of the full operands, and an
  # asynchronous collective is a start and a done fusion, each calling a copy of the op.
  text = """
%all-reduce-scatter.1 (p0: f32[64,192]) -> f32[64,48] {
  %ar = f32[64,192]{0,1} all-reduce(%p0), channel_id=1, replica_groups={{0,1,2,3}}, to_apply=%add
  ROOT %ds = f32[64,48]{0,1} dynamic-slice(%ar, %z, %o), dynamic_slice_sizes={64,48}
}

%body (p: (s32[], f32[64,48])) -> (s32[], f32[64,48]) {
  %ag = f32[64,192]{1,0:T(8,128)} all-gather(%w), channel_id=2, dimensions={1}
  %rs = f32[64,48]{0,1:T(8,128)S(1)} fusion(%g), kind=kCustom, calls=%all-reduce-scatter.1
  ROOT %t = (s32[], f32[64,48]) tuple(%i, %rs)
}

%cond (p: (s32[], f32[64,48])) -> pred[] {
  %constant.7 = s32[]{:T(128)} constant(24)
  %gte = s32[]{:T(128)} get-tuple-element(%p), index=0
  ROOT %lt = pred[]{:T(512)} compare(%gte, %constant.7), direction=LT
}

%fused_computation.1 (p0: bf16[16,8]) -> (bf16[16,8], bf16[64,8]) {
  %all-gather.5 = bf16[64,8]{1,0} all-gather(%p0), channel_id=5, dimensions={0}
  ROOT %cc = (bf16[16,8], bf16[64,8]) custom-call(%p0, %all-gather.5), custom_call_target="x"
}

%fused_computation.2 (p0: bf16[16,8]) -> bf16[64,8] {
  %all-gather.6 = bf16[64,8]{1,0} all-gather(%p0), channel_id=5, dimensions={0}
  ROOT %cc = bf16[64,8] custom-call(%p0, %all-gather.6), custom_call_target="x"
}

ENTRY %main (a: f32[64,48]) -> f32[64,48] {
  %w = (s32[], f32[64,48]) while(%init), condition=%cond, body=%body
  %async-collective-start.1 = (bf16[16,8], bf16[64,8]) fusion(%b), kind=kCustom, calls=%fused_computation.1
  %async-collective-done.1 = bf16[64,8] fusion(%s), kind=kCustom, calls=%fused_computation.2
  ROOT %r = f32[64,48] get-tuple-element(%w), index=1
}
"""
  s = hlo_stats.summary(hlo_stats.collectives(text))
  assert set(s) == {"all-gather", "reduce-scatter"}
  # 24 in the loop, and the asynchronous one once (its start, not its done).
  assert s["all-gather"]["count"] == 25
  assert s["all-gather"]["bytes"] == 24 * 64 * 192 * 4 + 64 * 8 * 2
  assert s["reduce-scatter"]["count"] == 24 and s["reduce-scatter"]["bytes"] == 24 * 64 * 48 * 4


def test_collectives_parser_counts_an_async_chain_once():
  # XLA:TPU splits one asynchronous collective into a start fusion in the entry and continuation
  # fusions (each a copy of the op under the same channel_id) inside the loop whose compute they
  # overlap: one gather per step, not one per loop trip. Another collective in the loop (its own
  # channel) runs every trip.
  text = """
%fused_computation.1 (p0: bf16[4,8]) -> (bf16[4,8], bf16[64,8]) {
  %all-gather.1 = bf16[64,8]{1,0} all-gather(%p0), channel_id=7, dimensions={0}
  ROOT %t = (bf16[4,8], bf16[64,8]) tuple(%p0, %all-gather.1)
}

%async_collective_fusion.2 (p0: bf16[4,8], p1: f32[16]) -> (f32[16], bf16[64,8]) {
  %all-gather.2 = bf16[64,8]{1,0} all-gather(%p0), channel_id=7, dimensions={0}
  ROOT %t = (f32[16], bf16[64,8]) tuple(%p1, %all-gather.2)
}

%body (p: (s32[], f32[16])) -> (s32[], f32[16]) {
  %f = (f32[16], bf16[64,8]) fusion(%a, %b), kind=kCustom, calls=%async_collective_fusion.2
  %ar = f32[16]{0} all-reduce(%x), channel_id=8, to_apply=%add
  ROOT %t = (s32[], f32[16]) tuple(%i, %ar)
}

%cond (p: (s32[], f32[16])) -> pred[] {
  ROOT %lt = pred[] compare(%a, %b), direction=LT
}

ENTRY %main (a: bf16[4,8]) -> f32[16] {
  %async-collective-start = (bf16[4,8], bf16[64,8]) fusion(%a), kind=kCustom, calls=%fused_computation.1
  %w = (s32[], f32[16]) while(%init), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"24"}}
  ROOT %r = f32[16] get-tuple-element(%w), index=1
}
"""
  s = hlo_stats.summary(hlo_stats.collectives(text))
  assert s["all-gather"]["count"] == 1 and s["all-gather"]["bytes"] == 64 * 8 * 2
  assert s["all-reduce"]["count"] == 24 and s["all-reduce"]["bytes"] == 24 * 16 * 4
