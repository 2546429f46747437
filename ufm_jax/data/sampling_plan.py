"""The epoch sampling plan of the training mixture, and each host's random-access index into it.

Position g in the global stream of unique pairs belongs to epoch g // E (E = sum of quotas). Each
epoch's plan is drawn from (seed, epoch) alone: every dataset contributes exactly its quota (without
replacement while it is large enough, every item floor(quota/len) times plus a draw without
replacement for the rest otherwise), then the union is shuffled. Global batch k holds positions
[k*Bu, (k+1)*Bu) (Bu unique pairs); host p reads its contiguous block of Bu/P of them, so the hosts'
batches together are exactly the global batch, and every position is read by exactly one host.

Element j of a host is a pure function of j (and the config), so grain's iterator state (the next
index) is the whole pipeline state: resuming mid-epoch yields exactly the remaining batches, with or
without worker processes.
"""

from __future__ import annotations

import dataclasses
import threading
import zlib
from typing import Sequence

import grain
import numpy as np

_STREAM_EPOCHS = 10**6  # "infinite" stream when num_epochs is None


# ----------------------------------------------------------------------------------------------
# The per-epoch plan


def draw_quota(size: int, quota: int, rng: np.random.Generator) -> np.ndarray:
  """`quota` indices into range(size): without replacement while size >= quota, else every index
  floor(quota/size) times plus a draw without replacement for the remainder."""
  if size <= 0:
    raise ValueError(f"cannot draw {quota} samples from an empty dataset")
  full, rest = divmod(quota, size)
  parts = [np.arange(size, dtype=np.int64)] * full
  if rest:
    parts.append(rng.choice(size, rest, replace=False).astype(np.int64))
  return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def epoch_plan(names: Sequence[str], sizes: Sequence[int], quotas: Sequence[int], seed: int,
               epoch: int) -> tuple[np.ndarray, np.ndarray]:
  """(dataset_id [E], sample_index [E]) of one epoch, shuffled; depends only on (seed, epoch).

  Each dataset's draw is keyed by its name, so adding or dropping another dataset leaves it as is.
  """
  ids, idx = [], []
  for d, (name, size, quota) in enumerate(zip(names, sizes, quotas)):
    rng = np.random.default_rng([seed, epoch, zlib.crc32(name.encode()), 1])
    idx.append(draw_quota(size, quota, rng))
    ids.append(np.full(quota, d, np.int32))
  ids, idx = np.concatenate(ids), np.concatenate(idx)
  perm = np.random.default_rng([seed, epoch, 2]).permutation(len(ids))
  return ids[perm], idx[perm]


# ----------------------------------------------------------------------------------------------
# Index: host-local element j -> (position, step, epoch, dataset, sample index)


@dataclasses.dataclass(frozen=True)
class MixtureLayout:
  names: tuple[str, ...]
  sizes: tuple[int, ...]
  quotas: tuple[int, ...]
  seed: int
  unique_per_host: int           # bu
  process_index: int
  process_count: int
  num_epochs: int | None

  @property
  def epoch_size(self) -> int:
    return int(sum(self.quotas))

  @property
  def unique_per_step(self) -> int:   # Bu
    return self.unique_per_host * self.process_count

  @property
  def num_steps(self) -> int:
    epochs = _STREAM_EPOCHS if self.num_epochs is None else self.num_epochs
    return epochs * self.epoch_size // self.unique_per_step

  def position(self, j: int) -> int:
    step, r = divmod(j, self.unique_per_host)
    return step * self.unique_per_step + self.process_index * self.unique_per_host + r


class MixtureIndex(grain.MapDataset):
  """Random-access index over this host's share of the mixture stream."""

  def __init__(self, layout: MixtureLayout):
    super().__init__()
    self.layout = layout
    self._plans: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    self._lock = threading.Lock()   # grain reads with several threads

  def __getstate__(self):
    state = self.__dict__.copy()
    state["_plans"] = {}   # recomputed in worker processes
    del state["_lock"]
    return state

  def __setstate__(self, state):
    self.__dict__.update(state)
    self._lock = threading.Lock()

  def __len__(self) -> int:
    return self.layout.num_steps * self.layout.unique_per_host

  def plan(self, epoch: int):
    with self._lock:
      if epoch not in self._plans:
        if len(self._plans) >= 2:   # batches straddle at most two epochs
          self._plans.pop(min(self._plans))
        lay = self.layout
        self._plans[epoch] = epoch_plan(lay.names, lay.sizes, lay.quotas, lay.seed, epoch)
      return self._plans[epoch]

  def __getitem__(self, j):
    if isinstance(j, slice):
      return self.slice(j)
    lay = self.layout
    j = int(j) % len(self)
    g = lay.position(j)
    epoch, offset = divmod(g, lay.epoch_size)
    ids, idx = self.plan(epoch)
    return {"position": g, "step": j // lay.unique_per_host, "epoch": epoch,
            "dataset_id": int(ids[offset]), "index": int(idx[offset])}

  def __str__(self):
    return f"MixtureIndex({dict(zip(self.layout.names, self.layout.quotas))})"
