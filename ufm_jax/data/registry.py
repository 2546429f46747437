"""Dataset sources register themselves by name; `get_source` builds one.

A source is a random-access sequence (`len()`, `__getitem__`) of sample dicts with the keys in
`SAMPLE_KEYS`:
  image0, image1  HWC uint8 RGB
  flow            [H, W, 2] float32, source (image0) -> target (image1), pixels, u right, v down
  covisibility    [H, W] bool
  flow_valid      [H, W] bool, where flow is supervised
  covis_valid     [H, W] bool, the covisibility supervision mask V_covis
  meta            dict: dataset, scene, frame ids; intrinsics, poses, depths when known

Every source class also declares two bool class attributes, read by the training pipeline when it
symmetrizes batches (ufm_jax.data.pipeline.backward_mode):
  has_backward    the source labels the backward pair (image1 -> image0) itself: `backward(i)`
                  returns it and `both(i)` returns (forward, backward), reading the images once
                  where it can; `both` may give (forward, None) for a pair without such labels
  static_scene    its pairs see a static scene, so when it has no backward labels of its own they
                  follow from depth + poses in meta (`thresholds` of the source, else those of
                  meta's dataset)

A source may also offer `lazy_pair(i)`: an object with `image0`, `image1`, the two posed views
`v0`, `v1` (image, z-depth, K, cam2world) and `training_labels(backward, params, rows, cols)`
-> the four label arrays of either direction by the official training code's rule, at the
source pixels rows x cols only (posed.PosedPair: static scenes; kubric4d.KubricPair: rigid
objects), and declare `pathway` ('static', 'kubric' or 'flow'): how the training pipeline crops
and labels its pairs (ufm_jax.data.augment; pipeline.pathway).
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Any, Callable

SAMPLE_KEYS = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid", "meta")

_REGISTRY: dict[str, Callable[..., Any]] = {}


def register(*names: str):
  """Class/function decorator: `@register("sintel_clean")` makes it reachable by `get_source`."""

  def wrap(factory):
    for name in names:
      key = name.lower()
      if key in _REGISTRY and _REGISTRY[key] is not factory:
        raise ValueError(f"dataset name {key!r} registered twice")
      _REGISTRY[key] = factory
    return factory

  return wrap


def _import_all_sources():
  from ufm_jax.data import sources
  for info in pkgutil.iter_modules(sources.__path__):
    importlib.import_module(f"{sources.__name__}.{info.name}")


def available() -> list[str]:
  """All registered dataset names."""
  _import_all_sources()
  return sorted(_REGISTRY)


def get_source(name: str, root: str | None = None, **options):
  """Builds the source registered as `name` (case-insensitive) reading from `root`."""
  _import_all_sources()
  key = name.lower()
  if key not in _REGISTRY:
    raise KeyError(f"unknown dataset {name!r}; known: {', '.join(sorted(_REGISTRY))}")
  return _REGISTRY[key](root, **options)
