"""The training input pipeline: a quota mixture of datasets as a grain random-access index.

Position g in the global stream of unique pairs belongs to epoch g // E (E = sum of quotas). Each
epoch's plan is drawn from (seed, epoch) alone: every dataset contributes exactly its quota (without
replacement while it is large enough, every item floor(quota/len) times plus a draw without
replacement for the rest otherwise), then the union is shuffled. Global batch k holds positions
[k*Bu, (k+1)*Bu) (Bu unique pairs); host p reads its contiguous block of Bu/P of them, so the hosts'
batches together are exactly the global batch, and every position is read by exactly one host.

Element j of a host is a pure function of j (and the config), so grain's iterator state (the next
index) is the whole pipeline state: resuming mid-epoch yields exactly the remaining batches, with or
without worker processes. Everything random (which pairs, augmentation, training shape of batch
k) comes from (seed, position), never from process-local generators.

Batches are dicts of numpy arrays with a leading batch axis of the per-host batch size:
image0, image1 [B,H,W,3] uint8; flow [B,H,W,2] float32; covisibility, flow_valid, covis_valid
[B,H,W] bool; dataset_id [B] int32 (index into `Pipeline.names`); epoch [B] int32.

Each pair goes through its dataset's official pathway (`pathway`, ufm_jax.data.augment): static
scenes (the posed sources' `lazy_pair(i)`) are cropped first and labelled after the crop from
their depth and cameras by the official rule, in both directions; flow sets' stored labels and
Kubric-4D's (labelled at the stored size) are resized and cropped with the masks cut where a
match leaves the crop. A posed source read as a flow set (TartanAir) is labelled only at the
stored pixels its crop reads. With symmetrize, rows (2i, 2i+1) are (a, b) and (b, a): backward
labels come from the pathway (static, Kubric), the source (its `both(i)`, when it declares
`has_backward`), a `static_scene` source's depth + poses in meta, else
(backward_fallback='unsupervised', e.g. FlyingChairs, HD1K) the (b, a) row has all masks False,
so the loss must tolerate rows without supervised pixels (FlyingChairs' covis_valid is all False
too).

A sample that raises while loading, labelling or augmenting, or fails validation, is skipped: a
replacement is drawn from the same dataset (deterministically), the failure is logged with the
error text (readers name the file) and counted; the iterator raises when the skipped fraction
exceeds `max_skip_fraction`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import zlib
from typing import Any, Mapping, Sequence

import grain
import numpy as np

from ufm_jax.data import augment as augment_lib
from ufm_jax.data import mixture
from ufm_jax.data.registry import get_source
from ufm_jax.geometry import camera

log = logging.getLogger(__name__)

_ARRAY_KEYS = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")
_GEOMETRY_META = ("depth0", "depth1", "K0", "K1", "cam2world0", "cam2world1")
_STREAM_EPOCHS = 10**6  # "infinite" stream when num_epochs is None


class SkipLimitExceeded(RuntimeError):
  pass


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


# ----------------------------------------------------------------------------------------------
# Loading, validation, symmetrization, augmentation


def check_sample(sample: Mapping[str, Any], where: str) -> dict:
  """Shapes/dtypes of the sample-dict interface; finite flow where supervised. Raises ValueError."""
  missing = [k for k in _ARRAY_KEYS if k not in sample]
  if missing:
    raise ValueError(f"{where}: sample lacks keys {missing}")
  out = dict(sample)
  out["image0"], out["image1"] = check_images(sample["image0"], sample["image1"], where)
  hw = out["image0"].shape[:2]
  flow = np.asarray(sample["flow"])
  if flow.shape != hw + (2,) or not np.issubdtype(flow.dtype, np.floating):
    raise ValueError(f"{where}: flow must be float {hw + (2,)}, got {flow.shape} {flow.dtype}")
  out["flow"] = flow.astype(np.float32, copy=False)
  for k in ("covisibility", "flow_valid", "covis_valid"):
    m = np.asarray(sample[k])
    if m.shape != hw:
      raise ValueError(f"{where}: {k} must be {hw}, got {m.shape}")
    out[k] = m.astype(bool, copy=False)
  bad = np.count_nonzero(out["flow_valid"] & ~camera.finite_pixels(out["flow"]))
  if bad:
    meta = sample.get("meta") or {}
    path = meta.get("path") or meta.get("gt_relpath")
    raise ValueError(f"{where}{f' ({path})' if path else ''}: non-finite flow at {bad} pixels "
                     "marked flow_valid")
  return out


def check_images(image0, image1, where: str) -> tuple[np.ndarray, np.ndarray]:
  out = []
  for k, a in (("image0", image0), ("image1", image1)):
    a = np.asarray(a)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8 or min(a.shape[:2]) < 2:
      raise ValueError(f"{where}: {k} must be HxWx3 uint8, got {a.shape} {a.dtype}")
    out.append(a)
  return out[0], out[1]


def _declared(source, name: str) -> tuple[bool, bool]:
  """(has_backward, static_scene) as the source class declares them (ufm_jax.data.registry)."""
  missing = [a for a in ("has_backward", "static_scene") if not isinstance(
      getattr(source, a, None), bool)]
  if missing:
    raise TypeError(f"dataset {name!r}: source class {type(source).__name__} does not declare "
                    f"{' and '.join(missing)} (bool class attributes; see ufm_jax/data/registry.py)")
  if source.has_backward and not callable(getattr(source, "both", None)):
    raise TypeError(f"dataset {name!r}: source class {type(source).__name__} declares has_backward "
                    "but has no both(i) -> (forward, backward) method")
  return source.has_backward, source.static_scene


def _geometry_possible(source, meta) -> bool:
  return source.static_scene and all(k in meta for k in _GEOMETRY_META)


def geometry_backward(sample: Mapping[str, Any], params=None) -> dict:
  """Backward labels (image1 -> image0) of a static-scene pair from depth + poses in meta, by the
  official rule (`geometry.official_labels`) with params = (absolute, temperature, relative)
  (default: `label_parameters` of meta's dataset)."""
  from ufm_jax import geometry  # pylint: disable=g-import-not-at-top
  meta = sample["meta"]
  if params is None:
    params = label_parameters(None, str(meta.get("dataset")))
  out = geometry.official_labels(meta["depth1"], meta["K1"], meta["cam2world1"], meta["depth0"],
                                 meta["K0"], meta["cam2world0"], params)
  return {"image0": sample["image1"], "image1": sample["image0"], "meta": meta,
          **{k: out[k] for k in augment_lib.LABEL_KEYS}}


def unsupervised_backward(sample: Mapping[str, Any]) -> dict:
  """The swapped pair with every supervision mask False: keeps the (a,b),(b,a) batch layout for
  datasets without backward labels (FlyingChairs, HD1K) without training on made-up labels."""
  hw = np.shape(sample["image1"])[:2]
  off = np.zeros(hw, bool)
  return {"image0": sample["image1"], "image1": sample["image0"],
          "flow": np.zeros(hw + (2,), np.float32), "covisibility": off, "flow_valid": off,
          "covis_valid": off, "meta": sample.get("meta", {})}


def backward_mode(source, name: str, fallback: str = "unsupervised") -> str:
  """How backward labels of `source` are obtained: 'source' (it declares has_backward: `both(i)`),
  'geometry' (it declares static_scene and its samples carry depth + poses in meta), else
  `fallback` ('unsupervised' or 'error')."""
  has_backward, static_scene = _declared(source, name)
  if has_backward:
    return "source"
  meta = {}
  if static_scene:
    try:
      meta = source[0].get("meta", {})
    except Exception as e:  # pylint: disable=broad-except  # a corrupt first sample is skipped later
      log.warning("%s[0] unreadable while probing for backward labels: %s", name, e)
  if _geometry_possible(source, meta):
    return "geometry"
  if fallback == "unsupervised":
    return "unsupervised"
  raise ValueError(
      f"dataset {name!r} cannot be symmetrized: its source ({type(source).__name__}) has no "
      f"backward labels (has_backward=False) and its samples are not static-scene pairs "
      f"(static_scene={static_scene}) with {', '.join(_GEOMETRY_META)} in meta to compute them "
      "from; set input.symmetrize=False, input.backward_fallback='unsupervised' or drop it from "
      "the mixture")


def pathway(source, name: str, cfg: augment_lib.AugmentConfig) -> str:
  """The official pathway a dataset's pairs take (ufm_jax.data.augment): 'static' (views
  cropped, then labelled from depth + poses), 'kubric' or 'flow' (stored labels resized and
  cropped). A source class may declare `pathway`; else static scenes are 'static', the rest
  'flow'; `cfg.flow_pathway_datasets` read as flow sets what the official code reads so."""
  if name.lower() in cfg.flow_pathway_datasets:
    return "flow"
  declared = getattr(source, "pathway", None)
  if declared is not None:
    if declared not in ("static", "flow", "kubric"):
      raise TypeError(f"dataset {name!r}: source class {type(source).__name__} declares pathway "
                      f"{declared!r}; expected 'static', 'flow' or 'kubric'")
    return declared
  return "static" if getattr(source, "static_scene", False) else "flow"


def label_parameters(source, name: str) -> tuple[float, float, float]:
  """(absolute, temperature, relative) of the official label rule for a dataset: the source's
  `thresholds` (3 values; 2 values = the supplementary's (tau_d, tau_r), no temperature), else
  the official `covisible_rendering_parameters` (geometry.RENDERING_PARAMETERS), else the
  supplementary's thresholds without temperature; looked up by the mixture name, then by the
  source's own `name` or `dataset`."""
  from ufm_jax import geometry  # pylint: disable=g-import-not-at-top
  own = getattr(source, "thresholds", None)
  if own is not None:
    own = tuple(float(x) for x in own)
    return own if len(own) == 3 else (own[0], 0.0, own[1])
  names = [name] + [str(getattr(source, a)) for a in ("name", "dataset")
                    if isinstance(getattr(source, a, None), str)]
  for n in names:
    params = geometry.rendering_parameters(n)
    if params is not None:
      return params
  for n in names:
    try:
      tau_d, tau_r = geometry.covis_thresholds(n)
    except KeyError:
      continue
    return (tau_d, 0.0, tau_r)
  raise KeyError(f"dataset {name!r}: no label thresholds (give its source `thresholds`, or add it "
                 f"to ufm_jax.geometry.RENDERING_PARAMETERS)")


class LoadPair:
  """grain map: index record -> dict of augmented arrays with a leading axis of 1 or 2 pairs."""

  def __init__(self, sources, names, backward_modes, layout: MixtureLayout, shapes,
               augment_cfg: augment_lib.AugmentConfig, symmetrize: bool, max_retries: int = 8):
    self.sources, self.names, self.backward_modes = sources, names, backward_modes
    self.layout, self.shapes, self.cfg = layout, tuple(shapes), augment_cfg
    self.symmetrize, self.max_retries = symmetrize, max_retries
    self.pathways = tuple(pathway(s, n, augment_cfg) for s, n in zip(sources, names))
    # The label rule's parameters, for the datasets labelled here from depth and cameras.
    modes = backward_modes or (None,) * len(sources)
    self.params = tuple(
        label_parameters(s, n) if (p != "flow" or callable(getattr(s, "lazy_pair", None))
                                   or m == "geometry") else None
        for s, n, p, m in zip(sources, names, self.pathways, modes))

  def _load(self, d: int, i: int):
    where = f"{self.names[d]}[{i}]"
    src = self.sources[d]
    mode = self.backward_modes[d] if self.symmetrize else None
    backward = None
    if mode == "source":
      sample, backward = src.both(i)
    else:
      sample = src[i]
    sample = check_sample(sample, where)
    if mode == "source" and backward is None:   # e.g. a pairs_folder pair without reverse/ labels
      mode = "geometry" if _geometry_possible(src, sample.get("meta", {})) else "unsupervised"
    if mode == "geometry":
      backward = geometry_backward(sample, self.params[d])
    elif mode == "unsupervised":
      backward = unsupervised_backward(sample)
    if backward is not None:
      backward = check_sample(backward, where + ".backward")
      if (backward["image0"].shape != sample["image1"].shape
          or backward["image1"].shape != sample["image0"].shape):
        raise ValueError(f"{where}: backward sample image shapes {backward['image0'].shape}, "
                         f"{backward['image1'].shape} do not swap the forward's")
    return sample, backward

  def _static_views(self, d: int, i: int, where: str):
    """The two posed views of a static pair: the source's lazy pair, else its sample's meta."""
    src = self.sources[d]
    if callable(getattr(src, "lazy_pair", None)):
      pair = src.lazy_pair(i)
      image0, image1 = check_images(pair.image0, pair.image1, where)
      views = ((image0, pair.v0), (image1, pair.v1))
      views = [(im, v.depth, v.K, v.cam2world) for im, v in views]
    else:
      sample = src[i]
      meta = sample.get("meta") or {}
      missing = [k for k in _GEOMETRY_META if k not in meta]
      if missing:
        raise ValueError(f"{where}: a static-pathway sample needs {', '.join(missing)} in meta")
      image0, image1 = check_images(sample["image0"], sample["image1"], where)
      views = [(im, meta[f"depth{k}"], meta[f"K{k}"], meta[f"cam2world{k}"])
               for k, im in enumerate((image0, image1))]
    out = []
    for k, (image, depth, K, c2w) in enumerate(views):
      if np.shape(depth) != image.shape[:2]:
        raise ValueError(f"{where}: view {k} image is {image.shape[:2]} but its depth is "
                         f"{np.shape(depth)}")
      out.append(augment_lib.StaticView(image, np.asarray(depth, np.float32),
                                        np.asarray(K, np.float64), np.asarray(c2w, np.float64)))
    return out

  def _augmented(self, d: int, i: int, out_hw, rng):
    """Sample i of dataset d through its official pathway as [fwd] or [fwd, bwd] rows."""
    src, name, cfg = self.sources[d], self.names[d].lower(), self.cfg
    where = f"{self.names[d]}[{i}]"
    params, path = self.params[d], self.pathways[d]
    low_light = name in cfg.low_light_datasets
    if path == "static":
      v0, v1 = self._static_views(d, i, where)
      return augment_lib.static_pair(v0, v1, params, out_hw, rng, cfg,
                                     crop=name not in cfg.no_crop_datasets,
                                     low_light_on=low_light, backward=self.symmetrize)
    lazy = callable(getattr(src, "lazy_pair", None))
    if path == "kubric":
      pair = src.lazy_pair(i)
      image0, image1 = check_images(pair.image0, pair.image1, where)
      fwd = {"image0": image0, "image1": image1, **pair.training_labels(False, params)}
      bwd = {"image0": image1, "image1": image0, **pair.training_labels(True, params)}
      return augment_lib.kubric_pair(fwd, bwd, out_hw, rng, cfg, with_backward=self.symmetrize)
    mode = self.backward_modes[d] if self.symmetrize else None
    if lazy and mode != "unsupervised":
      # A posed source read as a flow set (TartanAir): labelled only at the stored pixels the
      # nearest resize of the crop reads, in both directions.
      pair = src.lazy_pair(i)
      image0, image1 = check_images(pair.image0, pair.image1, where)
      crop = augment_lib.flow_crop(image0.shape[:2], out_hw, rng, cfg)
      grids = tuple(tuple(np.unique(g) for g in crop.source_grid(k)) for k in (0, 1))
      fwd = {"image0": image0, "image1": image1, **pair.training_labels(False, params, *grids[0])}
      bwd = None
      if mode is not None:
        bwd = {"image0": image1, "image1": image0, **pair.training_labels(True, params, *grids[1])}
      return augment_lib.flow_pair_with_crop(fwd, bwd, crop, rng, cfg, low_light_on=low_light,
                                             grid=grids)
    sample, backward = self._load(d, i)
    return augment_lib.flow_pair(sample, backward, out_hw, rng, cfg, low_light_on=low_light)

  def __call__(self, rec):
    d, i, g = rec["dataset_id"], rec["index"], rec["position"]
    out_hw = augment_lib.shape_for_step(self.shapes, self.layout.seed, rec["step"])
    skipped = []
    for attempt in range(self.max_retries + 1):
      try:
        pairs = self._augmented(d, i, out_hw, np.random.default_rng([self.layout.seed, g, 4]))
        break
      except Exception as e:  # pylint: disable=broad-except  # any unreadable sample is skipped
        # Logged (with running counts) when the batch reaches the main process.
        skipped.append(f"skipped {self.names[d]}[{i}]: {type(e).__name__}: {e}")
        i = int(np.random.default_rng([self.layout.seed, g, attempt, 3]).integers(
            self.layout.sizes[d]))
    else:
      raise SkipLimitExceeded(f"{self.max_retries + 1} consecutive unreadable samples from "
                              f"{self.names[d]!r}; last: {skipped[-1]}")
    # Rows stay separate arrays until `collate` stacks the batch: one copy of every row, not two.
    out = {k: [p[k] for p in pairs] for k in _ARRAY_KEYS}
    out["dataset_id"] = np.full(len(pairs), d, np.int32)
    out["epoch"] = np.full(len(pairs), rec["epoch"], np.int32)
    out["_attempts"] = len(skipped) + 1
    out["_skipped"] = skipped
    return out


def collate(elements):
  """Elements (lists of rows per key; dataset_id/epoch as arrays) -> one batch of stacked rows."""
  batch = {k: np.stack([row for e in elements for row in e[k]])
           for k in elements[0] if not k.startswith("_")}
  batch["_attempts"] = sum(e["_attempts"] for e in elements)
  batch["_skipped"] = [m for e in elements for m in e["_skipped"]]
  return batch


# ----------------------------------------------------------------------------------------------
# Skip accounting (in the main process, part of the checkpointed state)


class _SkipAccountingIterator(grain.DatasetIterator):

  def __init__(self, parent, max_skip_fraction: float, min_samples: int):
    super().__init__(parent)
    self.max_skip_fraction, self.min_samples = max_skip_fraction, min_samples
    self.attempted = 0
    self.skipped = 0

  def __next__(self):
    batch = next(self._parent)
    self.attempted += int(batch.pop("_attempts"))
    messages = batch.pop("_skipped")
    self.skipped += len(messages)
    for m in messages:
      log.warning("%s (%d skipped of %d read so far)", m, self.skipped, self.attempted)
    if (self.skipped and self.attempted >= self.min_samples
        and self.skipped > self.max_skip_fraction * self.attempted):
      raise SkipLimitExceeded(
          f"{self.skipped} of {self.attempted} samples were unreadable "
          f"({self.skipped / self.attempted:.1%} > max_skip_fraction={self.max_skip_fraction}); "
          f"last: {messages[-1] if messages else 'see log'}")
    return batch

  def get_state(self):
    return {"pipeline": self._parent.get_state(), "attempted": self.attempted,
            "skipped": self.skipped}

  def set_state(self, state):
    self._parent.set_state(state["pipeline"])
    self.attempted, self.skipped = int(state["attempted"]), int(state["skipped"])


class _SkipAccounting(grain.IterDataset):

  def __init__(self, parent, max_skip_fraction: float, min_samples: int):
    super().__init__(parent)
    self.max_skip_fraction, self.min_samples = max_skip_fraction, min_samples

  def __iter__(self):
    return _SkipAccountingIterator(self._parent.__iter__(), self.max_skip_fraction,
                                   self.min_samples)


# ----------------------------------------------------------------------------------------------
# Building the pipeline from the config's input block


@dataclasses.dataclass
class Pipeline:
  dataset: grain.IterDataset    # iter(dataset) -> checkpointable grain DatasetIterator of batches
  names: tuple[str, ...]        # dataset_id -> name
  quotas: tuple[int, ...]
  sizes: tuple[int, ...]
  dropped: tuple[str, ...]      # configured but absent on disk
  epoch_size: int               # unique pairs per epoch
  steps_per_epoch: float        # global batches per epoch (batches may straddle epochs)
  num_steps: int                # batches this iterator yields before it ends
  batch_size: int               # pairs per host batch
  shapes: tuple[tuple[int, int], ...]
  symmetrize: bool

  def __iter__(self):
    return iter(self.dataset)


def _open_sources(datasets: Mapping[str, Mapping[str, Any]], split: str | None,
                  data_root: str | None):
  present, dropped = {}, []
  for name, spec in datasets.items():
    spec = dict(spec)
    quota = int(spec.pop("quota"))
    root = spec.pop("root", None)
    options = dict(spec.pop("options", {}) or {})
    if spec:
      raise KeyError(f"input.datasets.{name}: unknown keys {sorted(spec)}; "
                     "expected quota, root, options")
    if quota <= 0:
      continue
    reader = name
    if name in mixture.LAYOUTS:
      # The official layout first, else the raw one (mixture.find_layout); LayoutError stops here.
      layout, found, why = mixture.find_layout(name, data_root, root)
      if layout is None:
        dropped.append(f"{name} ({why})")
        continue
      log.info("dataset %s: %s layout at %s, read by %r (%s)", name, layout.kind, found,
               layout.source, why)
      reader, root = layout.source, found
    elif root is not None:
      root = os.path.expanduser(str(root))
      if data_root is not None and not os.path.isabs(root):
        root = os.path.join(os.path.expanduser(str(data_root)), root)
    if root is not None and not os.path.exists(root):
      dropped.append(f"{name} ({root})")
      continue
    if split is not None:
      options.setdefault("split", split)
    try:
      source = get_source(reader, root, **options)
    except FileNotFoundError as e:
      dropped.append(f"{name} ({e})")
      continue
    if len(source) == 0:
      dropped.append(f"{name} (empty at {root})")
      continue
    present[name] = (source, quota)
  if dropped:
    log.warning("datasets absent on disk, dropped from the mixture (the others keep their "
                "quotas): %s", "; ".join(dropped))
  if not present:
    raise FileNotFoundError(f"no dataset of the mixture is available; absent: {'; '.join(dropped)}")
  return present, tuple(d.split(" ")[0] for d in dropped)


def make_train_iterator(config: Mapping[str, Any], *, process_batch: int | None = None,
                        seed: int = 0, num_epochs: int | None = None):
  """(checkpointable grain iterator of host batches, info) for train.py.

  info: pairs_per_epoch (batch rows per epoch: both directions counted when symmetrized, so
  steps per epoch = pairs_per_epoch / input.batch_size), unique_pairs_per_epoch, image_shape
  (the first training shape), shapes, datasets {name: quota}, dropped.
  """
  pipe = create(config, seed=seed, num_epochs=num_epochs)
  if process_batch is not None and int(process_batch) != pipe.batch_size:
    raise ValueError(f"train.py expects {process_batch} pairs per process, the pipeline makes "
                     f"{pipe.batch_size} (input.batch_size / process count)")
  rows = pipe.epoch_size * (2 if pipe.symmetrize else 1)
  info = {"pairs_per_epoch": rows, "unique_pairs_per_epoch": pipe.epoch_size,
          "image_shape": tuple(pipe.shapes[0]), "shapes": [tuple(x) for x in pipe.shapes],
          "datasets": dict(zip(pipe.names, pipe.quotas)), "dropped": list(pipe.dropped)}
  return iter(pipe), info


# The one home of the input block's defaults: `input_config` builds a block from them and
# `create` fills the keys a block leaves out.
INPUT_DEFAULTS = {
    "data_root": None,
    "split": None,
    "batch_size": 96,
    "symmetrize": True,
    "longest_side": 560,
    "aspect_ratios": augment_lib.DEFAULT_ASPECT_RATIOS,
    "shapes": (),
    "augment": {},
    "num_workers": -1,
    "read_threads": 2,
    "prefetch_buffer_size": 2,
    "worker_buffer_size": 1,
    "max_skip_fraction": 0.01,
    "skip_check_min_samples": 100,
    "backward_fallback": "unsupervised",
    "max_retries": 8,
    "keep_heap": True,
}


# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_heap(worker_index: int = 0, worker_count: int = 0) -> bool:
  """Makes glibc's malloc keep freed memory for the next sample (this process only).

  A sample's dozens of 0.1-10 MB temporaries are otherwise mmap'd fresh and unmapped again each
  time (or trimmed from the heap top), and the page faults of touching them anew cost ~12% of a
  row's host CPU at 560 (`benchmarks/data_pipeline.py --table1` with and without
  `--no_keep_heap`: 14.3 vs 12.6 ms, docs/host_input.md). Serving them from a heap that is not
  trimmed: mmap threshold at its 32 MiB maximum, trim threshold 512 MiB (freed memory up to that
  stays with the process). Runs in every process that makes samples: the grain workers (as their
  worker_init_fn, hence the signature) or, with num_workers=0, the training process. False where the C library is not glibc."""
  del worker_index, worker_count
  import ctypes  # pylint: disable=g-import-not-at-top
  try:
    mallopt = ctypes.CDLL("libc.so.6").mallopt
  except (OSError, AttributeError):
    return False
  return bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20)) and bool(mallopt(_M_TRIM_THRESHOLD, 512 << 20))


def auto_num_workers(cpu_count: int | None = None) -> int:
  """Grain worker processes for `num_workers=-1`: every core but two (the training process and
  its device feeding), at most 32; 0 (threads in-process) on small hosts."""
  cores = cpu_count or os.cpu_count() or 1
  return max(0, min(cores - 2, 32))


def input_config(datasets, **overrides):
  """The `config.input` block read by `create`: INPUT_DEFAULTS with `overrides`.

  batch_size is the global number of pairs per step, both directions counted when symmetrized
  (the paper's 96 = 48 unique pairs); each process gets batch_size / process_count.
  num_workers: grain worker processes per host (-1: `auto_num_workers()`, from the core count).
  backward_fallback: what symmetrize does for datasets without backward labels ('unsupervised':
  the (b, a) row has all masks False; 'error': refuse to build).
  keep_heap: glibc malloc keeps freed memory in the processes that make samples (`keep_heap`).
  shapes: the (H, W) training shapes, one drawn uniformly per global batch (the recipes give
  the official ones, augment.SHAPES_560 / SHAPES_980); empty: W = longest_side and H from
  aspect_ratios.
  augment: `augment.AugmentConfig` keys (empty: the official augmentation).
  """
  import ml_collections  # pylint: disable=g-import-not-at-top
  unknown = sorted(set(overrides) - set(INPUT_DEFAULTS))
  if unknown:
    raise KeyError(f"input_config: unknown keys {unknown}; known: {sorted(INPUT_DEFAULTS)}")
  block = {**INPUT_DEFAULTS, **overrides}
  block["aspect_ratios"] = tuple(block["aspect_ratios"])
  block["shapes"] = tuple(tuple(int(x) for x in hw) for hw in block["shapes"])
  block["augment"] = dict(block["augment"] or {})
  block["data_root"] = block["data_root"] or mixture.DEFAULT_DATA_ROOT
  if block["split"] is None:
    del block["split"]
  return ml_collections.ConfigDict({"datasets": ml_collections.ConfigDict(datasets), **block})


def create(config: Mapping[str, Any], *, seed: int = 0, num_epochs: int | None = None,
           process_index: int | None = None, process_count: int | None = None) -> Pipeline:
  """Builds the training pipeline from an input block (`input_config`; keys it leaves out take
  INPUT_DEFAULTS).

  Keys: datasets {name: {quota, root, options}} (relative roots are under data_root), data_root,
  batch_size (global pairs per step, counting both directions when symmetrized), symmetrize,
  longest_side, aspect_ratios, shapes, augment {...}, num_workers, worker_buffer_size, read_threads,
  prefetch_buffer_size, max_skip_fraction, skip_check_min_samples, backward_fallback, split,
  keep_heap.
  process_index/count default to jax's (grain ShardByJaxProcess).
  """
  cfg = dict(config.to_dict() if hasattr(config, "to_dict") else config)
  unknown = sorted(set(cfg) - set(INPUT_DEFAULTS) - {"datasets"})
  if unknown:
    raise KeyError(f"input block: unknown keys {unknown}; known: {sorted(INPUT_DEFAULTS)}")
  cfg = {**INPUT_DEFAULTS, **cfg}
  jax_processes = process_index is None or process_count is None
  if jax_processes:
    shard = grain.sharding.ShardByJaxProcess(drop_remainder=True)
    process_index, process_count = shard.shard_index, shard.shard_count
  symmetrize = bool(cfg["symmetrize"])
  global_batch = int(cfg["batch_size"])
  per_host, rem = divmod(global_batch, process_count)
  if rem:
    raise ValueError(f"input.batch_size={global_batch} is not divisible by {process_count} processes")
  if symmetrize and per_host % 2:
    raise ValueError(f"input.batch_size={global_batch}: symmetrized batches need an even per-host "
                     f"batch, got {per_host} on each of {process_count} processes")
  unique_per_host = per_host // 2 if symmetrize else per_host

  present, dropped = _open_sources(cfg["datasets"], cfg.get("split"), cfg.get("data_root"))
  names = tuple(present)
  sources = [present[n][0] for n in names]
  quotas = tuple(present[n][1] for n in names)
  sizes = tuple(len(s) for s in sources)
  modes = ()
  if symmetrize:
    fallback = str(cfg["backward_fallback"])
    if fallback not in ("unsupervised", "error"):
      raise ValueError(f"input.backward_fallback must be 'unsupervised' or 'error', got {fallback!r}")
    modes = tuple(backward_mode(s, n, fallback) for s, n in zip(sources, names))
    unsup = [n for n, m in zip(names, modes) if m == "unsupervised"]
    if unsup:
      log.warning("no backward labels for %s: their (b, a) rows in symmetrized batches carry no "
                  "supervision (all masks False)", ", ".join(unsup))
  shapes = (augment_lib.check_shapes(cfg["shapes"]) if cfg["shapes"] else
            augment_lib.training_shapes(int(cfg["longest_side"]), tuple(cfg["aspect_ratios"])))
  if jax_processes and process_count > 1:
    # Every host derives the same plans only if it sees the same datasets with the same sizes.
    from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
    multihost_utils.assert_equal(
        # int32: jax without x64 would wrap an int64 differently on each side of the comparison.
        np.array([zlib.crc32(repr((names, sizes, quotas)).encode()) & 0x7FFFFFFF], np.int32),
        f"hosts disagree on the mixture (names, sizes, quotas); this host: "
        f"{list(zip(names, sizes, quotas))}")
  layout = MixtureLayout(names, sizes, quotas, int(seed), unique_per_host, int(process_index),
                         int(process_count), num_epochs)
  if layout.num_steps == 0:
    raise ValueError(f"epoch of {layout.epoch_size} pairs is smaller than one global batch of "
                     f"{layout.unique_per_step} unique pairs")
  load = LoadPair(sources, names, backward_modes=modes, layout=layout, shapes=shapes,
                  augment_cfg=augment_lib.AugmentConfig.from_dict(cfg["augment"]),
                  symmetrize=symmetrize, max_retries=int(cfg["max_retries"]))
  ds = MixtureIndex(layout).map(load).batch(unique_per_host, drop_remainder=True, batch_fn=collate)
  ds = ds.to_iter_dataset(grain.ReadOptions(
      num_threads=int(cfg["read_threads"]),
      prefetch_buffer_size=int(cfg["prefetch_buffer_size"])))
  workers = int(cfg["num_workers"])
  if workers < 0:
    workers = auto_num_workers()
  if workers > 0:
    from absl import flags  # pylint: disable=g-import-not-at-top
    if not flags.FLAGS.is_parsed():
      # grain's worker start-up reads its absl flags; outside an absl app (pytest, notebooks,
      # benchmarks) they keep their defaults.
      flags.FLAGS.mark_as_parsed()
    ds = ds.mp_prefetch(grain.MultiprocessingOptions(
        num_workers=workers, per_worker_buffer_size=int(cfg["worker_buffer_size"])),
        worker_init_fn=keep_heap if cfg["keep_heap"] else None)
  elif cfg["keep_heap"]:
    keep_heap()
  ds = _SkipAccounting(ds, float(cfg["max_skip_fraction"]),
                       int(cfg["skip_check_min_samples"]))
  return Pipeline(dataset=ds, names=names, quotas=quotas, sizes=sizes, dropped=dropped,
                  epoch_size=layout.epoch_size,
                  steps_per_epoch=layout.epoch_size / layout.unique_per_step,
                  num_steps=layout.num_steps, batch_size=per_host, shapes=shapes,
                  symmetrize=symmetrize)
