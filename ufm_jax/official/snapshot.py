"""Official Hugging Face snapshots (config.json + model.safetensors, as `save_pretrained` writes
them): `load_official` reads one into (model, params), `save_official` writes one with a model
card, read back through the loader before anything is written.
"""

import dataclasses
import json
import pathlib
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


def read_snapshot(snapshot_dir) -> Tuple[dict, Dict[str, np.ndarray]]:
  d = pathlib.Path(snapshot_dir)
  cfg_path, w_path = d / "config.json", d / "model.safetensors"
  for p in (cfg_path, w_path):
    if not p.is_file():
      raise FileNotFoundError(f"{p} not found (expected a Hugging Face snapshot folder with "
                              "config.json and model.safetensors)")
  try:
    cj = json.loads(cfg_path.read_text())
  except json.JSONDecodeError as e:
    raise ValueError(f"{cfg_path}: invalid JSON ({e})") from e
  return cj, io.read_safetensors(w_path)


def load_official(snapshot_dir):
  """(model, params) from a Hugging Face snapshot of an official UFM release."""
  cj, state = read_snapshot(snapshot_dir)
  spec = official_config.official_spec(cj, state, f"{snapshot_dir}/config.json")
  params = keymap.params_from_state_dict(state, expected_param_shapes(spec.model), spec.buffers,
                                         f"{snapshot_dir}/model.safetensors")
  return spec.model, params


# UFMConfig fields a snapshot does not carry: compute options and initialisers (the encoder's
# LayerScale initial value included; the loader sets the hub's 1.0).
JAX_ONLY_FIELDS = ("dtype", "remat", "attention_impl", "refine_chunk", "encoder.pos_embed_init",
                   "encoder.init_values", "info_sharing.tied_qk_init")


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
  for k in sorted(set(ours) | set(back)):
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
  back_params = traverse_util.flatten_dict(keymap.params_from_state_dict(
      state, expected_param_shapes(spec.model), spec.buffers, "exported model.safetensors",
      as_jax=False))
  for path, v in traverse_util.flatten_dict(keymap.unfreeze(params)).items():
    if not np.array_equal(np.asarray(v, np.float32), back_params[path], equal_nan=True):
      raise ValueError(f"exported {keymap.path_to_torch_key(path)} does not read back to "
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


def save_official(model, params, out_dir, *, source: Optional[str] = None,
                  step: Optional[int] = None) -> List[str]:
  """Write (model, params) as an official Hugging Face snapshot: the inverse of load_official.

  out_dir (new; written atomically) gets config.json (the official constructor kwargs, as
  `save_pretrained` writes them), model.safetensors (every parameter and persistent buffer in
  float32 under its official name and layout; a tensor shared by several modules once, under the
  name safetensors keeps, the other names in the file's metadata) and a README.md model card
  naming `source`, `step` and the ufm_jax version. Returns notes for the user: the official
  kwargs written as defaults, the JAX-only options dropped, and where the official code builds a
  different model (see official_limits). Raises ValueError when config.json cannot describe the
  model (e.g. an encoder that is no DINOv2 hub size).
  """
  from safetensors.numpy import save_file
  params = keymap.unfreeze(params)
  if set(params) == {"params"}:   # the variables dict given to model.apply
    params = params["params"]
  if getattr(model.config, "scan_blocks", False):  # official names are per layer
    from ufm_jax.models import scan
    params = scan.unstack_blocks(params, model.config)
    model = model.clone(config=model.config.replace(scan_blocks=False))
  cfg = model.config
  class_name = official_config.class_name(model)
  cj = official_config.official_config_dict(cfg)
  state = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in keymap.state_dict_from_params(
      params, official_config.ufm_buffers(cfg)).items()}
  dropped = _check_export(model, params, cj, state, class_name)
  aliases = {a: k for k in sorted(state) for a in keymap.alias_keys(k)}
  notes = [f"written with the official default (not in the JAX config): {k} = {json.dumps(v)}"
           for k, v in official_config.OFFICIAL_DEFAULTS.items()]
  notes += [f"not written (JAX-only option): {d}" for d in dropped]
  notes += [f"the official code cannot load this snapshot unchanged: {n}"
            for n in official_config.official_limits(cfg)]

  with io.atomic_dir(out_dir) as tmp:
    (tmp / "config.json").write_text(json.dumps(cj, indent=2, sort_keys=True))
    save_file(state, str(tmp / "model.safetensors"), metadata=aliases or None)
    (tmp / "README.md").write_text(_model_card(class_name, source, step, notes))
  return notes

