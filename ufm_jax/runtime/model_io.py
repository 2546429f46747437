"""Models on disk: what a path holds, loading (model, variables) from any of them, and our own
checkpoint format.

    model, variables = model_io.load_model(path)   # `ufm_jax.load`: an official snapshot (folder,
                                                    # or Hub ID with snapshot=True), a converted
                                                    # checkpoint or a train.py workdir
    model_io.save(out_dir, model, variables)        # -> params/ (orbax) + model_config.json

Every loader returns the Flax variables {"params"[, "batch_stats"]}: `model.apply(variables, ...)`.
The command line, the demo, evaluate.py and `ufm_jax.tools.sequence` load through `load_model`;
`model_init` (ufm_jax.training.model_init) asks `what_is` too. The official format itself is
`ufm_jax.official`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

CONFIG_FILE = "model_config.json"
PARAMS_DIR = "params"

# What a path can hold (`what_is`).
SNAPSHOT = "snapshot"    # an official Hugging Face snapshot: config.json + model.safetensors
WORKDIR = "workdir"      # a train.py workdir (config.json + checkpoints/<step>/) or its checkpoints/
CONVERTED = "converted"  # written by `save` / `python -m ufm_jax convert`: params/ + model_config.json
DINOV2 = "dinov2"        # released DINOv2 weights (an encoder only): HF folder or file, or a .pth


def what_is(path: str | os.PathLike) -> str | None:
  """Which of SNAPSHOT, WORKDIR, CONVERTED, DINOV2 the file or folder `path` holds (None: none)."""
  p = pathlib.Path(path)
  if p.is_file():
    if p.suffix in (".pth", ".pt"):
      return DINOV2
    if p.suffix == ".safetensors":
      from safetensors import safe_open
      with safe_open(str(p), "np") as f:
        keys = list(f.keys())
      return SNAPSHOT if any(k.startswith("info_sharing.") for k in keys) else DINOV2
    return None
  if (p / "config.json").is_file() and (p / "model.safetensors").is_file():
    cfg = json.loads((p / "config.json").read_text())
    return DINOV2 if str(cfg.get("model_type", "")).startswith("dinov2") else SNAPSHOT
  if (p / "checkpoints").is_dir() or any(x.name.isdigit() and x.is_dir() for x in p.glob("*")):
    return WORKDIR
  if (p / PARAMS_DIR).exists() or (p / CONFIG_FILE).exists():
    return CONVERTED
  return None


def load_model(path: str | os.PathLike, snapshot: bool = False, revision: str | None = None,
               step: int | None = None):
  """(model, variables) from an official snapshot, a train.py workdir (its latest step, or
  `step`) or a converted checkpoint: what every command's --checkpoint takes. `snapshot=True`
  insists on a snapshot, which may then also be a Hugging Face model ID (infinity1096/UFM-Base,
  at `revision`; `ufm_jax.official.snapshot_folder`). variables: {"params"[, "batch_stats"]}."""
  model, variables, _ = load_recorded(path, snapshot, revision, step)
  return model, variables


def load_recorded(path: str | os.PathLike, snapshot: bool = False, revision: str | None = None,
                  step: int | None = None):
  """`load_model`, plus what a results file records of the source: {"checkpoint": the Hub ID as
  given, or the folder's absolute path; for a Hub ID "revision" (as asked, None: the default
  branch) and "commit" (the Hub commit it resolved to); for a workdir "step"}."""
  from ufm_jax.official import snapshot as official_snapshot
  p = pathlib.Path(path)
  if snapshot and not p.exists():
    _no_step(step, path)
    folder = official_snapshot.snapshot_folder(str(path), revision)
    model, variables = official_snapshot.load_official(folder)
    return model, variables, {"checkpoint": str(path), "revision": revision,
                              "commit": official_snapshot.hub_commit(folder)}
  if not p.is_dir():
    hint = (" (a Hugging Face model ID needs --snapshot on the command line, snapshot=True in "
            "ufm_jax.load, or ufm_jax.load_official)" if official_hub_id(str(path)) else "")
    raise FileNotFoundError(f"checkpoint directory not found: {p}{hint}")
  if revision is not None:
    raise ValueError(f"revision={revision!r} applies to Hugging Face model IDs; {p} is a local "
                     "folder")
  kind = what_is(p)
  if snapshot and kind != SNAPSHOT:
    raise FileNotFoundError(f"{p} is not a Hugging Face snapshot: expected config.json and "
                            "model.safetensors in it")
  record = {"checkpoint": str(p.absolute())}
  if kind == WORKDIR:
    model, variables, record["step"] = _load_workdir(p, step)
    return model, variables, record
  _no_step(step, p)
  if kind == SNAPSHOT:
    return (*official_snapshot.load_official(p), record)
  if kind == DINOV2:
    raise ValueError(f"{p} holds DINOv2 weights, an encoder only: start a training run from them "
                     f"with model_init=dinov2:{p}")
  return (*load_converted(p), record)


def _no_step(step, path) -> None:
  if step is not None:
    raise ValueError(f"step {step}: {path} is not a train.py workdir (config.json + "
                     "checkpoints/)")


def official_hub_id(name: str) -> bool:
  """Whether `name` is spelled like a Hugging Face model ID (owner/name)."""
  from ufm_jax.official import snapshot as official_snapshot
  return bool(official_snapshot.HUB_ID.fullmatch(name))


def load_workdir(path: str | os.PathLike, step: int | None = None):
  """(model, variables) of the latest (or given) checkpoint step of a train.py workdir; the model
  is rebuilt from the workdir's config.json by `ufm_jax.models.variants.from_config`, as training built it."""
  return _load_workdir(path, step)[:2]


def _load_workdir(path, step):
  from ufm_jax.runtime import checkpoint

  model = workdir_model(path)
  state, step = checkpoint.read_state_numpy(path, step)
  return model, state_variables(state), step


def workdir_model(path: str | os.PathLike):
  """The model a train.py workdir trained, rebuilt from its config.json (no parameters)."""
  import ml_collections

  from ufm_jax.models import variants

  cfg_path = pathlib.Path(path) / "config.json"
  if not cfg_path.is_file():
    raise FileNotFoundError(f"{cfg_path} not found: a train.py workdir holds the config it was "
                            "trained with")
  cfg = json.loads(cfg_path.read_text())
  if not cfg.get("model_fn") and not cfg.get("model_name"):
    raise ValueError(f"{cfg_path}: neither model_fn nor model_name; cannot rebuild the model")
  cfg["model"] = cfg.get("model") or {}
  return variants.from_config(ml_collections.ConfigDict(cfg))


def state_variables(state: dict):
  """A saved TrainState (as `checkpoint.read_state_numpy` reads it) -> the model's variables:
  {"params"}, and "batch_stats" when the run kept BatchNorm running statistics."""
  if state.get("batch_stats") is None:
    return {"params": state["params"]}
  return {"params": state["params"], "batch_stats": state["batch_stats"]}


# ----------------------------------------------------------------------------- our own format


def _saved_classes() -> dict:
  """Official class name (as model_config.json records it) -> (config_from_dict, build)."""
  from ufm_jax.models import refine, ufm
  return {
      "UniFlowMatchConfidence": (ufm.config_from_dict, ufm.model_from_config),
      "UniFlowMatch": (ufm.config_from_dict, ufm.model_from_config),
      "UniFlowMatchClassificationRefinement": (refine.refine_config_from_dict,
                                               refine.refine_model_from_config),
  }


def save(out_dir, model, variables, class_name: str | None = None):
  """Write the variables (orbax) + model_config.json into a new folder, atomically (temp +
  rename)."""
  import jax
  import numpy as np
  import orbax.checkpoint as ocp

  from ufm_jax.data import io
  from ufm_jax.models import ufm
  from ufm_jax.official import config as official_config

  with io.atomic_dir(out_dir) as tmp:
    ocp.PyTreeCheckpointer().save(tmp / PARAMS_DIR,
                                  jax.tree.map(np.asarray, ufm.variables(variables)))
    meta = {"class": class_name or official_config.class_name(model),
            "config": dataclasses.asdict(model.config)}
    (tmp / CONFIG_FILE).write_text(json.dumps(meta, indent=2))


def load_converted(ckpt_dir):
  """(model, variables) from a folder written by `save` / `python -m ufm_jax convert` (also one
  written before the variables convention, which held the bare parameter tree)."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  import orbax.checkpoint as ocp

  from ufm_jax.models import ufm
  from ufm_jax.official import keymap
  from ufm_jax.official import snapshot as official_snapshot

  d = pathlib.Path(ckpt_dir).absolute()
  cfg_path = d / CONFIG_FILE
  if not cfg_path.is_file():
    raise FileNotFoundError(f"{cfg_path} not found (not a checkpoint written by "
                            "`python -m ufm_jax convert`)")
  meta = json.loads(cfg_path.read_text())
  classes = _saved_classes()
  if meta.get("class") not in classes:
    raise ValueError(f"{cfg_path}: unknown model class {meta.get('class')!r}; known: "
                     f"{sorted(classes)}")
  from_dict, build = classes[meta["class"]]
  model = build(from_dict(meta["config"]))
  # Saved as numpy arrays: orbax restores them as numpy without a target tree.
  variables = ufm.variables(keymap.unfreeze(ocp.PyTreeCheckpointer().restore(d / PARAMS_DIR)))
  got = {k: tuple(np.shape(v)) for k, v in keymap.flat_variables(variables).items()}
  want = official_snapshot.expected_variable_shapes(model)
  if got != want:
    bad = sorted(set(got) ^ set(want)) + sorted(k for k in set(got) & set(want)
                                                 if got[k] != want[k])
    raise ValueError(f"{d / PARAMS_DIR}: parameters do not match the model of {cfg_path}: "
                     + ", ".join("/".join(k) for k in bad[:20]))
  return model, jax.tree.map(jnp.asarray, variables)


def convert_snapshot(snapshot_dir, out_dir, revision: str | None = None) -> str:
  """Official snapshot (folder or Hub ID) -> our checkpoint (`save`); returns a one-line
  summary."""
  import jax
  import numpy as np

  from ufm_jax.official import snapshot as official_snapshot
  model, variables = official_snapshot.load_official(snapshot_dir, revision)
  save(out_dir, model, variables)
  n = sum(int(np.prod(v.shape)) for v in jax.tree.leaves(variables["params"]))
  return f"wrote {out_dir} ({type(model).__name__}, {n:,} parameters)"
