"""Official PyTorch UFM checkpoints (Hugging Face snapshot: config.json + model.safetensors) <->
(Flax model, params); and the orbax checkpoint format of this project.

    model, params = load_official("path/to/UFM-Base")      # HF snapshot folder
    python -m ufm_jax.convert SNAPSHOT_DIR OUT_DIR          # -> orbax params + model_config.json
    model, params = load(OUT_DIR)
    save_official(model, params, "path/to/export")         # the inverse: a new HF snapshot

Key map (PyTorch state-dict name -> Flax param path), one rule each:
  1. aliases: `scratch.layer{k}_rn.*` / `scratch.layer_rn.{k-1}.*` -> `input_process.{k-1}.1.*`
     (one module registered three times; safetensors keeps only the alphabetically first name);
  2. prefixes: `encoder.model.` -> `encoder.`;
  3. split on ".", a numeric part joins the previous one with "_" (`blocks.3` -> `blocks_3`,
     `head1.0.0` -> `head1_0_0`), the leaf `weight` becomes `kernel` (Linear, Conv) or `scale`
     (LayerNorm);
  4. layouts: Linear [out, in] -> [in, out]; Conv OIHW -> HWIO; ConvTranspose [in, out, kh, kw]
     -> [kh, kw, in, out].
Buffers (view_pos_table, flow_mean/flow_std) are not parameters: they are checked against the
values the config implies. Other official model classes register a builder with
`register_official_class` (dispatch on config.json).

The export (save_official) runs the same rules backwards (path_to_torch_key, flax_to_torch_array,
alias_keys, official_config_dict) and then reads its result back with the loader before writing.
Released DINOv2 weights (transformers or original names) go through the same key map into the
encoder (read_dinov2, dinov2_to_flax, resize_pos_embed): `model_init: dinov2:PATH` of
ufm_jax.checkpoint.
"""

import dataclasses
import functools
import json
import os
import pathlib
import re
import shutil
import sys
import tempfile
from typing import Any, Callable, Dict, List, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from ufm_jax.models import dinov2, dpt, info_sharing, refine, ufm

# ----------------------------------------------------------------------------- key map

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
# Tensors that are not Flax params: name regex -> fn(config, match) -> expected value.
BufferFn = Callable[[Any, "re.Match"], np.ndarray]


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


# ----------------------------------------------------------------------------- model classes


@dataclasses.dataclass
class OfficialSpec:
  """What a builder returns: the Flax model plus the buffer tensors it expects in the file."""
  model: Any
  buffers: Dict[str, np.ndarray]  # exact torch name -> expected value
  class_name: str


def register_official_class(detect, build, front: bool = True):
  """Add a builder; front=True lets a more specific detector win over the base one."""
  if front:
    OFFICIAL_CLASSES.insert(0, (detect, build))
  else:
    OFFICIAL_CLASSES.append((detect, build))


def _kw(d: dict, key: str, where: str, default=None, required=True):
  if key in d:
    return d[key]
  if required and default is None:
    raise ValueError(f"config.json: missing {where}.{key}")
  return default


def encoder_config_from_official(enc: dict, shapes: dict, prefix: str = "encoder.model.",
                                 ) -> dinov2.DinoV2Config:
  size = _kw(enc, "size", "encoder_kwargs")
  if size not in dinov2.SIZES:
    raise ValueError(f"config.json: encoder_kwargs.size={size!r}; expected one of "
                     f"{sorted(dinov2.SIZES)}")
  dim, _, heads, _ = dinov2.SIZES[size]
  blocks = {int(m.group(1)) for k in shapes for m in [re.match(re.escape(prefix) + r"blocks\.(\d+)\.", k)] if m}
  if not blocks:
    raise ValueError(f"model.safetensors has no {prefix}blocks.* tensors")
  depth = max(blocks) + 1  # after keep_first_n_layers
  keep = enc.get("keep_first_n_layers")
  if keep is not None and keep != depth:
    raise ValueError(f"config.json keep_first_n_layers={keep} but model.safetensors has "
                     f"{depth} encoder blocks")
  pos = shapes.get(prefix + "pos_embed")
  if pos is None:
    raise ValueError(f"model.safetensors has no {prefix}pos_embed")
  grid = int(round(np.sqrt(pos[1] - 1)))
  if grid * grid != pos[1] - 1 or pos[2] != dim:
    raise ValueError(f"{prefix}pos_embed has shape {pos}; expected (1, 1 + G*G, {dim}) for "
                     f"DINOv2 {size}")
  reg = shapes.get(prefix + "register_tokens")
  n_reg = reg[1] if reg is not None else 0
  if bool(enc.get("with_registers", False)) != bool(n_reg):
    raise ValueError(f"config.json with_registers={enc.get('with_registers')} but "
                     f"model.safetensors has {n_reg} register tokens")
  patch = shapes[prefix + "patch_embed.proj.weight"][-1]
  if enc.get("patch_size", patch) != patch:
    raise ValueError(f"config.json patch_size={enc.get('patch_size')} but the patch embedding "
                     f"kernel is {patch}x{patch}")
  ffn = "swiglu" if any(k.startswith(prefix + "blocks.0.mlp.w12") for k in shapes) else "mlp"
  ls = any(k.startswith(prefix + "blocks.0.ls1") for k in shapes)
  indices = enc.get("indices", 1)
  indices = indices if isinstance(indices, int) else tuple(indices)
  return dinov2.DinoV2Config(
      embed_dim=dim, depth=depth, num_heads=heads, ffn=ffn, patch_size=patch, pos_grid=grid,
      num_register_tokens=n_reg, init_values=1.0 if ls else None,
      # facebookresearch/dinov2 hubconf: *_reg models use antialias=True, offset 0.0.
      interpolate_antialias=bool(n_reg), interpolate_offset=0.0 if n_reg else 0.1,
      indices=indices, norm_intermediate=bool(enc.get("norm_intermediate", True)))


def info_sharing_config_from_official(kw: dict, shapes: dict,
                                      prefix: str = "info_sharing.") -> info_sharing.InfoSharingConfig:
  if kw.get("custom_positional_encoding") is not None:
    raise ValueError("config.json: info_sharing custom_positional_encoding (RoPE) is not supported")
  views = kw.get("max_num_views", kw.get("max_num_views_for_pe", kw.get("num_views", 2)))
  if kw.get("use_rand_idx_pe_for_non_reference_views") and views > 2:
    raise ValueError("config.json: random view-index embeddings are not supported")
  depth = _kw(kw, "depth", "info_sharing_kwargs", 12, required=False)
  indices = kw.get("indices")
  if indices is None:
    indices = tuple(range(depth))
  elif isinstance(indices, int):
    indices = tuple(range(depth - indices, depth))
  dim = _kw(kw, "dim", "info_sharing_kwargs", 768, required=False)
  return info_sharing.InfoSharingConfig(
      input_embed_dim=_kw(kw, "input_embed_dim", "info_sharing_kwargs"), dim=dim, depth=depth,
      num_heads=_kw(kw, "num_heads", "info_sharing_kwargs", 12, required=False),
      mlp_ratio=float(kw.get("mlp_ratio", 4.0)), qkv_bias=bool(kw.get("qkv_bias", True)),
      qk_norm=bool(kw.get("qk_norm", False)), init_values=kw.get("init_values"),
      indices=tuple(indices), norm_intermediate=bool(kw.get("norm_intermediate", True)),
      max_num_views=views)


def dpt_config_from_official(kw: dict, where: str) -> dpt.DPTConfig:
  feat, proc = kw.get("dpt_feature"), kw.get("dpt_processor")
  if feat is None or proc is None:
    raise ValueError(f"config.json: {where} needs dpt_feature and dpt_processor")
  if feat.get("use_bn", False):
    raise ValueError(f"config.json: {where}.dpt_feature.use_bn=True is not supported")
  if feat.get("output_width_ratio", 1) != 1:
    raise ValueError(f"config.json: {where}.dpt_feature.output_width_ratio != 1 is not supported")
  dims = feat.get("input_feature_dims", 768)
  dims = (dims,) * 4 if isinstance(dims, int) else tuple(dims)
  if proc.get("input_feature_dim", feat.get("feature_dim", 256)) != feat.get("feature_dim", 256):
    raise ValueError(f"config.json: {where} processor input dim != dpt_feature.feature_dim")
  hidden = proc.get("hidden_dims")
  return dpt.DPTConfig(
      input_feature_dims=dims, layer_dims=tuple(feat.get("layer_dims", (96, 192, 384, 768))),
      feature_dim=feat.get("feature_dim", 256), hooks=tuple(feat.get("hooks", (0, 1, 2, 3))),
      output_dim=_kw(proc, "output_dim", f"{where}.dpt_processor"),
      hidden_dims=tuple(hidden) if hidden else None)


def flow_adaptor_from_official(adaptors: dict) -> dpt.FlowAdaptorConfig:
  if set(adaptors) != {"flow"} or adaptors["flow"].get("class") != "FlowAdaptor":
    raise ValueError(f"config.json: adaptors_kwargs {adaptors}; only a single FlowAdaptor named "
                     "'flow' is supported")
  kw = adaptors["flow"]["kwargs"]
  return dpt.FlowAdaptorConfig(
      flow_mean=tuple(float(v) for v in kw["flow_mean"]),
      flow_std=tuple(float(v) for v in kw["flow_std"]),
      base_shape=tuple(kw["base_shape"]),  # UniCeption's base_shape is already (H, W)
      scale_strategy=kw["scale_strategy"],
      output_normalized_coordinate=bool(kw.get("output_normalized_coordinate", False)))


def ufm_config_from_official(cj: dict, shapes: dict) -> ufm.UFMConfig:
  """UFMConfig from an official config.json (+ weight shapes for what it cannot say)."""
  for key, want in (("encoder_str", "dinov2"), ("info_sharing_str", "global_attention"),
                    ("head_type", "dpt"), ("uncertainty_head_type", "dpt"),
                    ("info_sharing_and_head_structure", "dual+single")):
    if cj.get(key, want) != want:
      raise ValueError(f"config.json: {key}={cj[key]!r} is not supported (expected {want!r})")
  unc = cj.get("uncertainty_adaptors_kwargs", {})
  if set(unc) != {"non_occluded_mask"} or unc["non_occluded_mask"].get("class") != "MaskAdaptor":
    raise ValueError(f"config.json: uncertainty_adaptors_kwargs {unc}; only a MaskAdaptor "
                     "'non_occluded_mask' is supported")
  w, h = cj.get("inference_resolution") or (560, 420)  # official order is (W, H)
  return ufm.UFMConfig(
      encoder=encoder_config_from_official(cj["encoder_kwargs"], shapes),
      info_sharing=info_sharing_config_from_official(cj.get("info_sharing_kwargs", {}), shapes),
      flow_head=dpt_config_from_official(cj["feature_head_kwargs"], "feature_head_kwargs"),
      covisibility_head=dpt_config_from_official(cj["uncertainty_head_kwargs"],
                                                 "uncertainty_head_kwargs"),
      flow_adaptor=flow_adaptor_from_official(cj["adaptors_kwargs"]),
      detach_uncertainty_head=bool(cj.get("detach_uncertainty_head", True)),
      inference_resolution=(int(h), int(w)))


def refine_config_from_official(cj: dict, shapes: dict, base: ufm.UFMConfig
                                ) -> refine.UFMRefineConfig:
  """The refiner's part of an official config.json; U-Net widths from the weight shapes."""
  if cj.get("classification_head_type", "patch_mlp") != "patch_mlp":
    raise ValueError(f"config.json: classification_head_type={cj['classification_head_type']!r} "
                     "is not supported (expected 'patch_mlp')")
  head = cj.get("classification_head_kwargs")
  if not head or "output_dim" not in head:
    raise ValueError("config.json: classification_head_kwargs.output_dim is missing")
  for key in ("refinement_range", "temperature"):
    if key not in cj:
      raise ValueError(f"config.json: {key} is missing (a UniFlowMatchClassificationRefinement "
                       "config names it)")
  patch = head.get("patch_size", base.encoder.patch_size)
  if patch != base.encoder.patch_size:
    raise ValueError(f"config.json: classification_head_kwargs.patch_size={patch} but the encoder "
                     f"patch size is {base.encoder.patch_size}")
  in_dim = head.get("input_feature_dim")
  want = base.encoder.embed_dim + base.info_sharing.dim
  if isinstance(in_dim, str):   # the official configs write e.g. "1024 + 768"
    in_dim = sum(int(t) for t in in_dim.split("+"))
  if in_dim is not None and in_dim != want:
    raise ValueError(f"config.json: classification_head_kwargs.input_feature_dim={in_dim} but "
                     f"encoder ({base.encoder.embed_dim}) + info sharing ({base.info_sharing.dim}) "
                     f"= {want}")
  use_unet = bool(cj.get("use_unet_feature", True))
  widths = refine.unet_widths(shapes) if use_unet else ()
  if use_unet and not widths:
    raise ValueError("config.json: use_unet_feature=True but model.safetensors has no "
                     "unet_feature.downs.0.conv.0.weight")
  fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(ufm.UFMConfig)}
  return refine.UFMRefineConfig(
      **fields, unet_features=widths, refine_feature_dim=int(head["output_dim"]),
      refine_mlp_ratio=float(head.get("mlp_ratio", 4.0)), use_unet_feature=use_unet,
      feature_combine_method=cj.get("feature_combine_method", "conv"),
      refinement_range=int(cj["refinement_range"]), temperature=float(cj["temperature"]))


def ufm_buffers(cfg: ufm.UFMConfig) -> Dict[str, np.ndarray]:
  fa = cfg.flow_adaptor
  return {
      "info_sharing.view_pos_table": info_sharing.sinusoid_table(
          cfg.info_sharing.max_num_views, cfg.info_sharing.dim),
      "head1.1.adaptors.flow.flow_mean": np.array(fa.flow_mean, np.float32).reshape(1, 2, 1, 1),
      "head1.1.adaptors.flow.flow_std": np.array(fa.flow_std, np.float32).reshape(1, 2, 1, 1),
  }


# Official constructor kwargs that the JAX config does not carry: an exported config.json gets
# these values (the official defaults; the loader rejects other values of use_bn,
# output_width_ratio, custom_positional_encoding and the random view embedding).
OFFICIAL_DEFAULTS = {
    "encoder_kwargs.data_norm_type": "dinov2",
    "encoder_kwargs.pretrained_checkpoint_path": None,
    "info_sharing_kwargs.attn_drop": 0.0,
    "info_sharing_kwargs.proj_drop": 0.0,
    "info_sharing_kwargs.drop_path": 0.0,
    "info_sharing_kwargs.custom_positional_encoding": None,
    "info_sharing_kwargs.use_rand_idx_pe_for_non_reference_views": False,
    "info_sharing_kwargs.pretrained_checkpoint_path": None,
    "feature_head_kwargs.dpt_feature.use_bn": False,
    "feature_head_kwargs.dpt_feature.output_width_ratio": 1,
    "uncertainty_head_kwargs.dpt_feature.use_bn": False,
    "uncertainty_head_kwargs.dpt_feature.output_width_ratio": 1,
    "pretrained_backbone_checkpoint_path": None,
    "pretrained_checkpoint_path": None,
}
def official_config_dict(cfg: ufm.UFMConfig) -> dict:
  """The official constructor kwargs (config.json) describing cfg; inverse of
  ufm_config_from_official (used to export and to test the loader on unseen structures)."""
  e, s, fa = cfg.encoder, cfg.info_sharing, cfg.flow_adaptor
  size = {v[0]: k for k, v in dinov2.SIZES.items()}.get(e.embed_dim)
  if size is None or dinov2.SIZES[size][2] != e.num_heads:
    raise ValueError(f"encoder width {e.embed_dim} / {e.num_heads} heads is not a DINOv2 hub size "
                     f"(expected one of {[(k, v[0], v[2]) for k, v in dinov2.SIZES.items()]}); "
                     "the official UFM classes cannot build this encoder")
  full_depth = dinov2.SIZES[size][1]

  def head(d: dpt.DPTConfig):
    proc = {"input_feature_dim": d.feature_dim, "output_dim": d.output_dim}
    if d.hidden_dims:
      proc["hidden_dims"] = list(d.hidden_dims)
    return {"dpt_feature": {"feature_dim": d.feature_dim, "hooks": list(d.hooks),
                            "input_feature_dims": list(d.input_feature_dims),
                            "layer_dims": list(d.layer_dims), "patch_size": e.patch_size},
            "dpt_processor": proc}

  enc = {"name": f"dinov2_{size}", "norm_intermediate": e.norm_intermediate,
         "patch_size": e.patch_size, "size": size, "with_registers": bool(e.num_register_tokens),
         "indices": e.indices if isinstance(e.indices, int) else list(e.indices)}
  if e.depth != full_depth:
    enc["keep_first_n_layers"] = e.depth
  out = {
      "adaptors_kwargs": {"flow": {"class": "FlowAdaptor", "kwargs": {
          "base_shape": list(fa.base_shape), "flow_mean": list(fa.flow_mean),
          "flow_std": list(fa.flow_std), "name": "flow",
          "output_normalized_coordinate": fa.output_normalized_coordinate,
          "scale_strategy": fa.scale_strategy}}},
      "detach_uncertainty_head": cfg.detach_uncertainty_head,
      "encoder_kwargs": enc, "encoder_str": "dinov2",
      "feature_head_kwargs": head(cfg.flow_head), "head_type": "dpt",
      "inference_resolution": [cfg.inference_resolution[1], cfg.inference_resolution[0]],
      "info_sharing_and_head_structure": "dual+single",
      "info_sharing_kwargs": {
          "depth": s.depth, "dim": s.dim, "indices": list(s.indices),
          "init_values": s.init_values, "input_embed_dim": s.input_embed_dim,
          "max_num_views": s.max_num_views, "mlp_ratio": s.mlp_ratio, "name": "info_sharing",
          "norm_intermediate": s.norm_intermediate, "num_heads": s.num_heads,
          "qk_norm": s.qk_norm, "qkv_bias": s.qkv_bias},
      "info_sharing_str": "global_attention",
      "uncertainty_adaptors_kwargs": {"non_occluded_mask": {
          "class": "MaskAdaptor", "kwargs": {"name": "non_occluded_mask"}}},
      "uncertainty_head_kwargs": head(cfg.covisibility_head), "uncertainty_head_type": "dpt",
  }
  for dotted, value in OFFICIAL_DEFAULTS.items():
    *parents, leaf = dotted.split(".")
    d = out
    for k in parents:
      d = d[k]
    d[leaf] = value
  for cls, extra, _ in OFFICIAL_CONFIG_EXTRAS:
    if isinstance(cfg, cls):
      out.update(extra(cfg))
  return out


def official_limits(cfg: ufm.UFMConfig) -> List[str]:
  """Where the official code builds something else than cfg whatever config.json says (such a
  snapshot round-trips through load_official, but `from_pretrained` needs the official code
  patched, as the refine fixture's README describes for its U-Net)."""
  e = cfg.encoder
  size = {v[0]: k for k, v in dinov2.SIZES.items()}[e.embed_dim]
  out = []
  # torch.hub DINOv2: img_size 518, patch 14, LayerScale, 4 registers in the *_reg models.
  if (e.patch_size, e.pos_grid) != (14, 37):
    out.append(f"encoder patch size {e.patch_size} / position grid {e.pos_grid}x{e.pos_grid}: "
               "torch.hub DINOv2 has 14 px patches and a 37x37 grid")
  if e.init_values is None:
    out.append("encoder without LayerScale: torch.hub DINOv2 blocks always have ls1/ls2")
  if e.num_register_tokens not in (0, 4):
    out.append(f"encoder with {e.num_register_tokens} register tokens: the hub's *_reg models "
               "have 4")
  if e.ffn != dinov2.SIZES[size][3]:
    out.append(f"encoder FFN {e.ffn!r}: the hub's {size} model has {dinov2.SIZES[size][3]!r}")
  for cls, _, limits in OFFICIAL_CONFIG_EXTRAS:
    if isinstance(cfg, cls):
      out.extend(limits(cfg))
  return out


# The official ufm.py builds UNet(features=[64, 128, 256, 512]) whatever config.json says.
OFFICIAL_UNET_FEATURES = (64, 128, 256, 512)


def refine_config_to_official(cfg: refine.UFMRefineConfig) -> dict:
  """The refiner's config.json keys (inverse of refine_config_from_official)."""
  ratio = float(cfg.refine_mlp_ratio)
  return {
      # Written as the official configs write them: "1024 + 768" and an integral ratio as int.
      "classification_head_kwargs": {
          "input_feature_dim": f"{cfg.encoder.embed_dim} + {cfg.info_sharing.dim}",
          "mlp_ratio": int(ratio) if ratio.is_integer() else ratio,
          "output_dim": cfg.refine_feature_dim, "patch_size": cfg.encoder.patch_size},
      "classification_head_type": "patch_mlp",
      "feature_combine_method": cfg.feature_combine_method,
      "refinement_range": cfg.refinement_range,
      "temperature": float(cfg.temperature),
      "use_unet_feature": cfg.use_unet_feature,
  }


def refine_official_limits(cfg: refine.UFMRefineConfig) -> List[str]:
  """The refiner's part of official_limits."""
  if cfg.use_unet_feature and tuple(cfg.unet_features) != OFFICIAL_UNET_FEATURES:
    return [f"U-Net widths {list(cfg.unet_features)}: the official ufm.py hard-codes "
            f"{list(OFFICIAL_UNET_FEATURES)} (the refine fixture's README shows the substitution "
            "from_pretrained then needs)"]
  return []


def _is_base(cj: dict) -> bool:
  return "uncertainty_head_kwargs" in cj and "refinement_range" not in cj


def _build_base(cj: dict, shapes: dict) -> OfficialSpec:
  cfg = ufm_config_from_official(cj, shapes)
  return OfficialSpec(ufm.UFM(cfg), ufm_buffers(cfg), "UniFlowMatchConfidence")


def _is_refine(cj: dict) -> bool:
  return "refinement_range" in cj


def _build_refine(cj: dict, shapes: dict) -> OfficialSpec:
  cfg = refine_config_from_official(cj, shapes, ufm_config_from_official(cj, shapes))
  return OfficialSpec(refine.UFMRefine(cfg), ufm_buffers(cfg),
                      "UniFlowMatchClassificationRefinement")


# (detect(config_json) -> bool, build(config_json, shapes: {torch name: shape}) -> OfficialSpec);
# the first match wins, so the more specific detectors come first.
OFFICIAL_CLASSES: List[Tuple[Callable[[dict], bool], Callable[[dict, dict], OfficialSpec]]] = [
    (_is_refine, _build_refine),
    (_is_base, _build_base),
]
# For model classes beyond the base one: (config class, fn(cfg) -> extra config.json keys,
# fn(cfg) -> what the official code builds differently, see official_limits).
OFFICIAL_CONFIG_EXTRAS: List[Tuple[type, Callable[[Any], dict], Callable[[Any], List[str]]]] = [
    (refine.UFMRefineConfig, refine_config_to_official, refine_official_limits),
]
# class name -> (config_from_dict, model_from_config) for checkpoints written by `save`.
SAVED_CLASSES: Dict[str, Tuple[Callable, Callable]] = {
    "UniFlowMatchConfidence": (ufm.config_from_dict, ufm.model_from_config),
    "UniFlowMatchClassificationRefinement": (refine.refine_config_from_dict,
                                             refine.refine_model_from_config),
}
# Flax module class -> the official class name stored in model_config.json.
CLASS_NAMES: Dict[type, str] = {ufm.UFM: "UniFlowMatchConfidence",
                                refine.UFMRefine: "UniFlowMatchClassificationRefinement"}

# ----------------------------------------------------------------------------- loading


def expected_param_shapes(model) -> Dict[Tuple[str, ...], Tuple[int, ...]]:
  """{Flax path: shape} of the model's parameters (ufm.param_shapes, flattened)."""
  return {k: tuple(v.shape) for k, v in traverse_util.flatten_dict(ufm.param_shapes(model)).items()}


def _unfreeze(tree):
  return {k: _unfreeze(v) for k, v in tree.items()} if hasattr(tree, "items") else tree


def params_from_state_dict(state: Dict[str, np.ndarray], model, buffers: Dict[str, np.ndarray],
                           source: str = "state dict", as_jax: bool = True):
  """Map a torch-named state dict onto the model's parameter tree; raise listing every problem.

  as_jax=False returns numpy views of `state` (no copy), for checking an export."""
  expected = expected_param_shapes(model)
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
    path = torch_key_to_path(key, value.ndim)
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
  missing = [f"{path_to_torch_key(p)} (Flax {'/'.join(p)} {expected[p]})"
             for p in sorted(expected) if p not in flat and not any(
                 m.startswith(path_to_torch_key(p) + ":") for m in misshaped)]
  missing_buffers = [k for k in buffers if k not in state]
  if unexpected or misshaped or missing or bad_buffers or missing_buffers:
    lines = [f"{source} does not match the model built from its config:"]
    for title, items in (("missing", missing + missing_buffers), ("unexpected", unexpected),
                         ("mis-shaped", misshaped), ("wrong buffer values", bad_buffers)):
      if items:
        lines.append(f"  {title} ({len(items)}):")
        lines.extend(f"    {s}" for s in items)
    raise ValueError("\n".join(lines))
  return traverse_util.unflatten_dict({k: jnp.asarray(v) if as_jax else v for k, v in flat.items()})


def state_dict_from_params(params, buffers: Dict[str, np.ndarray]) -> Dict[str, np.ndarray]:
  """Flax params -> torch-named state dict (canonical, de-duplicated names) plus buffers."""
  out = {}
  for path, v in traverse_util.flatten_dict(_unfreeze(params)).items():
    key = path_to_torch_key(path)
    out[key] = np.ascontiguousarray(flax_to_torch_array(key, np.asarray(v)))
  out.update({k: np.asarray(v) for k, v in buffers.items()})
  return out


def read_safetensors(path) -> Dict[str, np.ndarray]:
  """All tensors of a .safetensors file (numpy); a damaged file's error names it and, when its
  header promises more bytes than it has, the expected and actual sizes."""
  from safetensors.numpy import load_file
  path = pathlib.Path(path)
  try:
    return load_file(str(path))
  except Exception as e:  # safetensors raises its own error types
    raise ValueError(f"{path}: cannot read safetensors ({e}){_truncation_hint(path)}") from e


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
  return cj, read_safetensors(w_path)


def _truncation_hint(path: pathlib.Path) -> str:
  """'; the file looks truncated: ...' when its header promises more bytes than it has."""
  size = path.stat().st_size
  try:
    with open(path, "rb") as f:
      n = int.from_bytes(f.read(8), "little")
      header = json.loads(f.read(n)) if 0 < n <= size - 8 else None
  except (OSError, ValueError):
    header = None
  if header is None:
    return ""
  ends = [int(v["data_offsets"][1]) for k, v in header.items()
          if k != "__metadata__" and isinstance(v, dict) and "data_offsets" in v]
  expected = 8 + n + max(ends, default=0)
  if size < expected:
    return (f"; the file looks truncated: its header describes {expected:,} bytes, the file has "
            f"{size:,} (an interrupted download?)")
  return ""


def official_spec(cj: dict, state: Dict[str, np.ndarray], where: str = "config.json"
                  ) -> OfficialSpec:
  shapes = {k: tuple(v.shape) for k, v in state.items()}
  for detect, build in OFFICIAL_CLASSES:
    if detect(cj):
      return build(cj, shapes)
  raise ValueError(f"{where}: no supported UFM model class matches this config (keys: "
                   f"{sorted(cj)})")


def load_official(snapshot_dir):
  """(model, params) from a Hugging Face snapshot of an official UFM release."""
  cj, state = read_snapshot(snapshot_dir)
  spec = official_spec(cj, state, f"{snapshot_dir}/config.json")
  params = params_from_state_dict(state, spec.model, spec.buffers,
                                  f"{snapshot_dir}/model.safetensors")
  return spec.model, params


# ----------------------------------------------------------------------------- DINOv2 weights
# Released DINOv2 checkpoints -> the official (UniCeption) names, then the key map above: the
# encoder part of `model_init: dinov2:PATH` (ufm_jax.checkpoint).


def _dinov2_hf_to_original(sd: Dict[str, np.ndarray]) -> Dict[str, np.ndarray]:
  """transformers Dinov2Model names -> the original facebookresearch/dinov2 names."""
  out: Dict[str, np.ndarray] = {}
  qkv: dict[str, Dict[str, np.ndarray]] = {}
  simple = {
      "embeddings.cls_token": "cls_token",
      "embeddings.mask_token": "mask_token",
      "embeddings.position_embeddings": "pos_embed",
      "embeddings.register_tokens": "register_tokens",
      "embeddings.patch_embeddings.projection.weight": "patch_embed.proj.weight",
      "embeddings.patch_embeddings.projection.bias": "patch_embed.proj.bias",
      "layernorm.weight": "norm.weight",
      "layernorm.bias": "norm.bias",
  }
  layer = {
      "norm1": "norm1", "norm2": "norm2",
      "attention.output.dense": "attn.proj",
      "layer_scale1.lambda1": "ls1.gamma", "layer_scale2.lambda1": "ls2.gamma",
      "mlp.fc1": "mlp.fc1", "mlp.fc2": "mlp.fc2",
      "mlp.weights_in": "mlp.w12", "mlp.weights_out": "mlp.w3",  # SwiGLU (ViT-g)
  }
  for key, val in sd.items():
    k = key[len("dinov2."):] if key.startswith("dinov2.") else key
    if k in simple:
      out[simple[k]] = val
      continue
    m = re.fullmatch(r"encoder\.layer\.(\d+)\.(.+)", k)
    if not m:
      out[f"unmapped:{key}"] = val
      continue
    i, rest = m.groups()
    a = re.fullmatch(r"attention\.attention\.(query|key|value)\.(weight|bias)", rest)
    if a:
      qkv.setdefault(f"blocks.{i}.attn.qkv.{a.group(2)}", {})[a.group(1)] = val
      continue
    for src, dst in layer.items():
      if rest.startswith(src + ".") or rest == src:
        out[f"blocks.{i}.{dst}{rest[len(src):]}"] = val
        break
    else:
      out[f"unmapped:{key}"] = val
  for name, parts in qkv.items():
    if set(parts) != {"query", "key", "value"}:
      raise ValueError(f"DINOv2 checkpoint: incomplete q/k/v for {name}: has {sorted(parts)}")
    out[name] = np.concatenate([parts["query"], parts["key"], parts["value"]], axis=0)
  return out


def _dinov2_original_flatten_chunks(sd):
  """Chunked checkpoints ("blocks.<chunk>.<i>.") -> flat block indices."""
  if not any(re.match(r"blocks\.\d+\.\d+\.", k) for k in sd):
    return sd
  return {re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k): v for k, v in sd.items()}


def read_dinov2(path) -> Dict[str, np.ndarray]:
  """DINOv2 weights in the original naming (numpy), from HF safetensors or an original .pth."""
  path = pathlib.Path(path)
  if path.is_dir():
    cands = sorted(path.glob("*.safetensors")) + sorted(path.glob("*.pth"))
    if not cands:
      raise FileNotFoundError(f"no *.safetensors or *.pth DINOv2 weights in {path}")
    path = cands[0]
  if path.suffix == ".safetensors":
    sd = read_safetensors(path)
    if any(k.startswith(("embeddings.", "dinov2.embeddings.")) for k in sd):
      sd = _dinov2_hf_to_original(sd)
  elif path.suffix in (".pth", ".pt"):
    try:
      import torch
    except ImportError as e:
      raise ImportError(f"reading {path} needs torch (pip install 'ufm_jax[torch]'); or use the "
                        "Hugging Face facebook/dinov2-* model.safetensors instead") from e
    obj = torch.load(str(path), map_location="cpu", weights_only=True)
    obj = obj.get("model", obj) if isinstance(obj, dict) else obj
    sd = {k: v.float().numpy() if v.is_floating_point() else v.numpy() for k, v in obj.items()}
  else:
    raise ValueError(f"unknown DINOv2 checkpoint format: {path} (want .safetensors or .pth)")
  sd = _dinov2_original_flatten_chunks(sd)
  unmapped = [k for k in sd if k.startswith("unmapped:")]
  if unmapped:
    raise ValueError(f"{path}: keys with no DINOv2 counterpart: {unmapped[:10]}")
  return sd


def dinov2_to_flax(sd: Dict[str, np.ndarray]) -> Dict[str, np.ndarray]:
  """Original DINOv2 names -> flat "a/b/c" paths of the UFM encoder, via the model's key map."""
  out = {}
  for k, v in sd.items():
    if k == "mask_token":  # deleted by UniCeption: UFM has no masked-token path
      continue
    key = f"encoder.model.{k}"
    out["/".join(torch_key_to_path(key, v.ndim))] = torch_to_flax_array(key, v)
  return out


def resize_pos_embed(pe: np.ndarray, new_shape) -> np.ndarray:
  """[1, extra + g*g, D] -> [1, extra + g'*g', D]: bicubic on the square grid, extra tokens kept."""
  pe = np.asarray(pe, np.float32)
  n_old, n_new = pe.shape[1], new_shape[1]
  for extra in (1, 0):
    g_old, g_new = np.sqrt(n_old - extra), np.sqrt(n_new - extra)
    if g_old == int(g_old) and g_new == int(g_new):
      g_old, g_new = int(g_old), int(g_new)
      grid = pe[0, extra:].reshape(g_old, g_old, -1)
      grid = jax.image.resize(jnp.asarray(grid), (g_new, g_new, grid.shape[-1]), "cubic")
      return np.concatenate([pe[0, :extra], np.asarray(grid).reshape(g_new * g_new, -1)])[None]
  raise ValueError(f"cannot resize position embedding {pe.shape} -> {tuple(new_shape)}")


# ----------------------------------------------------------------------------- orbax format

CONFIG_FILE = "model_config.json"
PARAMS_DIR = "params"



def _class_name(model) -> str:
  if type(model) not in CLASS_NAMES:
    raise ValueError(f"no checkpoint class name registered for {type(model).__name__}")
  return CLASS_NAMES[type(model)]


def _write_new_dir(out_dir, write: Callable[[pathlib.Path], None]) -> pathlib.Path:
  """write(tmp) fills a temp folder beside out_dir, which is then renamed to out_dir (never
  overwritten); on any error nothing is left behind."""
  out = pathlib.Path(out_dir).absolute()
  if out.exists():
    raise FileExistsError(f"{out} already exists; refusing to overwrite a checkpoint")
  out.parent.mkdir(parents=True, exist_ok=True)
  tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
  try:
    write(tmp)
    os.replace(tmp, out)
  except BaseException:
    shutil.rmtree(tmp, ignore_errors=True)
    raise
  return out


def save(out_dir, model, params, class_name: Optional[str] = None):
  """Write params (orbax) + model_config.json into a new folder, atomically (temp + rename)."""
  import orbax.checkpoint as ocp

  def write(tmp):
    ocp.PyTreeCheckpointer().save(tmp / PARAMS_DIR, jax.tree.map(np.asarray, params))
    meta = {"class": class_name or _class_name(model), "config": dataclasses.asdict(model.config)}
    (tmp / CONFIG_FILE).write_text(json.dumps(meta, indent=2))

  _write_new_dir(out_dir, write)


def load(ckpt_dir):
  """(model, params) from a folder written by `save` / `python -m ufm_jax.convert`."""
  import orbax.checkpoint as ocp
  d = pathlib.Path(ckpt_dir).absolute()
  cfg_path = d / CONFIG_FILE
  if not cfg_path.is_file():
    raise FileNotFoundError(f"{cfg_path} not found (not a checkpoint written by "
                            "`python -m ufm_jax.convert`)")
  meta = json.loads(cfg_path.read_text())
  if meta.get("class") not in SAVED_CLASSES:
    raise ValueError(f"{cfg_path}: unknown model class {meta.get('class')!r}; known: "
                     f"{sorted(SAVED_CLASSES)}")
  from_dict, build = SAVED_CLASSES[meta["class"]]
  model = build(from_dict(meta["config"]))
  # Saved as numpy arrays: orbax restores them as numpy without a target tree.
  params = _unfreeze(ocp.PyTreeCheckpointer().restore(d / PARAMS_DIR))
  got = {k: tuple(np.shape(v)) for k, v in traverse_util.flatten_dict(params).items()}
  want = expected_param_shapes(model)
  if got != want:
    bad = sorted(set(got) ^ set(want)) + sorted(k for k in set(got) & set(want)
                                                 if got[k] != want[k])
    raise ValueError(f"{d / PARAMS_DIR}: parameters do not match the model of {cfg_path}: "
                     + ", ".join("/".join(k) for k in bad[:20]))
  params = jax.tree.map(jnp.asarray, params)
  return model, params


# ----------------------------------------------------------------------------- export

# UFMConfig fields a snapshot does not carry: compute options and initialisers (the encoder's
# LayerScale initial value included; the loader sets the hub's 1.0).
JAX_ONLY_FIELDS = ("dtype", "remat", "attention_impl", "refine_chunk", "encoder.pos_embed_init",
                   "encoder.init_values", "info_sharing.tied_qk_init")


def _check_export(model, params, cj: dict, state: Dict[str, np.ndarray], class_name: str
                  ) -> List[str]:
  """Reads an export back as load_official would: the same class, config and params, or raise.
  Returns the JAX-only config values that the snapshot drops."""
  spec = official_spec(cj, state, "exported config.json")
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
  back_params = traverse_util.flatten_dict(params_from_state_dict(state, spec.model, spec.buffers,
                                                "exported model.safetensors", as_jax=False))
  for path, v in traverse_util.flatten_dict(_unfreeze(params)).items():
    if not np.array_equal(np.asarray(v, np.float32), back_params[path], equal_nan=True):
      raise ValueError(f"exported {path_to_torch_key(path)} does not read back to "
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
  params = _unfreeze(params)
  if set(params) == {"params"}:   # the variables dict given to model.apply
    params = params["params"]
  if getattr(model.config, "scan_blocks", False):  # official names are per layer
    from ufm_jax.models import scan
    params = scan.unstack_blocks(params, model.config)
    model = model.clone(config=model.config.replace(scan_blocks=False))
  cfg = model.config
  class_name = _class_name(model)
  cj = official_config_dict(cfg)
  state = {k: np.ascontiguousarray(v, dtype=np.float32)
           for k, v in state_dict_from_params(params, ufm_buffers(cfg)).items()}
  dropped = _check_export(model, params, cj, state, class_name)
  aliases = {a: k for k in sorted(state) for a in alias_keys(k)}
  notes = [f"written with the official default (not in the JAX config): {k} = {json.dumps(v)}"
           for k, v in OFFICIAL_DEFAULTS.items()]
  notes += [f"not written (JAX-only option): {d}" for d in dropped]
  notes += [f"the official code cannot load this snapshot unchanged: {n}"
            for n in official_limits(cfg)]

  def write(tmp):
    (tmp / "config.json").write_text(json.dumps(cj, indent=2, sort_keys=True))
    save_file(state, str(tmp / "model.safetensors"), metadata=aliases or None)
    (tmp / "README.md").write_text(_model_card(class_name, source, step, notes))

  _write_new_dir(out_dir, write)
  return notes


def convert_snapshot(snapshot_dir, out_dir) -> str:
  """Official snapshot -> orbax checkpoint + model_config.json; returns a one-line summary."""
  model, params = load_official(snapshot_dir)
  save(out_dir, model, params)
  n = sum(int(np.prod(v.shape)) for v in jax.tree.leaves(params))
  return f"wrote {out_dir} ({type(model).__name__}, {n:,} parameters)"


def main(argv=None):
  """`python -m ufm_jax.convert ...` is `python -m ufm_jax convert ...`."""
  from ufm_jax import cli
  return cli.main(["convert", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
  sys.exit(main())
