"""The per-record transform of the training pipeline, and its skip accounting.

`LoadPair` is the grain map from an index record (ufm_jax.data.sampling_plan) to the rows of one
pair: each pair goes through its dataset's official pathway (`pathway`, ufm_jax.data.augment):
static scenes (the posed sources' `lazy_pair(i)`) are cropped first and labelled after the crop
from their depth and cameras by the official rule, in both directions; flow sets' stored labels
and Kubric-4D's (labelled at the stored size) are resized and cropped with the masks cut where a
match leaves the crop. A posed source read as a flow set (TartanAir) is labelled only at the
stored pixels its crop reads. Backward labels of the other sets: ufm_jax.data.backward_labels.
Everything random (augmentation, training shape of batch k) comes from (seed, position), never
from process-local generators.

A sample that raises while loading, labelling or augmenting, or fails validation, is skipped: a
replacement is drawn from the same dataset (deterministically), the failure is logged with the
error text (readers name the file) and counted (`SkipAccounting`, in the main process, part of
the checkpointed state); the iterator raises when the skipped fraction exceeds
`max_skip_fraction`.
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

import grain
import numpy as np

from ufm_jax.data import augment as augment_lib
from ufm_jax.data import official_ops
from ufm_jax.data.backward_labels import (GEOMETRY_META, geometry_backward, geometry_possible,
                                          label_parameters, unsupervised_backward)
from ufm_jax.data.sampling_plan import MixtureLayout
from ufm_jax.geometry import camera

log = logging.getLogger(__name__)

ARRAY_KEYS = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")


class SkipLimitExceeded(RuntimeError):
  pass


# ----------------------------------------------------------------------------------------------
# Validation, pathways, the per-record transform


def check_sample(sample: Mapping[str, Any], where: str) -> dict:
  """Shapes/dtypes of the sample-dict interface; finite flow where supervised. Raises ValueError."""
  missing = [k for k in ARRAY_KEYS if k not in sample]
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



class LoadPair:
  """grain map: index record -> dict of augmented arrays with a leading axis of 1 or 2 pairs.
  A subclass (ufm_jax.data.distill_rows) makes other rows through `_augmented` and names their
  keys in `row_keys`."""
  row_keys = ARRAY_KEYS

  def __init__(self, sources, names, backward_modes, layout: MixtureLayout, shapes,
               augment_cfg: augment_lib.AugmentConfig, symmetrize: bool, max_retries: int = 8,
               variants=None):
    self.sources, self.names, self.backward_modes = sources, names, backward_modes
    # Renderings per plan index (`input.draw_variants`): plan index i is source indices
    # [i * v, (i + 1) * v), one drawn per record.
    self.variants = tuple(variants) if variants is not None else (1,) * len(sources)
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
      mode = "geometry" if geometry_possible(src, sample.get("meta", {})) else "unsupervised"
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
      missing = [k for k in GEOMETRY_META if k not in meta]
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
      out.append(official_ops.StaticView(image, np.asarray(depth, np.float32),
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
    v = self.variants[d]
    for attempt in range(self.max_retries + 1):
      k = i if v == 1 else i * v + int(np.random.default_rng(
          [self.layout.seed, g, attempt, 6]).integers(v))
      try:
        pairs = self._augmented(d, k, out_hw, np.random.default_rng([self.layout.seed, g, 4]))
        break
      except Exception as e:  # pylint: disable=broad-except  # any unreadable sample is skipped
        # Logged (with running counts) when the batch reaches the main process.
        skipped.append(f"skipped {self.names[d]}[{k}]: {type(e).__name__}: {e}")
        i = int(np.random.default_rng([self.layout.seed, g, attempt, 3]).integers(
            self.layout.sizes[d]))
    else:
      raise SkipLimitExceeded(f"{self.max_retries + 1} consecutive unreadable samples from "
                              f"{self.names[d]!r}; last: {skipped[-1]}")
    # Rows stay separate arrays until `collate` stacks the batch: one copy of every row, not two.
    out = {k: [p[k] for p in pairs] for k in self.row_keys}
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


class SkipAccounting(grain.IterDataset):

  def __init__(self, parent, max_skip_fraction: float, min_samples: int):
    super().__init__(parent)
    self.max_skip_fraction, self.min_samples = max_skip_fraction, min_samples

  def __iter__(self):
    return _SkipAccountingIterator(self._parent.__iter__(), self.max_skip_fraction,
                                   self.min_samples)
