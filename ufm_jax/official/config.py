"""Official config.json <-> our model configs, and the registry of official model classes.

`official_spec(config_json, state)` picks the builder of the first registered class whose
detector matches the config (`register_official_class` adds one) and returns the Flax model plus
the buffer tensors the file must hold; `official_config_dict(cfg)` is the inverse (the
constructor kwargs `save_pretrained` writes), with `official_limits(cfg)` saying where the
official code would build something else.
"""

import dataclasses
import json
import re
import warnings
from typing import Any, Callable, Dict, List, Tuple

import numpy as np

from ufm_jax.models import covariance, dinov2, dpt, info_sharing, refine, ufm

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


def check_keys(d: dict, known, where: str) -> None:
  """Refuses a config.json section with a key the loader does not know: an option it ignored
  could change the model's outputs without any error."""
  unknown = sorted(set(d) - set(known))
  if unknown:
    names = ", ".join(f"{where}.{k}" if where else k for k in unknown)
    raise ValueError(f"config.json: {names}: not an option "
                     f"this loader knows (known: {', '.join(sorted(known))}); refusing to load a "
                     "model whose structure it may not reproduce")


def _require(d: dict, key: str, ok, want: str, where: str) -> None:
  if key in d and not ok(d[key]):
    raise ValueError(f"config.json: {where}.{key}={d[key]!r} is not supported (expected {want})")


# Constructor kwargs of the official classes (UFM main 3732a50, UniCeption ee7fa0b) per section.
# Dropout rates, checkpointing and checkpoint paths are known but do not change the inference
# forward (from_pretrained loads model.safetensors over whatever a path would have loaded).
ENCODER_KEYS = ("name", "data_norm_type", "patch_size", "size", "with_registers",
                "norm_returned_features", "pretrained_checkpoint_path", "torch_hub_force_reload",
                "gradient_checkpointing", "keep_first_n_layers", "use_pytorch_sdpa",
                "disable_torch_compile_for_pe", "indices", "norm_intermediate",
                "intermediates_only")
INFO_SHARING_KEYS = ("name", "input_embed_dim", "size", "depth", "dim", "num_heads", "mlp_ratio",
                     "qkv_bias", "qk_norm", "proj_drop", "attn_drop", "init_values", "drop_path",
                     "custom_positional_encoding", "pretrained_checkpoint_path",
                     "gradient_checkpointing", "indices", "norm_intermediate",
                     "intermediates_only", "max_num_views", "max_num_views_for_pe", "num_views",
                     "distinguish_ref_and_non_ref_views", "use_pe_for_non_reference_views",
                     "use_rand_idx_pe_for_non_reference_views", "use_scalable_softmax",
                     "use_entropy_scaling", "base_token_count_for_entropy_scaling",
                     "entropy_scaling_growth_factor")
DPT_FEATURE_KEYS = ("patch_size", "main_tasks", "hooks", "input_feature_dims", "layer_dims",
                    "feature_dim", "use_bn", "output_width_ratio", "pretrained_checkpoint_path",
                    "checkpoint_gradient", "nonlinearity")
DPT_PROCESSOR_KEYS = ("input_feature_dim", "output_dim", "hidden_dims",
                      "pretrained_checkpoint_path", "checkpoint_gradient", "nonlinearity")
FLOW_ADAPTOR_KEYS = ("name", "flow_mean", "flow_std", "base_shape", "scale_strategy",
                     "output_normalized_coordinate")
COVARIANCE_ADAPTOR_KEYS = ("name", "parametrization", "low_confidence_init")
CLASSIFICATION_HEAD_KEYS = ("input_feature_dim", "patch_size", "output_dim", "mlp_ratio", "bias",
                            "drop", "pretrained_checkpoint_path")
BASE_KEYS = ("encoder_str", "encoder_kwargs", "info_sharing_and_head_structure",
             "info_sharing_str", "info_sharing_kwargs", "encoder_skip_connection",
             "info_sharing_skip_connection", "head_type", "feature_head_kwargs",
             "adaptors_kwargs", "detach_uncertainty_head", "uncertainty_head_type",
             "uncertainty_head_kwargs", "uncertainty_adaptors_kwargs",
             "pretrained_backbone_checkpoint_path", "pretrained_checkpoint_path",
             "inference_resolution")
# UniFlowMatch (ufm.py:130-152 at 3732a50): one head, no uncertainty head.
ONE_HEAD_KEYS = ("encoder_str", "encoder_kwargs", "info_sharing_and_head_structure",
                 "info_sharing_str", "info_sharing_kwargs", "encoder_skip_connection",
                 "info_sharing_skip_connection", "head_type", "feature_head_kwargs",
                 "adaptors_kwargs", "pretrained_checkpoint_path", "inference_resolution")
REFINE_KEYS = BASE_KEYS + ("temperature", "use_unet_feature", "use_unet_batchnorm",
                           "classification_head_type", "classification_head_kwargs",
                           "feature_combine_method", "refinement_range")
# UniCeption ee7fa0b's values for info-sharing kwargs a config.json leaves out.
MAX_NUM_VIEWS_DEFAULT = 1000
USE_RAND_IDX_DEFAULT = True


def encoder_config_from_official(enc: dict, shapes: dict, prefix: str = "encoder.model.",
                                 ) -> dinov2.DinoV2Config:
  check_keys(enc, ENCODER_KEYS, "encoder_kwargs")
  _require(enc, "data_norm_type", lambda v: v == "dinov2", "'dinov2'", "encoder_kwargs")
  _require(enc, "intermediates_only", lambda v: not v, "false (UFM uses the final output too)",
           "encoder_kwargs")
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
      indices=indices, norm_intermediate=bool(enc.get("norm_intermediate", True)),
      norm_returned_features=bool(enc.get("norm_returned_features", True)))


def _view_count(kw: dict) -> int:
  """The view-embedding table's rows: max_num_views (UniCeption < 0.1.6, renamed by UFM main) or
  max_num_views_for_pe or num_views, else UniCeption ee7fa0b's default."""
  given = {k: kw[k] for k in ("max_num_views", "max_num_views_for_pe", "num_views") if k in kw}
  if len(set(given.values())) > 1:
    raise ValueError(f"config.json: info_sharing_kwargs gives different view counts {given}")
  return int(next(iter(given.values()), MAX_NUM_VIEWS_DEFAULT))


def info_sharing_config_from_official(kw: dict, shapes: dict, prefix: str = "info_sharing."
                                      ) -> info_sharing.InfoSharingConfig:
  check_keys(kw, INFO_SHARING_KEYS, "info_sharing_kwargs")
  if kw.get("custom_positional_encoding") is not None:
    raise ValueError("config.json: info_sharing custom_positional_encoding (RoPE) is not supported")
  _require(kw, "intermediates_only", lambda v: not v, "false (UFM uses the final output too)",
           "info_sharing_kwargs")
  views = _view_count(kw)
  depth = _kw(kw, "depth", "info_sharing_kwargs", 12, required=False)
  indices = kw.get("indices")
  if indices is None:
    indices = tuple(range(depth))
  elif isinstance(indices, int):
    indices = tuple(range(depth - indices, depth))
  dim = _kw(kw, "dim", "info_sharing_kwargs", 768, required=False)
  cfg = info_sharing.InfoSharingConfig(
      input_embed_dim=_kw(kw, "input_embed_dim", "info_sharing_kwargs"), dim=dim, depth=depth,
      num_heads=_kw(kw, "num_heads", "info_sharing_kwargs", 12, required=False),
      mlp_ratio=float(kw.get("mlp_ratio", 4.0)), qkv_bias=bool(kw.get("qkv_bias", True)),
      qk_norm=bool(kw.get("qk_norm", False)), init_values=kw.get("init_values"),
      indices=tuple(indices), norm_intermediate=bool(kw.get("norm_intermediate", True)),
      max_num_views=views,
      distinguish_ref_and_non_ref_views=bool(kw.get("distinguish_ref_and_non_ref_views", True)),
      use_pe_for_non_reference_views=bool(kw.get("use_pe_for_non_reference_views", True)),
      use_rand_idx_pe_for_non_reference_views=bool(kw.get(
          "use_rand_idx_pe_for_non_reference_views", USE_RAND_IDX_DEFAULT)),
      use_scalable_softmax=bool(kw.get("use_scalable_softmax", False)),
      use_entropy_scaling=bool(kw.get("use_entropy_scaling", False)),
      base_token_count_for_entropy_scaling=int(kw.get("base_token_count_for_entropy_scaling",
                                                      444)),
      entropy_scaling_growth_factor=float(kw.get("entropy_scaling_growth_factor", 1.4)))
  if random_view_rows(cfg):
    warnings.warn(
        "config.json: info_sharing_kwargs.use_rand_idx_pe_for_non_reference_views is "
        f"{'true' if 'use_rand_idx_pe_for_non_reference_views' in kw else 'left out (default true)'}"
        f" with a {views}-row view table: the official forward draws view 2's embedding row at "
        f"random from rows 1..{views - 1} on every call, eval included, so its outputs change "
        "from run to run (by pixels). ufm_jax always uses row 1, the row of the fixed-index "
        "setting (docs/inference.md, 'Snapshots with random view embeddings').", stacklevel=3)
  return cfg


def random_view_rows(cfg: info_sharing.InfoSharingConfig) -> bool:
  """Whether the official forward of this configuration draws view 2's embedding row at random
  (more than one candidate row), which ufm_jax replaces by row 1."""
  return (cfg.use_rand_idx_pe_for_non_reference_views and cfg.distinguish_ref_and_non_ref_views
          and cfg.use_pe_for_non_reference_views and cfg.max_num_views > 2)


def dpt_config_from_official(kw: dict, where: str, patch_size: int) -> dpt.DPTConfig:
  check_keys(kw, ("dpt_feature", "dpt_processor"), where)
  feat, proc = kw.get("dpt_feature"), kw.get("dpt_processor")
  if feat is None or proc is None:
    raise ValueError(f"config.json: {where} needs dpt_feature and dpt_processor")
  check_keys(feat, DPT_FEATURE_KEYS, f"{where}.dpt_feature")
  check_keys(proc, DPT_PROCESSOR_KEYS, f"{where}.dpt_processor")
  if feat.get("use_bn", False):
    raise ValueError(f"config.json: {where}.dpt_feature.use_bn=True is not supported")
  if feat.get("output_width_ratio", 1) != 1:
    raise ValueError(f"config.json: {where}.dpt_feature.output_width_ratio != 1 is not supported")
  for sub, name in ((feat, "dpt_feature"), (proc, "dpt_processor")):
    _require(sub, "nonlinearity", lambda v: v == "relu", "'relu'", f"{where}.{name}")
  _require(feat, "patch_size", lambda v: v in (patch_size, [patch_size, patch_size]),
           f"the encoder patch size {patch_size}", f"{where}.dpt_feature")
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


def flow_adaptor_from_official(kw: dict, where: str) -> dpt.FlowAdaptorConfig:
  check_keys(kw, FLOW_ADAPTOR_KEYS, where)
  for key in ("flow_mean", "flow_std", "base_shape", "scale_strategy"):
    if key not in kw:
      raise ValueError(f"config.json: missing {where}.{key} (a FlowAdaptor argument)")
  if kw["scale_strategy"] not in dpt.SCALE_STRATEGIES:
    raise ValueError(f"config.json: {where}.scale_strategy={kw['scale_strategy']!r} is not a "
                     "FlowAdaptor scale strategy (UniCeption ee7fa0b implements "
                     f"{', '.join(repr(v) for v in dpt.SCALE_STRATEGIES)})")
  return dpt.FlowAdaptorConfig(
      flow_mean=tuple(float(v) for v in kw["flow_mean"]),
      flow_std=tuple(float(v) for v in kw["flow_std"]),
      base_shape=tuple(kw["base_shape"]),  # UniCeption's base_shape is already (H, W)
      scale_strategy=kw["scale_strategy"],
      output_normalized_coordinate=bool(kw.get("output_normalized_coordinate", False)))


def covariance_from_official(kw: dict, where: str) -> covariance.CovarianceConfig:
  """Covariance2DAdaptor kwargs; a parametrisation other than exp_tanh is refused by name."""
  check_keys(kw, COVARIANCE_ADAPTOR_KEYS, where)
  param = kw.get("parametrization", "exp_tanh")
  if param not in covariance.PARAMETRIZATIONS:
    raise ValueError(f"config.json: {where}.parametrization={param!r} is not supported (expected "
                     f"one of {', '.join(repr(p) for p in covariance.PARAMETRIZATIONS)})")
  return covariance.CovarianceConfig(parametrization=param,
                                     low_confidence_init=bool(kw.get("low_confidence_init", False)))


# The adaptors UniFlowMatchConfidence reads from each head (ufm.py:646-669 at 3732a50; the main
# head's flow_cov is what UniFlowMatch reads, ufm.py:431-434), by key: (class, allowed there).
ADAPTOR_CLASSES = {"flow": "FlowAdaptor", "flow_cov": "Covariance2DAdaptor",
                   "non_occluded_mask": "MaskAdaptor"}
HEAD_ADAPTORS = {"adaptors_kwargs": ("flow", "flow_cov"),
                 "uncertainty_adaptors_kwargs": ("flow_cov", "non_occluded_mask")}
# UniFlowMatch reads all three from its one head (ufm.py:427-440 at 3732a50).
ONE_HEAD_ADAPTORS = ("flow", "flow_cov", "non_occluded_mask")


def adaptors_from_official(adaptors: dict, where: str, allowed=None
                           ) -> Tuple[Tuple[str, ...], dict]:
  """A head's adaptor map -> (its keys in config.json's order: the order the official AdaptorMap
  splits the head's channels in, {key: our config of that adaptor}). `allowed`: the keys the
  class reads from this head (default: UniFlowMatchConfidence's, HEAD_ADAPTORS)."""
  allowed = HEAD_ADAPTORS[where] if allowed is None else allowed
  out = {}
  for key, spec in adaptors.items():
    if key not in allowed:
      classes = ", ".join(f"{a} ({ADAPTOR_CLASSES[a]})" for a in allowed)
      raise ValueError(f"config.json: {where}.{key}: not an adaptor this loader builds in this "
                       f"head (known: {classes})")
    check_keys(spec, ("class", "kwargs"), f"{where}.{key}")
    if spec.get("class") != ADAPTOR_CLASSES[key]:
      raise ValueError(f"config.json: {where}.{key}.class={spec.get('class')!r}; the official "
                       f"model reads {key!r} as a {ADAPTOR_CLASSES[key]}")
    kw = spec.get("kwargs", {})
    if kw.get("name", key) != key:
      raise ValueError(f"config.json: {where}.{key}.kwargs.name={kw['name']!r}; the official "
                       f"AdaptorMap keys outputs by this name, so it must be {key!r}")
    kw_where = f"{where}.{key}.kwargs"
    if key == "flow":
      out[key] = flow_adaptor_from_official(kw, kw_where)
    elif key == "flow_cov":
      out[key] = covariance_from_official(kw, kw_where)
    else:
      check_keys(kw, ("name",), kw_where)
      out[key] = None
  return tuple(adaptors), out


def ufm_config_from_official(cj: dict, shapes: dict, keys=BASE_KEYS,
                             main_adaptors=None) -> ufm.UFMConfig:
  """UFMConfig from an official config.json (+ weight shapes for what it cannot say).
  `keys`: the top-level keys of the class's constructor (anything else is refused);
  `main_adaptors`: the adaptors the class reads from its main head (default HEAD_ADAPTORS')."""
  check_keys(cj, keys, "")
  for key, want in (("encoder_str", "dinov2"), ("info_sharing_str", "global_attention"),
                    ("head_type", "dpt"), ("uncertainty_head_type", "dpt"),
                    ("info_sharing_and_head_structure", "dual+single")):
    if cj.get(key, want) != want:
      raise ValueError(f"config.json: {key}={cj[key]!r} is not supported (expected {want!r})")
  encoder = encoder_config_from_official(cj["encoder_kwargs"], shapes)
  main_order, main = adaptors_from_official(cj.get("adaptors_kwargs", {}), "adaptors_kwargs",
                                            main_adaptors)
  if "flow" not in main:
    raise ValueError("config.json: adaptors_kwargs has no 'flow' (FlowAdaptor)")
  covisibility, unc_order, unc = None, ("non_occluded_mask",), {}
  if cj.get("uncertainty_head_kwargs"):  # the refinement class may have none
    unc_order, unc = adaptors_from_official(cj.get("uncertainty_adaptors_kwargs", {}),
                                            "uncertainty_adaptors_kwargs")
    if not unc:
      raise ValueError("config.json: uncertainty_head_kwargs without uncertainty_adaptors_kwargs")
    covisibility = dpt_config_from_official(cj["uncertainty_head_kwargs"],
                                            "uncertainty_head_kwargs", encoder.patch_size)
  if "non_occluded_mask" in main and covisibility is not None:
    raise ValueError("config.json: adaptors_kwargs.non_occluded_mask with an uncertainty head; "
                     "the official classes with one read covisibility from that head only")
  if "flow_cov" in main and "flow_cov" in unc:
    raise ValueError("config.json: both adaptors_kwargs and uncertainty_adaptors_kwargs have a "
                     "'flow_cov'; UniFlowMatchConfidence reads the uncertainty head's only")
  flow_head = dpt_config_from_official(cj["feature_head_kwargs"], "feature_head_kwargs",
                                       encoder.patch_size)
  for where, order, head in (("feature_head_kwargs", main_order, flow_head),
                             ("uncertainty_head_kwargs", unc_order, covisibility)):
    want = sum(dpt.ADAPTOR_CHANNELS[k] for k in order)
    if head is not None and head.output_dim != want:
      raise ValueError(f"config.json: {where}.dpt_processor.output_dim={head.output_dim} but its "
                       f"adaptors {list(order)} take {want} channels")
  res = cj.get("inference_resolution") or (560, 420)  # official order is (W, H)
  # one (W, H) or a list of them (UniFlowMatchModelsBase picks the closest aspect per pair)
  res = (int(res[1]), int(res[0])) if isinstance(res[0], int) else tuple(
      (int(h), int(w)) for w, h in res)
  return ufm.UFMConfig(
      encoder=encoder,
      info_sharing=info_sharing_config_from_official(cj.get("info_sharing_kwargs", {}), shapes),
      flow_head=flow_head, covisibility_head=covisibility, flow_adaptor=main["flow"],
      flow_head_adaptors=main_order, uncertainty_head_adaptors=unc_order,
      flow_covariance=main.get("flow_cov", unc.get("flow_cov")),
      detach_uncertainty_head=bool(cj.get("detach_uncertainty_head", True)),
      inference_resolution=res)


def refine_config_from_official(cj: dict, shapes: dict, base: ufm.UFMConfig
                                ) -> refine.UFMRefineConfig:
  """The refiner's part of an official config.json; U-Net widths from the weight shapes."""
  if cj.get("classification_head_type", "patch_mlp") != "patch_mlp":
    raise ValueError(f"config.json: classification_head_type={cj['classification_head_type']!r} "
                     "is not supported (expected 'patch_mlp')")
  head = cj.get("classification_head_kwargs")
  if not head or "output_dim" not in head:
    raise ValueError("config.json: classification_head_kwargs.output_dim is missing")
  check_keys(head, CLASSIFICATION_HEAD_KEYS, "classification_head_kwargs")
  _require(head, "bias", bool, "true (the patch MLP's biases)", "classification_head_kwargs")
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
  method = cj.get("feature_combine_method", "conv")
  if method not in ("conv", "modulate"):
    raise ValueError(f"config.json: feature_combine_method={method!r} is not supported (expected "
                     "'conv' or 'modulate')")
  use_unet = bool(cj.get("use_unet_feature", False))   # the official default
  widths = refine.unet_widths(shapes) if use_unet else ()
  if use_unet and not widths:
    raise ValueError("config.json: use_unet_feature=True but model.safetensors has no "
                     "unet_feature.downs.0.conv.0.weight")
  fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(ufm.UFMConfig)}
  return refine.UFMRefineConfig(
      **fields, unet_features=widths, refine_feature_dim=int(head["output_dim"]),
      refine_mlp_ratio=float(head.get("mlp_ratio", 4.0)), use_unet_feature=use_unet,
      feature_combine_method=method,
      use_unet_batchnorm=use_unet and bool(cj.get("use_unet_batchnorm", False)),
      refinement_range=int(cj["refinement_range"]), temperature=float(cj["temperature"]))


def ufm_buffers(cfg: ufm.UFMConfig) -> Dict[str, np.ndarray]:
  """The persistent buffers of the official module (torch name -> value) cfg implies."""
  fa = cfg.flow_adaptor
  out = {
      "head1.1.adaptors.flow.flow_mean": np.array(fa.flow_mean, np.float32).reshape(1, 2, 1, 1),
      "head1.1.adaptors.flow.flow_std": np.array(fa.flow_std, np.float32).reshape(1, 2, 1, 1),
  }
  rows = info_sharing.view_table_rows(cfg.info_sharing)
  if rows:
    out["info_sharing.view_pos_table"] = info_sharing.sinusoid_table(rows, cfg.info_sharing.dim)
  return out


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
    "info_sharing_kwargs.pretrained_checkpoint_path": None,
    "feature_head_kwargs.dpt_feature.use_bn": False,
    "feature_head_kwargs.dpt_feature.output_width_ratio": 1,
    "uncertainty_head_kwargs.dpt_feature.use_bn": False,
    "uncertainty_head_kwargs.dpt_feature.output_width_ratio": 1,
    "pretrained_backbone_checkpoint_path": None,
    "pretrained_checkpoint_path": None,
}


def _official_resolution(res) -> list:
  """(H, W), or a tuple of them, in the official (W, H) order."""
  if isinstance(res[0], int):
    return [res[1], res[0]]
  return [[w, h] for h, w in res]


def _new_info_sharing_kwargs(s: info_sharing.InfoSharingConfig) -> dict:
  """The UniCeption 0.1.6 info-sharing kwargs that differ from their defaults there (older
  official code does not know them, so they are written only when they matter)."""
  new = {"distinguish_ref_and_non_ref_views": True, "use_pe_for_non_reference_views": True,
         "use_scalable_softmax": False, "use_entropy_scaling": False}
  out = {k: getattr(s, k) for k, default in new.items() if getattr(s, k) != default}
  if s.use_entropy_scaling:
    out["base_token_count_for_entropy_scaling"] = s.base_token_count_for_entropy_scaling
    out["entropy_scaling_growth_factor"] = s.entropy_scaling_growth_factor
  return out


def official_config_dict(cfg: ufm.UFMConfig) -> dict:
  """The official constructor kwargs (config.json) describing cfg; inverse of
  ufm_config_from_official (used to export and to test the loader on unseen structures)."""
  e, s, fa = cfg.encoder, cfg.info_sharing, cfg.flow_adaptor
  if cfg.uncertainty_cues:
    raise ValueError(f"UFMConfig.uncertainty_cues={tuple(cfg.uncertainty_cues)}: the official "
                     "uncertainty head reads only the trunk's features, so this model cannot be "
                     "exported")
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
  if not e.norm_returned_features:   # UniCeption >= 0.1.6 only: written when it matters
    enc["norm_returned_features"] = False
  adaptor_kwargs = {
      "flow": {"base_shape": list(fa.base_shape), "flow_mean": list(fa.flow_mean),
               "flow_std": list(fa.flow_std), "name": "flow",
               "output_normalized_coordinate": fa.output_normalized_coordinate,
               "scale_strategy": fa.scale_strategy},
      "non_occluded_mask": {"name": "non_occluded_mask"}}
  if cfg.flow_covariance is not None:
    adaptor_kwargs["flow_cov"] = {"low_confidence_init": cfg.flow_covariance.low_confidence_init,
                                  "name": "flow_cov",
                                  "parametrization": cfg.flow_covariance.parametrization}

  def adaptor_map(names, field):
    # save_pretrained writes config.json with sorted keys, and a reloaded model splits the
    # head's channels in that order: another order would reload as a different model.
    if list(names) != sorted(names):
      raise ValueError(f"{field}={tuple(names)}: an official config.json lists a head's adaptors "
                       f"sorted ({tuple(sorted(names))}), and the official AdaptorMap splits the "
                       "channels in that order, so this channel order cannot be exported")
    return {n: {"class": ADAPTOR_CLASSES[n], "kwargs": adaptor_kwargs[n]} for n in names}

  out = {
      "adaptors_kwargs": adaptor_map(cfg.flow_head_adaptors, "flow_head_adaptors"),
      "detach_uncertainty_head": cfg.detach_uncertainty_head,
      "encoder_kwargs": enc, "encoder_str": "dinov2",
      "feature_head_kwargs": head(cfg.flow_head), "head_type": "dpt",
      "inference_resolution": _official_resolution(cfg.inference_resolution),
      "info_sharing_and_head_structure": "dual+single",
      "info_sharing_kwargs": {
          "depth": s.depth, "dim": s.dim, "indices": list(s.indices),
          "init_values": s.init_values, "input_embed_dim": s.input_embed_dim,
          "max_num_views": s.max_num_views, "mlp_ratio": s.mlp_ratio, "name": "info_sharing",
          "norm_intermediate": s.norm_intermediate, "num_heads": s.num_heads,
          "qk_norm": s.qk_norm, "qkv_bias": s.qkv_bias,
          "use_rand_idx_pe_for_non_reference_views": s.use_rand_idx_pe_for_non_reference_views,
          **_new_info_sharing_kwargs(s)},
      "info_sharing_str": "global_attention",
      "uncertainty_adaptors_kwargs": (
          cfg.covisibility_head and adaptor_map(cfg.uncertainty_head_adaptors,
                                                "uncertainty_head_adaptors")),
      "uncertainty_head_kwargs": cfg.covisibility_head and head(cfg.covisibility_head),
      "uncertainty_head_type": "dpt",
  }
  if cfg.covisibility_head is None:   # the refinement class's defaults: no uncertainty head
    out["uncertainty_head_kwargs"], out["uncertainty_adaptors_kwargs"] = {}, {}
  for dotted, value in OFFICIAL_DEFAULTS.items():
    *parents, leaf = dotted.split(".")
    d = out
    for k in parents:
      d = d.get(k)
      if d is None:
        break
    else:
      d[leaf] = value
  for cls, extra, _ in OFFICIAL_CONFIG_EXTRAS:
    if isinstance(cfg, cls):
      out.update(extra(cfg))
  if is_one_head(cfg):   # UniFlowMatch's constructor takes none of the uncertainty keys
    out = {k: v for k, v in out.items() if k in ONE_HEAD_KEYS}
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
      # UFM main >= 3732a50 only: written when it matters
      **({"use_unet_batchnorm": True} if cfg.use_unet_batchnorm else {}),
  }


def refine_official_limits(cfg: refine.UFMRefineConfig) -> List[str]:
  """The refiner's part of official_limits."""
  if cfg.use_unet_feature and tuple(cfg.unet_features) != OFFICIAL_UNET_FEATURES:
    return [f"U-Net widths {list(cfg.unet_features)}: the official ufm.py hard-codes "
            f"{list(OFFICIAL_UNET_FEATURES)} (the refine fixture's README shows the substitution "
            "from_pretrained then needs)"]
  return []


def is_one_head(cfg: ufm.UFMConfig) -> bool:
  """Whether cfg is the one-head UniFlowMatch: no uncertainty head and not the refinement class
  (whose recipe model has no uncertainty head either)."""
  return cfg.covisibility_head is None and not isinstance(cfg, refine.UFMRefineConfig)


def _is_base(cj: dict) -> bool:
  return "uncertainty_head_kwargs" in cj and "refinement_range" not in cj


# Keys only the classes with an uncertainty head take (UniFlowMatchConfidence and the refiner).
_UNCERTAINTY_KEYS = ("detach_uncertainty_head", "uncertainty_head_type", "uncertainty_head_kwargs",
                     "uncertainty_adaptors_kwargs", "pretrained_backbone_checkpoint_path")


def _is_one_head(cj: dict) -> bool:
  return "refinement_range" not in cj and not any(k in cj for k in _UNCERTAINTY_KEYS)


def _build_one_head(cj: dict, shapes: dict) -> OfficialSpec:
  cfg = ufm_config_from_official(cj, shapes, ONE_HEAD_KEYS, ONE_HEAD_ADAPTORS)
  return OfficialSpec(ufm.UFM(cfg), ufm_buffers(cfg), "UniFlowMatch")


def _build_base(cj: dict, shapes: dict) -> OfficialSpec:
  cfg = ufm_config_from_official(cj, shapes, BASE_KEYS)
  return OfficialSpec(ufm.UFM(cfg), ufm_buffers(cfg), "UniFlowMatchConfidence")


def _is_refine(cj: dict) -> bool:
  return "refinement_range" in cj


def _build_refine(cj: dict, shapes: dict) -> OfficialSpec:
  cfg = refine_config_from_official(cj, shapes, ufm_config_from_official(cj, shapes, REFINE_KEYS))
  return OfficialSpec(refine.UFMRefine(cfg), ufm_buffers(cfg),
                      "UniFlowMatchClassificationRefinement")


# (detect(config_json) -> bool, build(config_json, shapes: {torch name: shape}) -> OfficialSpec);
# the first match wins, so the more specific detectors come first.
OFFICIAL_CLASSES: List[Tuple[Callable[[dict], bool], Callable[[dict, dict], OfficialSpec]]] = [
    (_is_refine, _build_refine),
    (_is_base, _build_base),
    (_is_one_head, _build_one_head),
]


# For model classes beyond the base one: (config class, fn(cfg) -> extra config.json keys,
# fn(cfg) -> what the official code builds differently, see official_limits).
OFFICIAL_CONFIG_EXTRAS: List[Tuple[type, Callable[[Any], dict], Callable[[Any], List[str]]]] = [
    (refine.UFMRefineConfig, refine_config_to_official, refine_official_limits),
]


# Flax module class -> the official class name stored in model_config.json.
CLASS_NAMES: Dict[type, str] = {ufm.UFM: "UniFlowMatchConfidence",
                                refine.UFMRefine: "UniFlowMatchClassificationRefinement"}


def class_name(model) -> str:
  """The official class name of a Flax model (what config.json and model_config.json record)."""
  if type(model) not in CLASS_NAMES:
    raise ValueError(f"no official class name registered for {type(model).__name__}")
  if is_one_head(model.config):
    return "UniFlowMatch"
  return CLASS_NAMES[type(model)]


def official_spec(cj: dict, state: Dict[str, np.ndarray], where: str = "config.json"
                  ) -> OfficialSpec:
  """The model a snapshot's config.json and weights (`state`: torch name -> array) describe."""
  shapes = {k: tuple(v.shape) for k, v in state.items()}
  for detect, build in OFFICIAL_CLASSES:
    if detect(cj):
      with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        spec = build(cj, shapes)
      for w in caught:   # name the file (the builders know only the config's contents)
        warnings.warn(str(w.message).replace("config.json:", f"{where}:", 1), w.category,
                      stacklevel=2)
      if hasattr(spec.model.config, "official_kwargs"):
        # save_official writes this text back while it still describes the model
        config = dataclasses.replace(spec.model.config, official_kwargs=json.dumps(cj))
        spec = dataclasses.replace(spec, model=spec.model.clone(config=config))
      return spec
  raise ValueError(f"{where}: no supported UFM model class matches this config (keys: "
                   f"{sorted(cj)})")

