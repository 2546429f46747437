"""`model_init`: a training run's first parameters from elsewhere, merged into the fresh init.

Sources (a string, optionally prefixed with a kind; without one, `model_io.what_is` tells):
  ckpt:DIR       a training workdir or its checkpoints/ folder (latest step), or a
                 `python -m ufm_jax convert` output (read through `ufm_jax.load`)
  snapshot:DIR   a Hugging Face snapshot of the official PyTorch release (`ufm_jax.load_official`)
  dinov2:PATH    DINOv2 weights for the encoder: HF `facebook/dinov2-*` model.safetensors (or its
                 folder), transformers naming, no torch needed; or the original `dinov2_vit*14*.pth`
                 (needs the optional torch extra)
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import jax.numpy as jnp
import numpy as np
from absl import logging
from flax import traverse_util

from ufm_jax import model_io

KINDS = ("ckpt", "snapshot", "dinov2")


@dataclasses.dataclass
class InitReport:
  source: str
  loaded: list[str]
  resized: list[str]
  left_at_init: list[str]
  unused: list[str]

  def summary(self) -> str:
    lines = [f"model_init from {self.source}: {len(self.loaded)} loaded, {len(self.resized)} "
             f"resized, {len(self.left_at_init)} left at init, {len(self.unused)} unused"]
    for name, items in (("resized", self.resized), ("left at init", self.left_at_init),
                        ("unused", self.unused)):
      if items:
        shown = ", ".join(items[:20]) + (f", ... ({len(items) - 20} more)" if len(items) > 20 else "")
        lines.append(f"  {name}: {shown}")
    return "\n".join(lines)


def flatten(tree) -> dict[str, Any]:
  """A param tree as {"a/b/c": leaf}."""
  return traverse_util.flatten_dict(dict(tree), sep="/")


def merge_into(template, loaded: dict[str, np.ndarray], source: str,
               resizable: str = r"pos_embed") -> tuple[Any, InitReport]:
  """Fills `template` (a param tree) with `loaded` (flat "a/b/c" -> array) where paths match.

  Shape mismatches on `resizable` params (position embeddings) are resized; other mismatches
  are an error naming both shapes. Returns (params, report).
  """
  from ufm_jax.models import dinov2
  flat_t = flatten(template)
  out, rep = {}, InitReport(source, [], [], [], sorted(set(loaded) - set(flat_t)))
  mismatched = []
  for k, v in flat_t.items():
    if k not in loaded:
      out[k] = v
      rep.left_at_init.append(k)
      continue
    w = np.asarray(loaded[k])
    if w.shape == tuple(v.shape):
      out[k] = jnp.asarray(w, v.dtype)
      rep.loaded.append(k)
    elif re.search(resizable, k):
      out[k] = jnp.asarray(dinov2.resize_pos_embed(w, v.shape), v.dtype)
      rep.resized.append(f"{k} {w.shape}->{tuple(v.shape)}")
    else:
      mismatched.append(f"{k}: checkpoint {w.shape} vs model {tuple(v.shape)}")
  if mismatched:
    raise ValueError(f"model_init {source}: shape mismatch for\n  " + "\n  ".join(mismatched))
  return traverse_util.unflatten_dict(out, sep="/"), rep


def source_kind(spec: str) -> tuple[str, str]:
  """(kind, path) of a `model_init` source: its prefix, or what `model_io.what_is` finds."""
  if ":" in spec and spec.split(":", 1)[0] in KINDS:
    kind, path = spec.split(":", 1)
    return kind, path
  kind = model_io.what_is(spec)
  if kind is None:
    raise FileNotFoundError(f"model_init: cannot tell what {spec!r} is (expected a training "
                            "workdir, a converted checkpoint, a UFM HF snapshot or DINOv2 weights)")
  return {model_io.WORKDIR: "ckpt", model_io.CONVERTED: "ckpt"}.get(kind, kind), spec


def load_init_params(spec: str, template, config=None) -> tuple[Any, InitReport]:
  """Parameters for `template` (the freshly initialised tree) from the `model_init` source.

  `config` (the model's UFMConfig) puts the loaded blocks into the template's layout: per-layer
  sources (snapshots, DINOv2, unscanned runs) stacked for a `scan_blocks` model, stacked ones
  (scan runs) split for a per-layer model. Without it the layouts must already agree.
  """
  kind, path = source_kind(spec)
  if kind == "dinov2":
    from ufm_jax.models import dinov2
    loaded = dinov2.load(path)
  elif kind == "snapshot":
    from ufm_jax.official import snapshot
    _, params = snapshot.load_official(path)
    loaded = {k: np.asarray(v) for k, v in flatten(params).items()}
  elif model_io.what_is(path) == model_io.WORKDIR:
    from ufm_jax import checkpoint
    state, step = checkpoint.read_state_numpy(path)
    loaded, path = flatten(state["params"]), f"{path}@{step}"
  else:
    _, params = model_io.load(path)
    loaded = {k: np.asarray(v) for k, v in flatten(params).items()}
  if config is not None:
    from ufm_jax.models import scan
    tree = traverse_util.unflatten_dict(loaded, sep="/")
    loaded = flatten(scan.to_layout(tree, config))
  params, report = merge_into(template, loaded, f"{kind}:{path}")
  logging.info("%s", report.summary())
  return params, report
