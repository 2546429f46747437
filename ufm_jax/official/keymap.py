"""The official key map: PyTorch state-dict names and layouts <-> Flax param paths and arrays.

One rule each:
  1. aliases: `scratch.layer{k}_rn.*` / `scratch.layer_rn.{k-1}.*` -> `input_process.{k-1}.1.*`
     (one module registered three times; safetensors keeps only the alphabetically first name);
  2. prefixes: `encoder.model.` -> `encoder.`;
  3. split on ".", a numeric part joins the previous one with "_" (`blocks.3` -> `blocks_3`,
     `head1.0.0` -> `head1_0_0`), the leaf `weight` becomes `kernel` (Linear, Conv) or `scale`
     (LayerNorm);
  4. layouts: Linear [out, in] -> [in, out]; Conv OIHW -> HWIO; ConvTranspose [in, out, kh, kw]
     -> [kh, kw, in, out].
Buffers (view_pos_table, flow_mean/flow_std) are not parameters: `params_from_state_dict` checks
them against the values the config implies. BatchNorm running statistics go to the
"batch_stats" collection under the same rules. No model code is imported here, so the model modules
map their own released weights with it (`ufm_jax.official.dinov2_weights.load`).
"""

import functools
import re
from typing import Any, Dict, List, Tuple

import jax.numpy as jnp
import numpy as np
from flax import traverse_util

# One module registered under several names: (alias, canonical) name templates, {i} the 0-based
# DPT level and {i1} = i + 1. The canonical name is the one safetensors keeps (alphabetically
# first); `save_pretrained` records every other name in the file's metadata as alias -> kept.
ALIASES = [
    ("scratch.layer{i1}_rn.", "input_process.{i}.1."),
    ("scratch.layer_rn.{i}.", "input_process.{i}.1."),
]
PREFIXES = [("encoder.model.", "encoder.")]


# Weights stored [in, out, kh, kw] by torch ConvTranspose2d: the DPT's first two levels and the
# refiner's U-Net up-convolutions (the even `ups` entries; the odd ones are DoubleConvs).
CONV_TRANSPOSE = [re.compile(r"input_process\.[01]\.0\.1\.weight$"),
                  re.compile(r"^unet_feature\.ups\.\d*[02468]\.weight$")]


@functools.lru_cache(maxsize=None)
def _template_regex(template: str) -> "re.Pattern":
  parts = re.split(r"(\{i1?\})", template)
  return re.compile("".join(r"(?P<%s>\d+)" % p[1:-1] if p in ("{i}", "{i1}") else re.escape(p)
                            for p in parts))


def _level(m: "re.Match") -> int:
  groups = m.groupdict()
  return int(groups["i"]) if "i" in groups else int(groups["i1"]) - 1


def canonical_key(key: str) -> str:
  for alias, canonical in ALIASES:
    key = _template_regex(alias).sub(lambda m: canonical.format(i=_level(m)), key)
  return key


def alias_keys(key: str) -> List[str]:
  """The other names of the tensor stored as canonical `key` (inverse of canonical_key)."""
  out = []
  for alias, canonical in ALIASES:
    for m in _template_regex(canonical).finditer(key):
      i = _level(m)
      out.append(key[:m.start()] + alias.format(i=i, i1=i + 1) + key[m.end():])
  return out


def torch_key_to_path(key: str, ndim: int) -> Tuple[str, ...]:
  key = canonical_key(key)
  for old, new in PREFIXES:
    if key.startswith(old):
      key = new + key[len(old):]
  out: List[str] = []
  for part in key.split("."):
    if part.isdigit() and out:
      out[-1] += "_" + part
    else:
      out.append(part)
  if out[-1] == "weight":
    out[-1] = "kernel" if ndim >= 2 else "scale"
  return tuple(out)


def path_to_torch_key(path: Tuple[str, ...]) -> str:
  """Inverse of torch_key_to_path (the canonical, de-duplicated name)."""
  parts = list(path)
  if parts[-1] in ("kernel", "scale"):
    parts[-1] = "weight"
  key = ".".join(re.sub(r"_(\d+)", r".\1", p) for p in parts)
  for old, new in PREFIXES:
    if key.startswith(new):
      key = old + key[len(new):]
  return key


def torch_to_flax_array(key: str, value: np.ndarray) -> np.ndarray:
  if value.ndim == 2 and key.endswith("weight"):
    return value.T
  if value.ndim == 4 and key.endswith("weight"):
    if any(p.search(canonical_key(key)) for p in CONV_TRANSPOSE):
      return value.transpose(2, 3, 0, 1)
    return value.transpose(2, 3, 1, 0)
  return value


def flax_to_torch_array(key: str, value: np.ndarray) -> np.ndarray:
  if value.ndim == 2 and key.endswith("weight"):
    return value.T
  if value.ndim == 4 and key.endswith("weight"):
    if any(p.search(key) for p in CONV_TRANSPOSE):
      return value.transpose(2, 3, 0, 1)
    return value.transpose(3, 2, 0, 1)
  return value


def unfreeze(tree):
  """Nested mappings (FrozenDict included) -> plain dicts."""
  return {k: unfreeze(v) for k, v in tree.items()} if hasattr(tree, "items") else tree


# BatchNorm statistics: torch buffers, Flax variables of the "batch_stats" collection.
BATCH_STATS = ("running_mean", "running_var", "num_batches_tracked")


def variable_path(key: str, ndim: int) -> Tuple[str, ...]:
  """(collection, *Flax path) of a torch state-dict entry."""
  path = torch_key_to_path(key, ndim)
  return ("batch_stats" if path[-1] in BATCH_STATS else "params",) + path


def flat_variables(params) -> Dict[Tuple[str, ...], Any]:
  """{(collection, *path): leaf} of a parameter tree or of a variables dict with "params"."""
  tree = unfreeze(params)
  if "params" not in tree:
    tree = {"params": tree}
  return traverse_util.flatten_dict(tree)


def params_from_state_dict(state: Dict[str, np.ndarray], expected: Dict[Tuple[str, ...], tuple],
                           buffers: Dict[str, np.ndarray], source: str = "state dict",
                           as_jax: bool = True):
  """Map a torch-named state dict onto the variables with the `expected` {(collection, *Flax
  path): shape}; raise listing every problem. Returns the variables {"params"[,
  "batch_stats"]}.

  as_jax=False returns numpy views of `state` (no copy), for checking an export."""
  flat: Dict[Tuple[str, ...], np.ndarray] = {}
  origin: Dict[Tuple[str, ...], str] = {}
  unexpected, misshaped, bad_buffers = [], [], []
  for key in sorted(state):
    value = np.asarray(state[key])
    if key in buffers:
      want = buffers[key]
      if value.shape != want.shape or not np.allclose(value, want, rtol=0, atol=1e-6):
        bad_buffers.append(f"{key} {value.shape} (differs from the value implied by config.json)")
      continue
    path = variable_path(key, value.ndim)
    arr = torch_to_flax_array(key, value)
    if path not in expected:
      unexpected.append(f"{key} {tuple(value.shape)}")
      continue
    if path in flat:  # an alias of a tensor already read (shared module saved twice)
      if not np.array_equal(flat[path], arr):
        misshaped.append(f"{key}: differs from its alias {origin[path]}")
      continue
    if tuple(arr.shape) != expected[path]:
      misshaped.append(f"{key}: file {tuple(value.shape)} -> {tuple(arr.shape)}, model expects "
                       f"{expected[path]} at {'/'.join(path)}")
      continue
    flat[path], origin[path] = arr, key
  missing = [f"{path_to_torch_key(p[1:])} (Flax {'/'.join(p)} {expected[p]})"
             for p in sorted(expected) if p not in flat and not any(
                 m.startswith(path_to_torch_key(p[1:]) + ":") for m in misshaped)]
  missing_buffers = [k for k in buffers if k not in state]
  if unexpected or misshaped or missing or bad_buffers or missing_buffers:
    lines = [f"{source} does not match the model built from its config:"]
    for title, items in (("missing", missing + missing_buffers), ("unexpected", unexpected),
                         ("mis-shaped", misshaped), ("wrong buffer values", bad_buffers)):
      if items:
        lines.append(f"  {title} ({len(items)}):")
        lines.extend(f"    {s}" for s in items)
    raise ValueError("\n".join(lines))
  return traverse_util.unflatten_dict({k: jnp.asarray(v) if as_jax else v
                                       for k, v in flat.items()})


def state_dict_from_params(params, buffers: Dict[str, np.ndarray]) -> Dict[str, np.ndarray]:
  """Flax params (or variables with "batch_stats") -> torch-named state dict (canonical,
  de-duplicated names) plus buffers; BatchNorm batch counts as int64, as torch keeps them."""
  out = {}
  for path, v in flat_variables(params).items():
    key = path_to_torch_key(path[1:])
    v = np.asarray(v)
    if path[-1] == "num_batches_tracked":
      v = v.astype(np.int64)
    out[key] = np.asarray(flax_to_torch_array(key, v), order="C")
  out.update({k: np.asarray(v) for k, v in buffers.items()})
  return out
