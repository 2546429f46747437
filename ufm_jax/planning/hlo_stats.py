"""Collectives of a compiled XLA program, read from its HLO text (`compiled.as_text()`), and
XLA's own FLOP count of a program (`flops`; it counts a loop body once: the FLOPs of a train step
are counted on its jaxpr, `ufm_jax.planning.flops`).

What a step moves between devices decides whether it scales, and none of it shows on one device:
an FSDP step should gather each weight for the forward and backward pass and reduce-scatter its
gradient, never move the batch. `collectives(text)` lists every all-gather / all-reduce /
reduce-scatter / all-to-all / collective-permute, each counted as often as it runs: by its place in
the program, ops inside a `while` body (a scan over layers) times the loop's trip count (XLA's
known_trip_count, or the bound of the loop condition in XLA:TPU's programs, which carry none).
Each has two sizes:

- `bytes`: its result on one device (the unit of the `collective_bytes*` figures);
- `link_bytes`: what one device sends over its links under the op's ideal algorithm (a ring, or a
  bidirectional ring: the same bytes), with N the devices of its replica group: all-gather
  (N-1)/N x its result, reduce-scatter (N-1)/N x its operand, all-reduce 2(N-1)/N x its size
  (a reduce-scatter then an all-gather), all-to-all (N-1)/N x its size, collective-permute its
  size. This is what a team renting a pod can set beside the links' bandwidth.

XLA:TPU's reduce-scatter, a custom fusion around an all-reduce of the full operands, counts as a
reduce-scatter (its result: the fusion's, its operand: the all-reduce's). An asynchronous
collective counts once, at its start: XLA:GPU's `*-start` / `*-done` pairs and `async-start` /
`async-update` / `async-done` wrappers; XLA:TPU's start fusion (whose root is the custom call
AsyncCollectiveStart), whose copies of the op (same kind, channel_id and result) in the done
fusion and in continuation fusions, which XLA:TPU may place inside the loops whose compute they
overlap, are not counted again. Ops are never merged by channel_id alone: XLA:TPU gives distinct
collective-permutes one channel_id.
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
_DEVICES = re.compile(r"\b(num_partitions|replica_count)=(\d+)")
# XLA:GPU's asynchronous wrappers: the start's callee is counted, not the update's or done's.
_ASYNC_REST = re.compile(r"\sasync-(?:update|done)\(")
# XLA:TPU's asynchronous collectives: fusions calling a copy of the op each. The start fusion's
# root is a custom call AsyncCollectiveStart (older programs: the fusion is named
# async-collective-start), the done fusion's AsyncCollectiveDone (or named async-collective-done).
_ROOT_TARGET = re.compile(r'^\s*ROOT\s.*\bcustom_call_target="(AsyncCollective(?:Start|Done))"')
_ASYNC_CALLER = re.compile(r"^\s*(?:ROOT\s+)?%?async-collective-(start|done)[\w.\-]*\s+=.*"
                           r"\bcalls=%?([\w.\-]+)")
# XLA:TPU emits a reduce-scatter as a custom fusion whose body all-reduces the full operands: count
# it once, as a reduce-scatter of the fusion's (sharded) results, and not its body.
_FUSED_RS = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s+=\s+(.+?)\s+fusion\(.*\bcalls=%?"
                       r"(all-reduce-scatter[\w.\-]*)")


def link_bytes(kind: str, size: float, group: int, operand: float | None = None) -> float:
  """Bytes one device sends per execution under the ideal ring algorithm, for a collective of
  `kind` over `group` devices whose result is `size` bytes (a reduce-scatter's `operand`: its
  input, by default `group` x its result)."""
  n = group
  if kind == "all-gather":
    return (n - 1) / n * size
  if kind == "reduce-scatter":
    return (n - 1) / n * (n * size if operand is None else operand)
  if kind == "all-reduce":
    return 2 * (n - 1) / n * size
  if kind == "all-to-all":
    return (n - 1) / n * size
  if kind == "collective-permute":
    return float(size)
  raise ValueError(f"unknown collective kind {kind!r}")


@dataclasses.dataclass
class Collective:
  kind: str
  shapes: list           # [(dtype, (dims...)), ...] of the result (a tuple for variadic ops)
  bytes: int             # result bytes on one device, per execution
  count: int             # executions per program run (trip counts of enclosing loops)
  computation: str
  channel: int | None = None   # channel_id (not an identity: XLA:TPU reuses them)
  group: int | None = None     # devices per replica group (None: not stated, devices unknown)
  operand_bytes: int | None = None   # a reduce-scatter's input, where the HLO states it

  def shape_str(self) -> str:
    return ", ".join(f"{d}[{','.join(map(str, s))}]" for d, s in self.shapes)

  @property
  def link_bytes(self) -> float:
    """Bytes one device sends over its links per execution (`link_bytes`)."""
    if self.group is None and self.kind != "collective-permute":
      raise ValueError(f"{self.kind} {self.shape_str()} in {self.computation} states no replica "
                       "group and the HLO module no device count: its link bytes are unknown")
    return link_bytes(self.kind, self.bytes, self.group or 1, self.operand_bytes)


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


def _result_shapes(kind: str, suffix: str | None, shapes: list) -> list:
  """The results among the shapes an op's HLO line states. A `*-start` of all-gather or
  collective-permute returns (operands..., results...[, u32[] contexts]: XLA:TPU's
  collective-permute-start ends in two synchronisation contexts); an all-reduce-start returns its
  results alone (one per operand: the variadic GPU form)."""
  if suffix != "-start" or len(shapes) < 2 or kind == "all-reduce":
    return shapes
  shapes = [s for s in shapes if s != ("u32", ())] or shapes
  return shapes[len(shapes) // 2:]


def _parse(hlo_text: str):
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
  return comps, entry


def collectives(hlo_text: str) -> list[Collective]:
  """Every collective of the program, with how many times it runs per call of the entry."""
  comps, entry = _parse(hlo_text)
  header = hlo_text.lstrip().split("\n", 1)[0] if hlo_text.lstrip().startswith("HloModule") else ""
  sizes = dict(_DEVICES.findall(header))
  devices = (int(sizes.get("num_partitions", 1)) * int(sizes.get("replica_count", 1))
             if sizes else None)

  # XLA:TPU's asynchronous collectives: the start fusions' computations and the done fusions'.
  role = {}
  for name, lines in comps.items():
    for line in lines:
      t = _ROOT_TARGET.match(line)
      if t:
        role[name] = "start" if t.group(1).endswith("Start") else "done"
      c = _ASYNC_CALLER.match(line)
      if c:
        role.setdefault(c.group(2), c.group(1))

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
      if _ASYNC_REST.search(line):
        continue
      for kind, listed, single in _CALLEE.findall(line):
        names = listed or single
        if kind == "to_apply":   # reductions of all-reduce/reduce: scalar graphs, no collectives
          continue
        n = trips(line) if kind in ("body", "condition") else 1
        for callee in names.split(","):
          callee = callee.strip().lstrip("%")
          if not callee.startswith("all-reduce-scatter"):
            visit(callee, times * n, depth + 1)

  visit(entry, 1)

  def group_of(line: str) -> int | None:
    g = group_size(line)
    return devices if g is None else g

  found = []   # (Collective, role of its computation)
  for name, lines in comps.items():
    if not runs.get(name):
      continue
    for line in lines:
      fused = _FUSED_RS.match(line)
      if fused:
        shapes = _shapes(fused.group(1))
        inner = [_OP.match(x) for x in comps.get(fused.group(2), [])]
        inner = [(m, x) for m, x in zip(inner, comps.get(fused.group(2), [])) if m]
        operand = sum(_nbytes(_shapes(m.group(1))) for m, _ in inner) or None
        group = group_of(inner[0][1]) if inner else devices
        found.append((Collective("reduce-scatter", shapes, _nbytes(shapes), runs[name], name,
                                 None, group, operand), None))
        continue
      m = _OP.match(line)
      if not m or m.group(3) == "-done":
        continue
      shapes = _result_shapes(m.group(2), m.group(3), _shapes(m.group(1)))
      channel = _CHANNEL.search(line)
      found.append((Collective(m.group(2), shapes, _nbytes(shapes), runs[name], name,
                               int(channel.group(1)) if channel else None, group_of(line)),
                    role.get(name)))
  # Copies of a started collective (the done fusion's, the continuations') are not counted again.
  started = {(c.kind, c.channel, tuple(c.shapes)) for c, r in found if r == "start"}
  return [c for c, r in found
          if r == "start" or (r != "done" and (c.kind, c.channel, tuple(c.shapes)) not in started)]


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


def summary(colls: list[Collective], top: int = 5) -> dict:
  """{kind: {"count", "bytes", "link_bytes", "largest": [(bytes, shape), ...]}} with executions
  counted (`link_bytes` None where a collective's group is unknown)."""
  out = {}
  for kind in KINDS:
    items = [c for c in colls if c.kind == kind]
    if not items:
      continue
    largest = sorted(items, key=lambda c: -c.bytes)[:top]
    out[kind] = {"count": sum(c.count for c in items),
                 "bytes": sum(c.bytes * c.count for c in items),
                 "link_bytes": _link_or_none(items),
                 "largest": [(c.bytes, c.shape_str()) for c in largest]}
  return out


def _link_or_none(items):
  try:
    return total_link_bytes(items)
  except ValueError:
    return None


def total_bytes(colls: list[Collective]) -> int:
  return sum(c.bytes * c.count for c in colls)


def total_link_bytes(colls: list[Collective]) -> int:
  """Bytes one device sends over its links per program run (`link_bytes`), rounded."""
  return round(sum(c.link_bytes * c.count for c in colls))


def format_summary(s: dict) -> str:
  lines = []
  for kind, v in s.items():
    link = v.get("link_bytes")
    lines.append(f"  {kind:18s} {v['count']:6d} ops  {v['bytes'] / 2**30:9.3f} GiB of results, "
                 + ("link bytes unknown" if link is None else f"{link / 2**30:.3f} GiB sent")
                 + " per device")
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
