"""The teacher of a distillation run (configs/distill.py): loaded from anything `ufm_jax.load`
takes, rebuilt for the run's mesh with the student's compute options, its variables sharded by
the student's rules. The step that runs it: ufm_jax.training.distill.

`config.teacher` (configs/distill.py):
  checkpoint  anything `ufm_jax.load` takes: a converted checkpoint, a train.py workdir, an
              official snapshot folder, or a Hugging Face ID with snapshot=True; or
              "variant:NAME" (a `ufm_jax.models.variants` structure with random weights,
              `random_variables`: for compiling and planning, where only shapes matter, and
              for tests)
  snapshot, revision, step   as `ufm_jax.load`'s
  dtype       the teacher's compute dtype (None: the student's `config.model.dtype`)
  resolution  (H, W) the teacher sees the un-augmented pair at (None: a workdir's training
              shape, else the model's first inference resolution)
  interpolation  "bilinear" | "nearest": how the teacher's outputs are sampled at the crop's
              pixels
"""

from __future__ import annotations

import json
import pathlib
from typing import Optional

import numpy as np

from ufm_jax.training.distill import INTERPOLATIONS, Teacher

VARIANT_PREFIX = "variant:"


def load_spec(spec) -> tuple:
  """(model, variables or a loader of them, the source's own training shape or None, name) of a
  config.teacher block, as loaded (not yet rebuilt for a mesh)."""
  checkpoint = spec.get("checkpoint")
  if not checkpoint:
    raise ValueError("config.teacher.checkpoint is empty: name the teacher (a converted "
                     "checkpoint, a train.py workdir, a snapshot folder, a Hub ID with "
                     "snapshot=True, or variant:NAME)")
  checkpoint = str(checkpoint)
  if checkpoint.startswith(VARIANT_PREFIX):
    from ufm_jax.models import variants
    model = variants.build_model(checkpoint[len(VARIANT_PREFIX):])
    return model, lambda: random_variables(model), None, checkpoint
  from ufm_jax.runtime import model_io
  model, variables = model_io.load_model(checkpoint, snapshot=bool(spec.get("snapshot")),
                                         revision=spec.get("revision"), step=spec.get("step"))
  shape = None
  if model_io.what_is(checkpoint) == model_io.WORKDIR:
    shape = workdir_training_shape(checkpoint)
  return model, variables, shape, checkpoint


def random_variables(model, seed: int = 0) -> dict:
  """{"params"} of `model` drawn with numpy at its shapes, N(0, 1 / fan_in) (norm scales around
  1): a variant:NAME teacher's weights. Only shapes matter where it is used (compiling, planning,
  tests), and compiling flax's initialisers costs seconds to minutes on CPU."""
  from ufm_jax.models import ufm
  return {"params": ufm.random_param_values(model, seed)}


def workdir_training_shape(workdir) -> Optional[tuple]:
  """The first training shape (H, W) of a train.py workdir's recorded config, by the pipeline's
  rule (explicit `input.shapes`, else `longest_side` with the first aspect ratio); None when the
  config records neither."""
  from ufm_jax.data import input_block
  path = pathlib.Path(workdir)
  if path.name == "checkpoints":
    path = path.parent
  cfg = json.loads((path / "config.json").read_text()).get("input") or {}
  if not (cfg.get("shapes") or cfg.get("longest_side")):
    return None
  return tuple(int(v) for v in input_block.training_shapes(cfg)[0])


def from_config(config, mesh) -> Optional[Teacher]:
  """`load_teacher(config, mesh)` for a distillation config, None for any other: what train.py,
  the planner and the FLOP count pass to `trainer.setup`."""
  return load_teacher(config, mesh) if config.get("teacher") else None


def load_teacher(config, mesh) -> Teacher:
  """The teacher of `config.teacher`, rebuilt with the student's compute options (scan layout,
  remat, attention) and the mesh's activation constraint and FSDP gathers, its variables sharded
  by the student's rules. Loads nothing onto the devices."""
  import jax
  from ufm_jax.training import sharding
  from ufm_jax.models import scan, ufm

  spec = dict(config.teacher)
  interpolation = spec.get("interpolation") or "bilinear"
  if interpolation not in INTERPOLATIONS:
    raise ValueError(f"config.teacher.interpolation={interpolation!r}; expected one of "
                     f"{INTERPOLATIONS}")
  model, variables, trained_shape, source = load_spec(spec)
  block = config.get("model") or {}
  compute = {k: block[k] for k in ("remat", "scan_blocks", "attention_impl", "head_dtype")
             if block.get(k) is not None}
  compute["dtype"] = spec.get("dtype") or block.get("dtype") or model.config.dtype
  cfg = model.config.replace(**compute)
  _, layer_gather = sharding.fsdp_gathers(mesh, config)
  model = ufm.model_from_config(cfg, activation_sharding=sharding.activation_constraint(mesh),
                                layer_gather=layer_gather)

  def host():
    v = variables() if callable(variables) else variables
    v = ufm.variables(v)
    v = dict(v, params=scan.to_layout(v["params"], cfg))
    return jax.tree.map(np.asarray, v)

  abstract = ufm.variable_shapes(model)
  shardings = sharding.tree_shardings(abstract, mesh, config.sharding_rules,
                                      config.sharding_min_size)
  abstract = jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                          abstract, shardings)
  resolution = spec.get("resolution") or trained_shape
  if not resolution:
    from ufm_jax.runtime import inference
    resolution = inference.inference_resolutions(model)[0]
  resolution = tuple(int(v) for v in resolution)
  p = cfg.encoder.patch_size
  if resolution[0] % p or resolution[1] % p:
    raise ValueError(f"config.teacher.resolution={resolution}: H and W must be multiples of the "
                     f"teacher's patch size {p}")
  return Teacher(model, abstract, shardings, resolution, interpolation, source, _load=host)
