"""Collectives of a compiled XLA program, read from its HLO text (`compiled.as_text()`), and
XLA's own FLOP count of a program (`flops`; it counts a loop body once: the FLOPs of a train step
are counted on its jaxpr, `ufm_jax.planning.flops`).

What a step moves between devices decides whether it scales, and none of it shows on one device:
an FSDP step should gather each weight for the forward and backward pass and reduce-scatter its
gradient (about 3x the parameter bytes per device), never move the batch. `collectives(text)`
lists every all-gather / all-reduce / reduce-scatter / all-to-all / collective-permute with its
result shape and bytes per device, counted as often as it runs: ops inside a `while` body (a scan
over layers) are multiplied by the loop's trip count (XLA's known_trip_count, or the bound of the
loop condition in XLA:TPU's programs, which carry none). XLA:TPU's reduce-scatter, a custom fusion
around an all-reduce, counts as a reduce-scatter of its results, and its asynchronous collectives
once: XLA:TPU splits one into a start fusion, continuation fusions and a done fusion, each holding
a copy of the op under the one channel_id, and may place the continuations inside the loops whose
compute they overlap (a DPT weight's gather started before the encoder's loop, progressed in its 24
iterations); the collective runs as often as its least-run copy, the start.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import re

KINDS = ("all-gather", "all-reduce", "reduce-scatter", "all-to-all", "collective-permute")
DTYPE_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4,
               "u32": 4, "f32": 4, "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16,
               "f8e4m3fn": 1, "f8e5m2": 1}

_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s+\(.*\)\s+->\s+.*\{\s*$")
_OP = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s+=\s+(.+?)\s+(" + "|".join(KINDS) +
                 r")(-start|-done)?\(")
_SHAPE = re.compile(r"\b(" + "|".join(DTYPE_BYTES) + r")\[([\d,]*)\]")
_CALLEE = re.compile(r"\b(body|condition|to_apply|calls|true_computation|false_computation|"
                     r"branch_computations)=(?:\{([^}]*)\}|(%?[\w.\-]+))")
_TRIP = re.compile(r'"known_trip_count":\{"n":"(\d+)"\}')
# A loop condition `counter < N` (XLA:TPU's while ops carry no known_trip_count).
_CONST = re.compile(r"%([\w.\-]+)\s+=\s+s32\[\]\S*\s+constant\((\d+)\)")
_LT = re.compile(r"^\s*ROOT\s.*\scompare\(%?[\w.\-]+,\s*%?([\w.\-]+)\),\s*direction=LT")
_COND = re.compile(r"\bcondition=%?([\w.\-]+)")
_CHANNEL = re.compile(r"\bchannel_id=(\d+)")
_GROUPS_MESH = re.compile(r"replica_groups=mesh\[([^\]]*)\]\s*\{([^}]*)\}")
_GROUPS_IOTA = re.compile(r"replica_groups=\[\d+,(\d+)\]<=")
_GROUPS_LIST = re.compile(r"replica_groups=\{\{([^}]*)\}")
# XLA:TPU's asynchronous collectives: a start fusion and a done fusion, each calling a copy of the
# collective. The start's copy is counted, the done's is not.
_ASYNC_DONE = re.compile(r"^\s*(?:ROOT\s+)?%?async-collective-done[\w.\-]*\s+=")
# XLA:TPU emits a reduce-scatter as a custom fusion whose body all-reduces the full operands: count
# it once, as a reduce-scatter of the fusion's (sharded) results, and not its body.
_FUSED_RS = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s+=\s+(.+?)\s+fusion\(.*\bcalls=%?"
                       r"(all-reduce-scatter[\w.\-]*)")


@dataclasses.dataclass
class Collective:
  kind: str
  shapes: list           # [(dtype, (dims...)), ...] of the result (a tuple for variadic ops)
  bytes: int             # result bytes on one device, per execution
  count: int             # executions per program run (trip counts of enclosing loops)
  computation: str
  channel: int | None = None   # channel_id: copies of one asynchronous collective share it
  group: int | None = None     # devices per replica group (None: not stated, or all)

  def shape_str(self) -> str:
    return ", ".join(f"{d}[{','.join(map(str, s))}]" for d, s in self.shapes)


def _shapes(text: str):
  return [(d, tuple(int(x) for x in dims.split(",") if x)) for d, dims in _SHAPE.findall(text)]


def _nbytes(shapes) -> int:
  total = 0
  for dtype, dims in shapes:
    n = 1
    for d in dims:
      n *= d
    total += n * DTYPE_BYTES[dtype]
  return total


def collectives(hlo_text: str) -> list[Collective]:
  """Every collective of the program, with how many times it runs per call of the entry."""
  comps: dict[str, list[str]] = {}
  entry = None
  current = None
  for line in hlo_text.splitlines():
    m = _COMPUTATION.match(line)
    if m:
      current = m.group(1)
      comps[current] = []
      if line.startswith("ENTRY"):
        entry = current
      continue
    if current is not None:
      if line.strip() == "}":
        current = None
      else:
        comps[current].append(line)
  if entry is None:
    raise ValueError("no ENTRY computation in the HLO text (pass compiled.as_text())")

  # Executions of each computation: a while body runs trip-count times per execution of its
  # caller; everything else once. Collectives sit in the entry, loop bodies or called graphs.
  runs: dict[str, int] = collections.defaultdict(int)

  def trips(line: str) -> int:
    """Trip count of a while op: its known_trip_count, else the N of a `counter < N` condition
    (a counter from 0 by 1, as lax.scan and fori_loop lower), else 1."""
    known = _TRIP.search(line)
    if known:
      return int(known.group(1))
    cond = _COND.search(line)
    lines = comps.get(cond.group(1), []) if cond else []
    consts = dict(_CONST.findall("\n".join(lines)))
    for cline in lines:
      lt = _LT.match(cline)
      if lt and lt.group(1) in consts:
        return int(consts[lt.group(1)])
    return 1

  def visit(name: str, times: int, depth: int = 0):
    if depth > 64 or name not in comps:
      return
    runs[name] += times
    for line in comps[name]:
      if _ASYNC_DONE.match(line):
        continue
      for role, listed, single in _CALLEE.findall(line):
        names = listed or single
        if role == "to_apply":   # reductions of all-reduce/reduce: scalar graphs, no collectives
          continue
        n = trips(line) if role in ("body", "condition") else 1
        for callee in names.split(","):
          callee = callee.strip().lstrip("%")
          if not callee.startswith("all-reduce-scatter"):
            visit(callee, times * n, depth + 1)

  visit(entry, 1)
  out = []
  for name, lines in comps.items():
    if not runs.get(name):
      continue
    for line in lines:
      fused = _FUSED_RS.match(line)
      if fused:
        shapes = _shapes(fused.group(1))
        out.append(Collective("reduce-scatter", shapes, _nbytes(shapes), runs[name], name))
        continue
      m = _OP.match(line)
      if not m or m.group(3) == "-done":
        continue
      shapes = _shapes(m.group(1))
      if m.group(3) == "-start" and len(shapes) > 1:
        # (operands..., results...[, u32[] contexts]): keep the results. XLA:TPU's
        # collective-permute-start ends in two u32[] synchronisation contexts.
        shapes = [s for s in shapes if s != ("u32", ())] or shapes
        shapes = shapes[len(shapes) // 2:]
      channel = _CHANNEL.search(line)
      out.append(Collective(m.group(2), shapes, _nbytes(shapes), runs[name], name,
                            int(channel.group(1)) if channel else None, group_size(line)))
  return _one_per_channel(out)


def group_size(line: str) -> int | None:
  """Devices per replica group of a collective's HLO line: `replica_groups={{0,1},{2,3}}`, the
  iota form `[groups,size]<=[...]`, or `mesh['axis_0'=2,'axis_1'=4] {'axis_1'}` (the product of
  the listed axes' sizes). None where the line states none (every device)."""
  m = _GROUPS_MESH.search(line)
  if m:
    sizes = {k: int(v) for k, v in re.findall(r"'([\w]+)'=(\d+)", m.group(1))}
    return math.prod(sizes[a] for a in re.findall(r"'([\w]+)'", m.group(2)))
  m = _GROUPS_IOTA.search(line)
  if m:
    return int(m.group(1))
  m = _GROUPS_LIST.search(line)
  if m and m.group(1).strip():
    return len(m.group(1).split(","))
  return None


def _one_per_channel(colls: list[Collective]) -> list[Collective]:
  """One entry per asynchronous collective: of the copies sharing a kind and a channel_id, the
  least-run one (its start; the continuations may sit in loops)."""
  first: dict = {}
  for c in colls:
    if c.channel is None:
      continue
    key = (c.kind, c.channel)
    if key not in first or c.count < first[key].count:
      first[key] = c
  return [c for c in colls if c.channel is None or first[(c.kind, c.channel)] is c]


def summary(colls: list[Collective], top: int = 5) -> dict:
  """{kind: {"count", "bytes", "largest": [(bytes, shape), ...]}} with executions counted."""
  out = {}
  for kind in KINDS:
    items = [c for c in colls if c.kind == kind]
    if not items:
      continue
    largest = sorted(items, key=lambda c: -c.bytes)[:top]
    out[kind] = {"count": sum(c.count for c in items),
                 "bytes": sum(c.bytes * c.count for c in items),
                 "largest": [(c.bytes, c.shape_str()) for c in largest]}
  return out


def total_bytes(colls: list[Collective]) -> int:
  return sum(c.bytes * c.count for c in colls)


def format_summary(s: dict) -> str:
  lines = []
  for kind, v in s.items():
    lines.append(f"  {kind:18s} {v['count']:6d} ops  {v['bytes'] / 2**30:9.3f} GiB per device")
    for b, shape in v["largest"]:
      lines.append(f"      {b / 2**20:10.2f} MiB  {shape}")
  return "\n".join(lines) if lines else "  (no collectives)"


def flops(lowered) -> float | None:
  """XLA's FLOP count of a lowered (or compiled) program; None where the backend has none."""
  try:
    ca = lowered.cost_analysis()
    ca = ca[0] if isinstance(ca, (list, tuple)) else ca
    return float(ca.get("flops")) if ca and ca.get("flops") else None
  except Exception:  # noqa: BLE001 - not every backend reports a cost analysis
    return None
