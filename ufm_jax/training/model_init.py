"""`model_init`: a training run's first parameters from elsewhere, merged into the fresh init.

Sources (a string, optionally prefixed with a kind; without one, `model_io.what_is` tells):
  ckpt:DIR       a training workdir or its checkpoints/ folder (latest step), or a
                 `python -m ufm_jax convert` output (read through `ufm_jax.load`)
  snapshot:DIR   a Hugging Face snapshot of the official PyTorch release (`ufm_jax.load_official`):
                 its folder, or a Hub ID (`snapshot:infinity1096/UFM-Base`), optionally at a
                 revision (`snapshot:infinity1096/UFM-Base@REVISION`: a branch, tag or commit);
                 the report names the commit the Hub ID resolved to
  teacher:SRC    a distillation student's start from its teacher (SRC: any ckpt: or snapshot:
                 source): every parameter whose path and shape the student shares is loaded, the
                 rest (narrower MLPs or heads) left at init and listed; no structure check, the
                 two models differ by design (configs/distill.py init=teacher)
  dinov2:PATH    DINOv2 weights for the encoder: HF `facebook/dinov2-*` model.safetensors (or its
                 folder), transformers naming, no torch needed; or the original `dinov2_vit*14*.pth`
                 (needs the optional torch extra)

BatchNorm running statistics ("batch_stats") come along from a source that has them for the same
modules (a refinement-recipe workdir or snapshot); otherwise they stay fresh (a base model's
weights into a refinement model: its U-Net is new).

The source's model config must agree with the training config in every field that changes the
model's outputs without changing its parameters (the flow adaptor's normalisation above all: the
official flow_mean / flow_std are buffers that a snapshot carries, base_shape and scale_strategy
config values). A run's config is what rebuilds its model later (config.json of the workdir), so
a difference is refused before training (`check_structure`), naming both values and the
--config override that adopts the source's, rather than training a model whose output scale the
config does not describe.

A head may have adaptors the source's lacks (a flow covariance added to a released model,
`configs/ufm560.py:cov=True` from UFM-Base): the head's last convolution takes the source's
channels for the adaptors both have and keeps its fresh ones for the new adaptor
(`head_channel_maps`; listed under "resized" in the report). An adaptor the source has and the
model lacks is dropped the same way.

`config.model_init_flow_adaptor` = "buffers" does what the official `resume_model` does
(train_pl.py:496-518: `load_state_dict` of the source's weights and buffers into the model the
YAML builds): before the run writes its config.json, `adopt_flow_adaptor` sets the config's
flow_mean / flow_std to the source's (its buffers), while base_shape and scale_strategy (YAML
values, not in a state dict) stay the config's, differences logged instead of refused. "check"
(and configs without the key): every difference is refused.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
from typing import Any

import jax.numpy as jnp
import numpy as np
from absl import logging
from flax import traverse_util

from ufm_jax.runtime import model_io

KINDS = ("ckpt", "snapshot", "dinov2", "teacher")


@dataclasses.dataclass
class InitReport:
  source: str
  loaded: list[str]
  resized: list[str]
  left_at_init: list[str]
  unused: list[str]
  # Parameter values (not arrays) in the arrays loaded or resized from the source (a head whose
  # adaptors were remapped counts whole), and in the template.
  copied_values: int = 0
  total_values: int = 0

  def summary(self) -> str:
    lines = [f"model_init from {self.source}: {len(self.loaded)} loaded, {len(self.resized)} "
             f"resized, {len(self.left_at_init)} left at init, {len(self.unused)} unused"]
    if self.total_values:
      lines.append(f"  {self.copied_values:,} of the model's {self.total_values:,} parameters "
                   f"from the source ({100 * self.copied_values / self.total_values:.1f}%)")
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
               resizable: str = r"pos_embed", partial: bool = False) -> tuple[Any, InitReport]:
  """Fills `template` (a param tree) with `loaded` (flat "a/b/c" -> array) where paths match.

  Shape mismatches on `resizable` params (position embeddings) are resized; other mismatches
  are an error naming both shapes, or with `partial` left at init (listed with both shapes).
  Returns (params, report).
  """
  from ufm_jax.models import dinov2
  flat_t = flatten(template)
  out, rep = {}, InitReport(source, [], [], [], sorted(set(loaded) - set(flat_t)))
  mismatched = []
  for k, v in flat_t.items():
    rep.total_values += int(np.prod(v.shape))
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
    elif partial:
      out[k] = v
      rep.left_at_init.append(f"{k} (source {w.shape}, model {tuple(v.shape)})")
      continue
    else:
      mismatched.append(f"{k}: checkpoint {w.shape} vs model {tuple(v.shape)}")
      continue
    rep.copied_values += int(np.prod(v.shape))
  if mismatched:
    raise ValueError(f"model_init {source}: shape mismatch for\n  " + "\n  ".join(mismatched))
  return traverse_util.unflatten_dict(out, sep="/"), rep


# The last convolution of each head (its output channels feed the adaptors), by adaptor field.
HEAD_OUTPUT_CONVS = {"flow_head_adaptors": ("head1_0_1", "conv2_2"),
                     "uncertainty_head_adaptors": ("uncertainty_head_0_1", "conv2_2")}


def head_channel_maps(source_config, config) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
  """{"<conv>/kernel" and "<conv>/bias": (model channels, source channels, note)} for every head
  whose adaptors differ between the source and the model: the channels of the adaptors both
  have, by name (the rest of the model's channels stay as initialised)."""
  from ufm_jax.models import dpt
  out = {}
  for field, path in HEAD_OUTPUT_CONVS.items():
    src, dst = getattr(source_config, field, None), getattr(config, field, None)
    if src is None or dst is None or tuple(src) == tuple(dst):
      continue
    a, b = dpt.adaptor_slices(src), dpt.adaptor_slices(dst)
    common = [n for n in dst if n in a]
    to = np.concatenate([np.arange(*b[n]) for n in common] or [np.zeros(0, int)])
    frm = np.concatenate([np.arange(*a[n]) for n in common] or [np.zeros(0, int)])
    new = [n for n in dst if n not in a]
    note = (f"adaptors {tuple(src)} -> {tuple(dst)}: {', '.join(common) or 'nothing'} loaded"
            + (f", {', '.join(new)} left at init" if new else ""))
    for leaf in ("kernel", "bias"):
      out["/".join(path + (leaf,))] = (to, frm, note)
  return out


def _remap_channels(template_flat: dict, loaded: dict, maps: dict, report: "InitReport"):
  """`loaded` with each mapped tensor rebuilt on the template's shape: its fresh values, the
  source's channels where `maps` says."""
  out = dict(loaded)
  for k, (to, frm, note) in maps.items():
    if k not in loaded or k not in template_flat:
      continue
    fresh = np.array(template_flat[k])
    fresh[..., to] = np.asarray(loaded[k])[..., frm]
    out[k] = fresh
    report.resized.append(f"{k} ({note})")
  return out


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


def snapshot_ref(path: str) -> tuple[str, str | None]:
  """(folder or Hub ID, revision) of a `snapshot:` source: `ID@REVISION` asks for a revision of a
  Hub ID; a folder that exists is taken whole, "@" and all."""
  if "@" in path and not pathlib.Path(path).exists():
    name, revision = path.rsplit("@", 1)
    if not revision:
      raise ValueError(f"model_init snapshot:{path}: empty revision after '@'")
    return name, revision
  return path, None


def _snapshot_source(path: str) -> tuple[str, str | None, str]:
  """(folder or Hub ID, revision, the report's name: with the resolved Hub commit)."""
  from ufm_jax.official import snapshot
  name, revision = snapshot_ref(path)
  folder = snapshot.snapshot_folder(name, revision)
  commit = snapshot.hub_commit(folder)
  shown = f"snapshot:{path}" + (f" (commit {commit})" if commit and commit != revision else "")
  return name, revision, shown


def load_init_params(spec: str, template, config=None) -> tuple[Any, InitReport]:
  """Parameters for `template` (the freshly initialised parameter tree) from the `model_init`
  source: `load_init_variables` on {"params": template}."""
  variables, report = load_init_variables(spec, {"params": template}, config)
  return variables["params"], report


def _read_source(kind: str, path: str, want_config: bool):
  """(variables {"params"[, "batch_stats"]} as flat "a/b" dicts, the source's model config (None
  for DINOv2 weights, a model without one, or when not `want_config`), the report's name of the
  source)."""
  if kind == "dinov2":
    from ufm_jax.official import dinov2_weights
    return {"params": dinov2_weights.load(path)}, None, f"{kind}:{path}"
  model, shown = None, None
  if kind == "snapshot":
    from ufm_jax.official import snapshot
    name, revision, shown = _snapshot_source(path)
    model, variables = snapshot.load_official(name, revision)
  elif model_io.what_is(path) == model_io.WORKDIR:
    from ufm_jax.runtime import checkpoint
    state, step = checkpoint.read_state_numpy(path)
    variables = model_io.state_variables(state)
    root = _workdir_root(path)
    if want_config and (root / "config.json").is_file():
      model = model_io.workdir_model(root)
    elif want_config:
      # Checkpoints copied without their run's config.json: the layouts can still be matched,
      # the structure cannot be checked (as for DINOv2 weights); say so instead of refusing.
      logging.warning("model_init: %s has no config.json; the source's model structure (flow "
                      "normalisation, heads) is not checked against the config", root)
    path = f"{path}@{step}"
  else:
    model, variables = model_io.load_converted(path)
  out = {c: {k: np.asarray(v) for k, v in flatten(tree).items()}
         for c, tree in variables.items() if c in ("params", "batch_stats")}
  return out, getattr(model, "config", None), shown or f"{kind}:{path}"


def _workdir_root(path):
  """A train.py workdir from itself or its checkpoints/ folder (config.json sits in the root)."""
  p = pathlib.Path(path)
  return p.parent if p.name == "checkpoints" and not (p / "config.json").exists() else p


# The flow adaptor's fields a state dict carries (buffers: the official resume_model loads them
# from the source) and the ones only a config states (they stay the run's).
FLOW_ADAPTOR_BUFFERS = ("flow_adaptor.flow_mean", "flow_adaptor.flow_std")
FLOW_ADAPTOR_CONFIG = ("flow_adaptor.base_shape", "flow_adaptor.scale_strategy")
FLOW_ADAPTOR_MODES = ("check", "buffers")


def source_model_config(spec: str):
  """The model config of a `model_init` source without reading its weights where it can (a
  snapshot's config.json and tensor shapes, a workdir's config.json); None for DINOv2 weights or
  a workdir without config.json."""
  kind, path = source_kind(spec)
  if kind == "dinov2":
    return None
  if kind == "snapshot":
    from ufm_jax.official import snapshot
    return snapshot.snapshot_model(*snapshot_ref(path)).config
  if model_io.what_is(path) == model_io.WORKDIR:
    root = _workdir_root(path)
    return model_io.workdir_model(root).config if (root / "config.json").is_file() else None
  model, _ = model_io.load_converted(path)
  return getattr(model, "config", None)


def adopt_flow_adaptor(config) -> list[str]:
  """With `config.model_init_flow_adaptor` = "buffers" and a `model_init` source: the config's
  model.flow_adaptor.flow_mean / flow_std set to the source's (what the official resume_model
  loads with the weights). Returns a line per value changed (nothing for a source without a
  model config). Run before the config is written to the workdir, so config.json states them."""
  mode = config.get("model_init_flow_adaptor") or "check"
  if mode not in FLOW_ADAPTOR_MODES:
    raise ValueError(f"model_init_flow_adaptor={mode!r}; expected one of {FLOW_ADAPTOR_MODES}")
  if mode != "buffers" or not config.get("model_init"):
    return []
  source = source_model_config(config.model_init)
  if source is None:
    return []
  block = config.model.get("flow_adaptor")
  if block is None:
    raise ValueError("model_init_flow_adaptor='buffers' needs a config.model.flow_adaptor block "
                     "(flow_mean, flow_std, base_shape, scale_strategy) to write the source's "
                     "buffers into")
  changed = []
  for field in FLOW_ADAPTOR_BUFFERS:
    key = field.split(".")[1]
    value = tuple(float(x) for x in getattr(source.flow_adaptor, key))
    old = block.get(key)
    if old is None or tuple(float(x) for x in old) != value:
      block[key] = value
      changed.append(f"model.{field}: {_show(old)} -> {_show(value)} (the buffers of "
                     f"{config.model_init}, as the official resume_model loads them)")
  return changed


def load_init_variables(spec: str, template: dict, config=None, model_block=None,
                        flow_adaptor: str = "check") -> tuple[dict, InitReport]:
  """Variables for `template` ({"params"[, "batch_stats"]}, freshly initialised) from the
  `model_init` source.

  `config` (the model's UFMConfig) puts the loaded blocks into the template's layout: per-layer
  sources (snapshots, DINOv2, unscanned runs) stacked for a `scan_blocks` model, stacked ones
  (scan runs) split for a per-layer model; and the source's model config (a snapshot's
  config.json, a workdir's, a converted checkpoint's) is checked against it (`check_structure`;
  `model_block`, the training config's `model` block, makes the error name --config overrides
  that exist). Without it the layouts must already agree and nothing is checked. BatchNorm
  statistics the source lacks stay as initialised; the report lists them under "left at init"
  with a "batch_stats/" prefix. `flow_adaptor` (`config.model_init_flow_adaptor`): "buffers"
  leaves the flow adaptor's base_shape and scale_strategy out of the check (the run keeps its
  config's, as the official resume_model does; a difference is logged), after
  `adopt_flow_adaptor` put the source's flow_mean / flow_std into the config.
  """
  kind, path = source_kind(spec)
  partial = kind == "teacher"
  if partial:
    kind, path = source_kind(path)
  loaded, source_config, source = _read_source(kind, path, want_config=config is not None)
  if partial:
    source = f"teacher:{source}"
  if config is not None and source_config is not None and not partial:
    if flow_adaptor not in FLOW_ADAPTOR_MODES:
      raise ValueError(f"model_init_flow_adaptor={flow_adaptor!r}; expected one of "
                       f"{FLOW_ADAPTOR_MODES}")
    keep = FLOW_ADAPTOR_CONFIG if flow_adaptor == "buffers" else ()
    for k, va, vb in structure_differences(source_config, config):
      if k in keep:
        logging.warning("model_init %s: %s is %s there; this run keeps the config's %s (the "
                        "official resume_model loads weights and buffers only)", source, k,
                        _show(va), _show(vb))
    check_structure(source_config, config, source, model_block, skip=keep)
  params = loaded["params"]
  maps = {}
  if config is not None:
    from ufm_jax.models import scan
    tree = traverse_util.unflatten_dict(params, sep="/")
    params = flatten(scan.to_layout(tree, config))
    if source_config is not None:
      maps = head_channel_maps(source_config, config)
  remapped = InitReport(source, [], [], [], [])
  params = _remap_channels(flatten(template["params"]), params, maps, remapped)
  out = {}
  out["params"], report = merge_into(template["params"], params, source, partial=partial)
  report.resized += remapped.resized
  stats = loaded.get("batch_stats", {})
  if "batch_stats" in template:
    out["batch_stats"], rep = merge_into(template["batch_stats"], stats, source, resizable=r"(?!)")
    report.loaded += [f"batch_stats/{k}" for k in rep.loaded]
    report.left_at_init += [f"batch_stats/{k}" for k in rep.left_at_init]
    report.unused += [f"batch_stats/{k}" for k in rep.unused]
  else:
    report.unused += [f"batch_stats/{k}" for k in sorted(stats)]
  logging.info("%s", report.summary())
  return out, report


# UFMConfig fields that may differ between a model_init source and the model it initialises:
# compute options and initialisers (they change no output of trained weights), where `predict`
# resizes to, a training-only gradient switch, and the position table (resized on load).
INIT_FREE_FIELDS = ("dtype", "remat", "attention_impl", "scan_blocks", "head_dtype", "param_init",
                    "official_kwargs", "refine_chunk", "unet_batchnorm_group_rows",
                    "inference_resolution",
                    "detach_uncertainty_head", "encoder.pos_embed_init", "encoder.init_values",
                    "encoder.pos_grid", "info_sharing.tied_qk_init")


# Fields a head's adaptors decide (compared through `head_channel_maps` instead): which adaptors
# a head has and hence its width. An adaptor both have must agree (flow_adaptor, flow_covariance).
ADAPTOR_FIELDS = ("flow_head_adaptors", "uncertainty_head_adaptors", "flow_head.output_dim",
                  "covisibility_head.output_dim")


def structure_differences(source_config, config) -> list[tuple[str, Any, Any]]:
  """(field, source value, config value) for every model-structure field on which the two
  disagree. Fields only one side has (a base model's source for a refinement model: the refiner's
  fields; a head or an adaptor one side lacks: the refinement recipe has no uncertainty head, a
  released model no flow covariance) are not compared, nor `INIT_FREE_FIELDS` and
  `ADAPTOR_FIELDS`; of `encoder.indices` only the last, the block the fusion transformer and
  the heads read (the refinement recipe adds an earlier tap for its refiner)."""
  a = traverse_util.flatten_dict(dataclasses.asdict(source_config), sep=".")
  b = traverse_util.flatten_dict(dataclasses.asdict(config), sep=".")
  out = []
  for k in sorted(set(a) & set(b)):
    if k in INIT_FREE_FIELDS or k in ADAPTOR_FIELDS:
      continue
    va, vb = a[k], b[k]
    if k == "encoder.indices":
      va, vb = tuple(va)[-1:], tuple(vb)[-1:]
    if _norm(va) != _norm(vb):
      out.append((k, va, vb))
  return out


def _norm(v):
  return tuple(_norm(x) for x in v) if isinstance(v, (list, tuple)) else v


def check_structure(source_config, config, source: str, model_block=None, skip=()) -> None:
  """ValueError when the source's model differs from `config` in a field that changes outputs
  (`structure_differences`, less the fields in `skip`), naming each field's two values and how
  to adopt the source's."""
  diffs = [d for d in structure_differences(source_config, config) if d[0] not in skip]
  if not diffs:
    return
  lines = []
  for k, va, vb in diffs:
    hint = _override_hint(k, va, model_block)
    lines.append(f"{k}: source {_show(va)}, config {_show(vb)}" + (f"  ->  {hint}" if hint else ""))
  raise ValueError(
      f"model_init {source}: the source model differs from this run's model config in fields "
      "that change its outputs (its weights were trained for the source's values; a run's "
      "config.json is what rebuilds its model later, so the config must state them):\n  " +
      "\n  ".join(lines) + "\nSet the config to the source's values (the overrides above), or "
      "start from a source trained with this config.")


def _show(v) -> str:
  return repr(tuple(v)) if isinstance(v, (list, tuple)) else repr(v)


def _override_hint(field: str, value, model_block) -> str:
  """--config.model.FIELD=VALUE where the training config's model block has that key (a locked
  ml_collections config takes no other), else where to set it."""
  flag_value = _show(value)
  if isinstance(value, (list, tuple)) or " " in flag_value:
    flag_value = f"'{flag_value}'"
  node, found = model_block, model_block is not None
  for part in field.split("."):
    try:
      node = node[part]
    except (KeyError, TypeError, AttributeError):
      found = False
      break
  if found:
    return f"--config.model.{field}={flag_value}"
  return f"set config.model.{field} = {_show(value)} in the config file (or pick a model " \
         "variant that has it)"
