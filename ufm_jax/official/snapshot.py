"""Official Hugging Face snapshots (config.json + model.safetensors, as `save_pretrained` writes
them): `load_official` reads one into (model, variables), from a folder or a Hub ID through the
standard Hugging Face cache; `save_official` writes one with a model card, read back through the
loader before anything is written.
"""

import dataclasses
import json
import pathlib
import re
import struct
import warnings
from typing import Dict, List, Optional, Tuple

import numpy as np
from flax import traverse_util

from ufm_jax.data import io
from ufm_jax.models import ufm
from ufm_jax.official import config as official_config
from ufm_jax.official import keymap


def expected_param_shapes(model) -> Dict[Tuple[str, ...], Tuple[int, ...]]:
  """{Flax path: shape} of the model's parameters (ufm.param_shapes, flattened)."""
  return {k: tuple(v.shape) for k, v in traverse_util.flatten_dict(ufm.param_shapes(model)).items()}


def expected_variable_shapes(model) -> Dict[Tuple[str, ...], Tuple[int, ...]]:
  """{(collection, *Flax path): shape} of every variable (params, BatchNorm batch_stats)."""
  flat = traverse_util.flatten_dict(ufm.variable_shapes(model))
  return {k: tuple(v.shape) for k, v in flat.items()}


# owner/name as the Hub spells model IDs (a path that exists is always read as a folder).
HUB_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*/[A-Za-z0-9][A-Za-z0-9._-]*")


def snapshot_folder(name, revision: Optional[str] = None) -> pathlib.Path:
  """The folder of a snapshot: `name` itself when it exists, else the Hugging Face model ID
  `name` (e.g. infinity1096/UFM-Base) at `revision` through huggingface_hub's standard cache
  (HF_HOME / HF_HUB_CACHE; HF_HUB_OFFLINE=1 reads the cache only), downloading config.json and
  model.safetensors when they are not cached."""
  path = pathlib.Path(name)
  if path.exists():
    if revision is not None:
      raise ValueError(f"revision={revision!r} applies to Hub IDs; {name} is a local folder")
    return path
  if not HUB_ID.fullmatch(str(name)):
    raise FileNotFoundError(f"snapshot not found: {name} is no folder (a snapshot folder holds "
                            "config.json and model.safetensors) nor a Hugging Face model ID "
                            "(owner/name, e.g. infinity1096/UFM-Base)")
  import huggingface_hub
  from huggingface_hub import constants
  try:
    return pathlib.Path(huggingface_hub.snapshot_download(
        str(name), revision=revision, allow_patterns=["config.json", "model.safetensors"]))
  except Exception as e:  # noqa: BLE001 - offline, unknown repo, network: one clear message
    at = f"{name}" + (f" (revision {revision})" if revision else "")
    how = ("HF_HUB_OFFLINE is set, so only the cache was read" if constants.HF_HUB_OFFLINE else
           "and the Hub could not provide it")
    raise FileNotFoundError(
        f"Hugging Face model {at} is not in the local cache {constants.HF_HUB_CACHE} {how} "
        f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}); no folder named "
        f"{name} either") from None


def hub_commit(folder) -> Optional[str]:
  """The Hub commit of a folder of huggingface_hub's cache (`.../snapshots/<commit>/`), else
  None (a folder of the user's own)."""
  folder = pathlib.Path(folder)
  return folder.name if folder.parent.name == "snapshots" else None


def _snapshot_files(d: pathlib.Path) -> Tuple[pathlib.Path, pathlib.Path]:
  """(config.json, model.safetensors) of a snapshot folder; FileNotFoundError naming a missing one."""
  cfg_path, w_path = d / "config.json", d / "model.safetensors"
  for p in (cfg_path, w_path):
    if not p.is_file():
      raise FileNotFoundError(f"{p} not found (expected a Hugging Face snapshot folder with "
                              "config.json and model.safetensors)")
  return cfg_path, w_path


def read_snapshot(snapshot_dir) -> Tuple[dict, Dict[str, np.ndarray]]:
  cfg_path, w_path = _snapshot_files(pathlib.Path(snapshot_dir))
  try:
    cj = json.loads(cfg_path.read_text())
  except json.JSONDecodeError as e:
    raise ValueError(f"{cfg_path}: invalid JSON ({e})") from e
  return cj, io.read_safetensors(w_path)


def snapshot_model(snapshot, revision: Optional[str] = None):
  """The model (no parameters) a snapshot describes: its config.json and the tensor shapes of
  model.safetensors' header, without reading the weights."""
  import types

  from safetensors import safe_open
  d = snapshot_folder(snapshot, revision)
  cfg_path, w_path = _snapshot_files(d)
  try:
    cj = json.loads(cfg_path.read_text())
    with safe_open(str(w_path), framework="numpy") as f:
      shapes = {k: types.SimpleNamespace(shape=tuple(f.get_slice(k).get_shape()))
                for k in f.keys()}
  except Exception as e:  # noqa: BLE001 - JSON or safetensors header: one message naming the file
    raise ValueError(f"{d}: cannot read the snapshot's config.json / model.safetensors header "
                     f"({e})") from e
  return official_config.official_spec(cj, shapes, f"{snapshot}/config.json").model


def load_official(snapshot, revision: Optional[str] = None):
  """(model, variables) from a snapshot of an official UFM release: a folder, or a Hugging Face
  model ID (`load_official("infinity1096/UFM-Base")`, `snapshot_folder`).

  variables: {"params": ...}, plus "batch_stats" for a U-Net with BatchNorm, as every loader
  returns them: `model.apply(variables, ...)`, `ufm_jax.predict(model, variables, ...)`.
  """
  d = snapshot_folder(snapshot, revision)
  cj, state = read_snapshot(d)
  where = str(snapshot) if d == pathlib.Path(snapshot) else f"{snapshot} ({d})"
  spec = official_config.official_spec(cj, state, f"{where}/config.json")
  variables = keymap.params_from_state_dict(state, expected_variable_shapes(spec.model),
                                            spec.buffers, f"{where}/model.safetensors")
  return spec.model, variables


# UFMConfig fields a snapshot does not carry: compute options and initialisers (the encoder's
# LayerScale initial value included; the loader sets the hub's 1.0).
JAX_ONLY_FIELDS = ("dtype", "remat", "attention_impl", "refine_chunk",
                   "unet_batchnorm_group_rows", "encoder.pos_embed_init",
                   "encoder.init_values", "info_sharing.tied_qk_init", "param_init")


def _check_export(model, params, cj: dict, state: Dict[str, np.ndarray], class_name: str
                  ) -> List[str]:
  """Reads an export back as load_official would: the same class, config and params, or raise.
  Returns the JAX-only config values that the snapshot drops."""
  spec = official_config.official_spec(cj, state, "exported config.json")
  if spec.class_name != class_name:
    raise ValueError(f"exported config.json reads back as {spec.class_name}, not {class_name}")
  ours = traverse_util.flatten_dict(dataclasses.asdict(model.config))
  back = traverse_util.flatten_dict(dataclasses.asdict(spec.model.config))
  dropped, lost = [], []
  for k in sorted((set(ours) | set(back)) - {("official_kwargs",)}):
    a, b = ours.get(k), back.get(k)
    if a != b:
      name = ".".join(k)
      if name in JAX_ONLY_FIELDS:
        dropped.append(f"{name}={a!r}")
      else:
        lost.append(f"{name}={a!r} (an official config.json gives {b!r})")
  if lost:
    raise ValueError(f"{class_name}: config.json cannot describe this model config: "
                     + "; ".join(lost))
  back_params = keymap.flat_variables(keymap.params_from_state_dict(
      state, expected_variable_shapes(spec.model), spec.buffers, "exported model.safetensors",
      as_jax=False))
  for path, v in keymap.flat_variables(params).items():
    if not np.array_equal(np.asarray(v, np.float32), back_params[path], equal_nan=True):
      raise ValueError(f"exported {keymap.path_to_torch_key(path[1:])} does not read back to "
                       f"{'/'.join(path)}")
  return dropped


def _model_card(class_name: str, source: Optional[str], step: Optional[int],
                notes: List[str]) -> str:
  from ufm_jax import __version__
  lines = [
      "---", "tags:", "- ufm", "- optical-flow", "- dense-correspondence", "- ufm-jax",
      "- model_hub_mixin", "- pytorch_model_hub_mixin", "---", "",
      f"# {class_name} exported from UFM-JAX", "",
      f"- Source checkpoint: `{source if source is not None else 'parameters in memory'}`",
      f"- Step: {step if step is not None else 'n/a (not a train.py checkpoint step)'}",
      f"- Written by: ufm_jax {__version__} (`ufm_jax.save_official`)", "",
      "PyTorch (official UFM code): `from uniflowmatch.models.ufm import "
      f"{class_name}` then `{class_name}.from_pretrained(DIR)`. JAX: `ufm_jax.load_official(DIR)`.",
  ]
  if notes:
    lines += ["", "## Export notes", ""] + [f"- {n}" for n in notes]
  return "\n".join(lines) + "\n"


def _safetensors_header(path: pathlib.Path) -> tuple[bytes, dict]:
  """(the 8-byte length + header bytes as stored, the header parsed) of a .safetensors file."""
  with open(path, "rb") as f:
    raw = f.read(8)
    n = struct.unpack("<Q", raw)[0] if len(raw) == 8 else 0
    head = raw + f.read(n)
  return head, json.loads(head[8:])


def _header_as_in(path: pathlib.Path, source: pathlib.Path) -> None:
  """Gives `path` the header bytes of `source` when both describe the same tensors at the same
  offsets with the same metadata: only the order of the metadata entries (the alias map, which
  the safetensors writer keeps in a hash map, so two official saves need not agree on it) and
  padding can differ, and the file becomes byte-identical to a source holding the same data."""
  if not source.is_file():
    return
  try:
    theirs, theirs_parsed = _safetensors_header(source)
  except (OSError, ValueError, struct.error):
    return
  ours, ours_parsed = _safetensors_header(path)
  if theirs == ours or theirs_parsed != ours_parsed:
    return
  data = path.read_bytes()[len(ours):]
  path.write_bytes(theirs + data)


def save_official(model, variables, out_dir, *, source: Optional[str] = None,
                  step: Optional[int] = None) -> List[str]:
  """Write (model, variables) as an official Hugging Face snapshot: the inverse of load_official.

  out_dir (new; written atomically) gets config.json (the official constructor kwargs, as
  `save_pretrained` writes them: for a model read by load_official, the config.json it was read
  from, key for key, as long as that still describes the model), model.safetensors (every
  parameter and persistent buffer in float32 under its official name and layout, BatchNorm
  batch counts in int64; a tensor shared by several modules once, under the name safetensors
  keeps, the other names in the file's metadata; when `source` is a snapshot folder whose file
  describes the same tensors, its header bytes, so the alias order is the source's too) and a
  README.md model card naming `source`, `step` and the ufm_jax version. `variables`: as the
  loaders return them ({"params"[, "batch_stats"]}; a bare parameter tree is taken too). Returns
  notes for the user: the official kwargs written as
  defaults, the JAX-only options dropped, and where the official code builds a different model
  (see official_limits). Raises ValueError when config.json cannot describe the model (e.g. an
  encoder that is no DINOv2 hub size).
  """
  from safetensors.numpy import save_file
  variables = ufm.variables(keymap.unfreeze(variables))
  if getattr(model.config, "scan_blocks", False):  # official names are per layer
    from ufm_jax.models import scan
    variables = dict(variables, params=scan.unstack_blocks(variables["params"], model.config))
    model = model.clone(config=model.config.replace(scan_blocks=False))
  cfg = model.config
  class_name = official_config.class_name(model)
  state = {k: np.asarray(v, dtype=v.dtype if v.dtype == np.int64 else np.float32, order="C")
           for k, v in keymap.state_dict_from_params(variables,
                                                     official_config.ufm_buffers(cfg)).items()}
  with warnings.catch_warnings():   # reading our own export back: its warnings are not news
    warnings.simplefilter("ignore")
    cj, dropped, notes = None, [], []
    if cfg.official_kwargs is not None:
      try:   # the source's config.json, if it still describes this model
        # as written (sorted keys): a head's adaptors split its channels in config.json's order
        cj = json.loads(json.dumps(json.loads(cfg.official_kwargs), sort_keys=True))
        dropped = _check_export(model, variables, cj, state, class_name)
        notes = ["config.json: the source snapshot's, key for key"]
      except ValueError:
        cj = None
    if cj is None:
      cj = official_config.official_config_dict(cfg)
      dropped = _check_export(model, variables, cj, state, class_name)
      notes = [f"written with the official default (not in the JAX config): {k} = "
               f"{json.dumps(v)}" for k, v in official_config.OFFICIAL_DEFAULTS.items()]
  aliases = {a: k for k in sorted(state) for a in keymap.alias_keys(k)}
  notes += [f"not written (JAX-only option): {d}" for d in dropped]
  notes += [f"the official code cannot load this snapshot unchanged: {n}"
            for n in official_config.official_limits(cfg)]
  if official_config.random_view_rows(cfg.info_sharing):
    notes.append("the official forward draws view 2's embedding row at random "
                 "(use_rand_idx_pe_for_non_reference_views); ufm_jax uses row 1")

  with io.atomic_dir(out_dir) as tmp:
    (tmp / "config.json").write_text(json.dumps(cj, indent=2, sort_keys=True))
    save_file(state, str(tmp / "model.safetensors"), metadata=aliases or None)
    if source is not None:
      _header_as_in(tmp / "model.safetensors", pathlib.Path(source) / "model.safetensors")
    (tmp / "README.md").write_text(_model_card(class_name, source, step, notes))
  return notes
