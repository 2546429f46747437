"""Backward labels (image1 -> image0) for symmetrized batches, and the label rule's parameters.

With symmetrize, rows (2i, 2i+1) of a batch are (a, b) and (b, a). `backward_mode` says where a
dataset's backward labels come from: the source (its `both(i)`, when it declares `has_backward`),
a `static_scene` source's depth + poses in meta (`geometry_backward`, by the official rule with
`label_parameters`), else (backward_fallback='unsupervised', e.g. HD1K's raw layout, whose
official reader gives its second view 4000 px flow that no loss range reads) a (b, a) row with
all masks False (`unsupervised_backward`), so the loss must tolerate rows without supervised
pixels. FlyingChairs labels its own backward row (the official zero flow, see its reader). The
static and Kubric pathways label both directions themselves (ufm_jax.data.augment).
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

import numpy as np

from ufm_jax.data import augment as augment_lib

log = logging.getLogger(__name__)

# What a static-scene sample's meta must hold to be labelled from its geometry.
GEOMETRY_META = ("depth0", "depth1", "K0", "K1", "cam2world0", "cam2world1")


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


def geometry_possible(source, meta) -> bool:
  return source.static_scene and all(k in meta for k in GEOMETRY_META)


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
  datasets without backward labels (HD1K's raw layout) without training on made-up labels."""
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
  if geometry_possible(source, meta):
    return "geometry"
  if fallback == "unsupervised":
    return "unsupervised"
  raise ValueError(
      f"dataset {name!r} cannot be symmetrized: its source ({type(source).__name__}) has no "
      f"backward labels (has_backward=False) and its samples are not static-scene pairs "
      f"(static_scene={static_scene}) with {', '.join(GEOMETRY_META)} in meta to compute them "
      "from; set input.symmetrize=False, input.backward_fallback='unsupervised' or drop it from "
      "the mixture")



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
