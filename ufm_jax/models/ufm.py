"""UFM (`UniFlowMatchConfidence`): DINOv2 encoder -> two-view info sharing -> DPT flow head and
DPT covisibility head; without the covisibility head (`covisibility_head=None`) the one-head
`UniFlowMatch`, whose main head may also hold the covisibility ("non_occluded_mask") and the flow
covariance ("flow_cov") channels.

Contract: `model.apply(variables(params), source, target)` with [B, H, W, 3] uint8 (or float
0..255) images, H and W multiples of the patch size, returns
{"flow" [B, H, W, 2] (pixels, u then v), "covisibility" [B, H, W], "covisibility_logits" [B, H, W]}
(no covisibility without a non_occluded_mask adaptor: `UFMConfig.has_covisibility`), and for a
model with a flow covariance adaptor (`flow_covariance` set) "flow_covariance" [B, H, W, 3] =
(var_x, var_y, cov_xy) in px^2, "flow_covariance_log_det" [B, H, W] and "flow_covariance_params"
[B, H, W, 3] (models/covariance.py).
ImageNet normalisation of x / 255 happens inside.
Internals are sown into the "intermediates" collection (read them with `mutable=["intermediates"]`).
`params` is the parameter tree, or for models with BatchNorm (a refiner with
`use_unet_batchnorm`) the variables {"params", "batch_stats"}: see `variables`.
"""

import dataclasses
import json
import re
from typing import Any, Dict, Mapping, Optional, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from ufm_jax.models import covariance, dinov2, dpt, layers, sampling, scan
from ufm_jax.models import info_sharing as info_sharing_lib

# UniCeption data_norm_type "dinov2" (ImageNet), float32 like the official tensors.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16, "float64": jnp.float64}


@dataclasses.dataclass(frozen=True)
class UFMConfig:
  """Structure of a UFM model plus compute options (dtype, remat) that do not change params."""
  encoder: dinov2.DinoV2Config = dinov2.DinoV2Config()
  info_sharing: info_sharing_lib.InfoSharingConfig = info_sharing_lib.InfoSharingConfig()
  flow_head: dpt.DPTConfig = dpt.DPTConfig(output_dim=2)
  # None: no uncertainty head (the official refinement training recipe); no covisibility output.
  covisibility_head: Optional[dpt.DPTConfig] = dpt.DPTConfig(output_dim=1)
  flow_adaptor: dpt.FlowAdaptorConfig = dpt.FlowAdaptorConfig()
  detach_uncertainty_head: bool = True
  # Per-pixel cues the uncertainty head reads beside the trunk's features, concatenated after
  # its processor's upsampling (sampling.CUE_CHANNELS: "warp_residual", "flow_edges"; computed
  # from the images and the predicted flow with no gradient into the flow). Not in the official
  # model: () for every official structure.
  uncertainty_cues: Tuple[str, ...] = ()
  # Each head's adaptors in the order they take its output channels (the official AdaptorMap
  # splits them in the order of config.json's keys, which save_pretrained sorts): "flow" (2
  # channels), "flow_cov" (3), "non_occluded_mask" (1). The head's output_dim is their sum.
  flow_head_adaptors: Tuple[str, ...] = ("flow",)
  uncertainty_head_adaptors: Tuple[str, ...] = ("non_occluded_mask",)
  # The Covariance2DAdaptor's kwargs when a head has "flow_cov" (models/covariance.py), else None.
  flow_covariance: Optional[covariance.CovarianceConfig] = None
  # (H, W) used by ufm_jax.predict, or several: predict picks the closest aspect ratio per pair.
  inference_resolution: Tuple[int, int] = (420, 560)
  # Compute dtype of encoder + info sharing: "float32", "bfloat16" (heads stay float32, as the
  # official autocast does), or "float64" (everything; needs jax_enable_x64, for testing).
  dtype: str = "float32"
  remat: bool = False  # gradient checkpointing per transformer block
  # None or "auto": cuDNN fused attention on GPU when dtype and head size allow, else the
  # cache-blocked loop on CPU and XLA's on other platforms (layers.attention_implementation);
  # "xla", "cudnn" or "cpu" force one.
  attention_impl: Optional[str] = None
  # Encoder and fusion blocks as one stacked parameter tree run by lax.scan (models/scan.py):
  # one compiled block body instead of 24 + 12. Changes the param layout (scan.stack_blocks).
  scan_blocks: bool = False
  # Compute dtype of the DPT heads: "float32" (as the official code, even under autocast) or
  # "bfloat16" (half the head activation memory); params and outputs stay float32.
  head_dtype: str = "float32"
  # Initializers of a fresh model (`UFM.init`): "flax" (the modules' flax defaults, lecun_normal)
  # or "official" (as the official PyTorch modules: `official_init`). Pretrained weights loaded
  # afterwards replace either.
  param_init: str = "flax"
  # The official config.json this model was read from (JSON text), kept so that save_official
  # writes it back as the official code wrote it while it still describes the model. Not part
  # of the structure: equality, hashing and repr ignore it.
  official_kwargs: Optional[str] = dataclasses.field(default=None, compare=False, hash=False,
                                                     repr=False)

  def __post_init__(self):
    if self.dtype not in DTYPES:
      raise ValueError(f"UFMConfig.dtype {self.dtype!r}; expected one of {sorted(DTYPES)}")
    if self.head_dtype not in ("float32", "bfloat16"):
      raise ValueError(f"UFMConfig.head_dtype {self.head_dtype!r}; expected 'float32' or "
                       "'bfloat16'")
    if self.attention_impl not in layers.ATTENTION_IMPLS:
      raise ValueError(f"UFMConfig.attention_impl {self.attention_impl!r}; expected one of "
                       f"{layers.ATTENTION_IMPLS}")
    if self.param_init not in ("flax", "official"):
      raise ValueError(f"UFMConfig.param_init {self.param_init!r}; expected 'flax' or 'official'")
    if self.param_init == "official" and self.info_sharing.tied_qk_init is not None:
      raise ValueError("UFMConfig: param_init='official' redraws the fusion transformer, which "
                       "discards info_sharing.tied_qk_init; set one of them")
    if len(self.info_sharing.indices) != 2:
      raise ValueError("UFM feeds exactly two info-sharing intermediates to the DPT heads; "
                       f"got info_sharing.indices={self.info_sharing.indices}")
    _check_adaptors(self)
    unknown = [c for c in self.uncertainty_cues if c not in sampling.CUE_CHANNELS]
    if unknown or len(set(self.uncertainty_cues)) != len(self.uncertainty_cues):
      raise ValueError(f"UFMConfig.uncertainty_cues={tuple(self.uncertainty_cues)}: each cue once, "
                       f"of {', '.join(sampling.CUE_CHANNELS)}")
    if self.uncertainty_cues and self.covisibility_head is None:
      raise ValueError("UFMConfig.uncertainty_cues needs an uncertainty head (covisibility_head)")

  @property
  def has_flow_covariance(self) -> bool:
    return self.flow_covariance is not None

  @property
  def has_covisibility(self) -> bool:
    """Whether the model predicts covisibility: a non_occluded_mask adaptor in the uncertainty
    head, or in the main head of a model without one (UniFlowMatch)."""
    if self.covisibility_head is not None:
      return "non_occluded_mask" in self.uncertainty_head_adaptors
    return "non_occluded_mask" in self.flow_head_adaptors

  def replace(self, **kw) -> "UFMConfig":
    """dataclasses.replace; a mapping for a sub-config (e.g. flow_adaptor={"flow_std": ...},
    as a training config's `model` block gives it) replaces only the fields it names."""
    for k, v in kw.items():
      if k in _SUB and isinstance(v, Mapping):
        fields = {kk: _tuplify(vv) for kk, vv in v.items()}
        current = getattr(self, k)
        kw[k] = _SUB[k](**fields) if current is None else dataclasses.replace(current, **fields)
      elif isinstance(v, list):
        kw[k] = _tuplify(v)
    return dataclasses.replace(self, **kw)


_SUB = {"encoder": dinov2.DinoV2Config, "info_sharing": info_sharing_lib.InfoSharingConfig,
        "flow_head": dpt.DPTConfig, "covisibility_head": dpt.DPTConfig,
        "flow_adaptor": dpt.FlowAdaptorConfig, "flow_covariance": covariance.CovarianceConfig}


def _check_adaptors(cfg: UFMConfig) -> None:
  """ValueError naming the field when the heads' adaptor lists do not describe the heads."""
  heads = {"flow_head_adaptors": (cfg.flow_head_adaptors, cfg.flow_head, "flow_head")}
  if cfg.covisibility_head is not None:
    heads["uncertainty_head_adaptors"] = (cfg.uncertainty_head_adaptors, cfg.covisibility_head,
                                          "covisibility_head")
  for field, (names, head, head_field) in heads.items():
    unknown = [n for n in names if n not in dpt.ADAPTOR_CHANNELS]
    if unknown or len(set(names)) != len(names):
      raise ValueError(f"UFMConfig.{field}={tuple(names)}: each adaptor once, of "
                       f"{', '.join(dpt.ADAPTOR_CHANNELS)}")
    want = sum(dpt.ADAPTOR_CHANNELS[n] for n in names)
    if head.output_dim != want:
      raise ValueError(f"UFMConfig.{head_field}.output_dim={head.output_dim} but its adaptors "
                       f"{field}={tuple(names)} take {want} channels")
  if "flow" not in cfg.flow_head_adaptors:
    raise ValueError(f"UFMConfig.flow_head_adaptors={cfg.flow_head_adaptors} has no 'flow'")
  if "non_occluded_mask" in cfg.flow_head_adaptors and cfg.covisibility_head is not None:
    raise ValueError("UFMConfig.flow_head_adaptors: a 'non_occluded_mask' in the main head goes "
                     "with no uncertainty head (UniFlowMatch); UniFlowMatchConfidence reads "
                     "covisibility from its uncertainty head")
  if "flow" in cfg.uncertainty_head_adaptors:
    raise ValueError("UFMConfig.uncertainty_head_adaptors: the flow comes from the main head")
  where = [f for f, (names, _, _) in heads.items() if "flow_cov" in names]
  if len(where) > 1:
    raise ValueError("UFMConfig: 'flow_cov' in both heads' adaptors; one head predicts it")
  if bool(where) != (cfg.flow_covariance is not None):
    raise ValueError(
        f"UFMConfig.flow_covariance={cfg.flow_covariance} but "
        + (f"{where[0]} has a 'flow_cov' adaptor" if where else "no head has a 'flow_cov' adaptor")
        + ": set both or neither (ufm.with_flow_covariance does)")


def with_flow_covariance(cfg: UFMConfig, head: str = "uncertainty",
                         low_confidence_init: bool = True) -> UFMConfig:
  """`cfg` with a flow covariance adaptor ("flow_cov", exp_tanh) added to the `head`
  ("uncertainty" or "main") in the channel order a reloaded official snapshot uses (sorted
  adaptor names); the head's output_dim grows by 3."""
  if cfg.flow_covariance is not None:
    raise ValueError("with_flow_covariance: the config has a flow covariance already")
  cov = covariance.CovarianceConfig(low_confidence_init=low_confidence_init)
  if head == "main":
    return cfg.replace(flow_head_adaptors=tuple(sorted(cfg.flow_head_adaptors + ("flow_cov",))),
                       flow_head=dataclasses.replace(cfg.flow_head,
                                                     output_dim=cfg.flow_head.output_dim + 3),
                       flow_covariance=cov)
  if head != "uncertainty":
    raise ValueError(f"with_flow_covariance: head {head!r}; expected 'uncertainty' or 'main'")
  if cfg.covisibility_head is None:
    raise ValueError("with_flow_covariance: the model has no uncertainty head; use head='main'")
  return cfg.replace(
      uncertainty_head_adaptors=tuple(sorted(cfg.uncertainty_head_adaptors + ("flow_cov",))),
      covisibility_head=dataclasses.replace(cfg.covisibility_head,
                                            output_dim=cfg.covisibility_head.output_dim + 3),
      flow_covariance=cov)


def _tuplify(v):
  return tuple(_tuplify(x) for x in v) if isinstance(v, (list, tuple)) else v


def config_to_dict(cfg: UFMConfig) -> Dict[str, Any]:
  return dataclasses.asdict(cfg)


def config_from_dict(d: Dict[str, Any]) -> UFMConfig:
  """Inverse of config_to_dict (JSON lists become tuples); unknown keys raise."""
  kw = {}
  for k, v in d.items():
    if k in _SUB and v is None:
      kw[k] = None
    elif k in _SUB:
      cls = _SUB[k]
      names = {f.name for f in dataclasses.fields(cls)}
      unknown = set(v) - names
      if unknown:
        raise ValueError(f"unknown keys {sorted(unknown)} in model config section {k!r}")
      kw[k] = cls(**{kk: _tuplify(vv) for kk, vv in v.items()})
    elif k in {f.name for f in dataclasses.fields(UFMConfig)}:
      kw[k] = _tuplify(v)
    else:
      raise ValueError(f"unknown model config key {k!r}")
  return UFMConfig(**kw)


def config_to_json(cfg: UFMConfig) -> str:
  return json.dumps(config_to_dict(cfg), indent=2)


def config_from_json(text: str) -> UFMConfig:
  return config_from_dict(json.loads(text))


def check_images(source, target, patch_size: int, symmetrized: bool = False):
  """ValueError naming the offending shape/dtype (the edge of the jitted model)."""
  for name, x in (("source", source), ("target", target)):
    if x.ndim != 4:
      raise ValueError(f"{name} has shape {tuple(x.shape)} (rank {x.ndim}); expected rank 4 "
                       "[B, H, W, 3]")
    if x.shape[-1] != 3:
      raise ValueError(f"{name} has shape {tuple(x.shape)}; expected 3 channels (RGB) last, "
                       "[B, H, W, 3]")
    if not (x.dtype == jnp.uint8 or jnp.issubdtype(x.dtype, jnp.floating)):
      raise ValueError(f"{name} has dtype {x.dtype}; expected uint8 or float (0..255)")
    h, w = x.shape[1:3]
    if h % patch_size or w % patch_size or h == 0 or w == 0:
      raise ValueError(f"{name} has shape {tuple(x.shape)}; H and W must be positive multiples "
                       f"of the patch size {patch_size}")
  if source.shape != target.shape:
    raise ValueError(f"source shape {tuple(source.shape)} != target shape {tuple(target.shape)}; "
                     "both views must have the same [B, H, W, 3]")
  if symmetrized and source.shape[0] % 2:
    raise ValueError(f"symmetrized=True needs an even batch of (a,b),(b,a) pairs; got batch "
                     f"{source.shape[0]}")


def _uint8_table() -> np.ndarray:
  """[256, 3] float32: (v / 255 - mean) / std with IEEE divisions, as torch computes it."""
  v = np.arange(256, dtype=np.float32)[:, None] / np.float32(255.0)
  return ((v - np.array(IMAGENET_MEAN, np.float32)) / np.array(IMAGENET_STD, np.float32))


_NORM_TABLE = _uint8_table()


def normalize(x: jax.Array) -> jax.Array:
  """(x / 255 - mean) / std in float32, the official uint8 branch.

  uint8 goes through a 256-entry table so the result is bitwise the official one (XLA turns
  divisions by constants into multiplications by reciprocals, which is off by an ulp).
  """
  if x.dtype == jnp.uint8:
    table = jnp.asarray(_NORM_TABLE)
    return jnp.stack([table[x[..., c].astype(jnp.int32), c] for c in range(3)], axis=-1)
  x = x.astype(jnp.float32) / jnp.float32(255.0)
  return (x - jnp.asarray(IMAGENET_MEAN, jnp.float32)) / jnp.asarray(IMAGENET_STD, jnp.float32)


def encoder_batch(source, target, symmetrized: bool):
  """The images the encoder runs on, laid out so that each pair's rows stay adjacent: with the
  batch sharded in contiguous blocks, every device encodes exactly its own pairs' images.

  symmetrized ((a, b), (b, a) rows): `source` already holds every image once (a0, b0, a1, ...).
  Otherwise: source and target interleaved (s0, t0, s1, t1, ...).
  """
  if symmetrized:
    return source
  s = source.shape
  return jnp.stack([source, target], axis=1).reshape((2 * s[0],) + s[1:])


def split_views(x, symmetrized: bool):
  """Inverse of `encoder_batch` on any per-image array: (view1, view2) rows of the pairs."""
  s = x.shape
  pairs = x.reshape((s[0] // 2, 2) + s[1:])
  if symmetrized:  # view 2 of row (a, b) is b: the neighbouring row, swapped within each pair
    return x, pairs[:, ::-1].reshape(s)
  return pairs[:, 0], pairs[:, 1]


class UFM(nn.Module):
  """UniFlowMatchConfidence. `activation_sharding` (optional, `ufm_jax.training.sharding.
  activation_constraint`) is applied to every batch-leading activation at block boundaries:
  images, encoder and fusion blocks, DPT stages, outputs. `layer_gather` (optional,
  `ufm_jax.training.sharding.layer_gather`) gathers the scanned blocks' weights one layer at a time."""
  config: UFMConfig
  activation_sharding: layers.ActivationHook = None
  layer_gather: scan.LayerGather = None

  def constrain(self, x):
    return x if self.activation_sharding is None else self.activation_sharding(x)

  @nn.nowrap
  def apply(self, variables, *args, **kwargs):
    """flax's apply, refusing with a message what the loaders' convention rules out: the
    variables {"params"[, "batch_stats"]} wrapped once more (`{"params": variables}`, the call
    of the loaders' old (model, params) convention), or a bare parameter tree."""
    check_variables(variables)
    return super().apply(variables, *args, **kwargs)

  @nn.nowrap
  def init(self, rngs, *args, **kwargs):
    """flax's init; with config.param_init "official" the fresh parameters are then redrawn as
    the official modules draw them (`official_init`)."""
    variables = super().init(rngs, *args, **kwargs)
    if self.config.param_init == "flax" or kwargs.get("method") is not None:
      return variables
    key = rngs["params"] if isinstance(rngs, Mapping) else rngs
    params = official_init(variables["params"], jax.random.fold_in(key, 0x0FF1C1A1))
    return {**variables, "params": params}

  def setup(self):
    cfg = self.config
    compute = DTYPES[cfg.dtype]
    bb_dtype = None if cfg.dtype == "float32" else compute
    self.encoder = dinov2.DinoV2(cfg.encoder, bb_dtype, cfg.remat, self.activation_sharding,
                                 cfg.attention_impl, cfg.scan_blocks, self.layer_gather)
    self.info_sharing = info_sharing_lib.InfoSharing(cfg.info_sharing, bb_dtype, cfg.remat,
                                                     self.activation_sharding, cfg.attention_impl,
                                                     cfg.scan_blocks, self.layer_gather)
    # float64 mode runs the heads in float64 too (their inputs are float64).
    hd = jnp.bfloat16 if cfg.head_dtype == "bfloat16" and cfg.dtype != "float64" else None
    # torch: head1 = Sequential(Sequential(DPTFeature, DPTRegressionProcessor), AdaptorMap).
    hook = self.activation_sharding
    self.head1_0_0 = dpt.DPTFeature(cfg.flow_head, hd, hook)
    self.head1_0_1 = dpt.DPTRegressionProcessor(cfg.flow_head, hd, hook)
    if cfg.covisibility_head is not None:
      self.uncertainty_head_0_0 = dpt.DPTFeature(cfg.covisibility_head, hd, hook)
      self.uncertainty_head_0_1 = dpt.DPTRegressionProcessor(cfg.covisibility_head, hd, hook)

  def encode(self, source, target, symmetrized: bool = False):
    """Normalised [B, H, W, 3] pair -> last encoder feature maps (view1, view2)."""
    feats = self.encoder(self.constrain(encoder_batch(source, target, symmetrized)))[-1]
    return tuple(self.constrain(v) for v in split_views(feats, symmetrized))

  def backbone(self, source, target, symmetrized: bool = False) -> Dict[str, Any]:
    """Checks and normalises the images, runs encoder + info sharing.

    Returns {"encoder": (view1, view2) last encoder maps, "info_sharing": (view1, view2) final
    fusion maps, "head_features": the 4 view-1 maps the DPT heads take (float32), "hw": (H, W),
    "images": the normalised (source, target)}.
    Subclasses (the refinement model) reuse it.
    """
    cfg = self.config
    check_images(source, target, cfg.encoder.patch_size, symmetrized)
    head_dtype = jnp.float64 if cfg.dtype == "float64" else jnp.float32
    src, tgt = normalize(source), normalize(target)
    if cfg.dtype == "float64":
      src, tgt = src.astype(jnp.float64), tgt.astype(jnp.float64)
    f1, f2 = self.encode(src, tgt, symmetrized)
    (fin1, fin2), inters = self.info_sharing(f1, f2)
    # Heads see view 1 only: [encoder last, intermediate 0, intermediate 1, final], in float32.
    feats = [self.constrain(t.astype(head_dtype)) for t in (f1, inters[0][0], inters[1][0], fin1)]
    return {"encoder": (f1, f2), "info_sharing": (fin1, fin2), "head_features": feats,
            "hw": tuple(source.shape[1:3]), "images": (src, tgt)}

  def heads(self, feats, hw, images=None) -> Dict[str, jax.Array]:
    """DPT flow head and the (gradient-stopped) uncertainty head, each through its adaptors.
    `images`: the normalised (source, target), needed when the config has uncertainty_cues."""
    cfg = self.config
    decoded = self.head1_0_1(self.head1_0_0(feats), hw)
    self.sow("intermediates", "flow_decoded_channels", decoded)
    main = dpt.split_adaptor_channels(decoded, cfg.flow_head_adaptors)
    out = {"flow": dpt.flow_adaptor(main["flow"], cfg.flow_adaptor)}
    unc = {}
    if cfg.covisibility_head is not None:
      unc_feats = ([jax.lax.stop_gradient(t) for t in feats] if cfg.detach_uncertainty_head
                   else feats)
      cues = None
      if cfg.uncertainty_cues:
        if images is None:
          raise ValueError("UFM.heads: the config has uncertainty_cues "
                           f"{cfg.uncertainty_cues}, which need the images")
        cues = sampling.uncertainty_cues(cfg.uncertainty_cues, *images, out["flow"])
      unc = dpt.split_adaptor_channels(
          self.uncertainty_head_0_1(self.uncertainty_head_0_0(unc_feats), hw, extra=cues),
          cfg.uncertainty_head_adaptors)
    # UniFlowMatch (no uncertainty head) reads the mask from the main head (ufm.py:436-440 at
    # 3732a50); the two heads never both have one (_check_adaptors).
    mask = unc.get("non_occluded_mask", main.get("non_occluded_mask"))
    if mask is not None:
      logits = mask[..., 0]
      out.update(covisibility=jax.nn.sigmoid(logits), covisibility_logits=logits)
    cov = main.get("flow_cov", unc.get("flow_cov"))
    if cov is not None:
      out.update(covariance.adaptor(cov, cfg.flow_covariance))
    return {k: self.constrain(v) for k, v in out.items()}

  def __call__(self, source, target, symmetrized: bool = False,
               train: bool = False) -> Dict[str, jax.Array]:
    del train  # no BatchNorm or dropout here; the refinement model's U-Net has BatchNorm
    b = self.backbone(source, target, symmetrized)
    return self.heads(b["head_features"], b["hw"], b["images"])


def _transposed(module_path) -> bool:
  """Whether a module of the tree is a transposed convolution: DPTFeature's two, and the
  refinement U-Net's up-convolutions (`unet_feature/ups_{2k}`, refine.UpConv2x2)."""
  name = module_path[-1]
  return name in dpt.CONV_TRANSPOSE or (
      module_path[0] == "unet_feature" and re.fullmatch(r"ups_\d*[02468]", name) is not None)


def official_init(params, key):
  """Fresh parameters redrawn as the official PyTorch model initialises them, for training from
  scratch: the fusion transformer's Linear weights xavier_uniform with zero biases (UniCeption
  global_attention_transformer.py:197-211 at the train branch's pin 1cff080); every other Linear
  / Conv2d / ConvTranspose2d (DPT heads, refiner) with PyTorch's defaults
  (`dpt.torch_default_init`). Norm scales 1 and biases 0, LayerScale and the classification bias
  are already as the official ones; the encoder is left as drawn (the recipes load pretrained
  DINOv2 into it). Works on the per-layer and the scanned (stacked) layouts alike."""
  flat = traverse_util.flatten_dict(params)
  out = dict(flat)
  modules = sorted({path[:-1] for path in flat if path[-1] == "kernel"})
  for i, module in enumerate(modules):
    if module[0] == "encoder":
      continue
    k = jax.random.fold_in(key, i)
    kernel = flat[module + ("kernel",)]
    if module[0] == "info_sharing":
      batch = tuple(range(kernel.ndim - 2))   # the stacked layout's leading depth axis
      out[module + ("kernel",)] = jax.nn.initializers.xavier_uniform(batch_axis=batch)(
          k, kernel.shape, kernel.dtype)
      continue
    w, b = dpt.torch_default_init(k, kernel.shape, _transposed(module), kernel.dtype)
    out[module + ("kernel",)] = w
    if module + ("bias",) in flat:
      out[module + ("bias",)] = b
  return traverse_util.unflatten_dict(out)


def model_from_config(cfg: UFMConfig, **kw) -> UFM:
  # Config subclasses name their own module (refine.UFMRefineConfig -> UFMRefine).
  if hasattr(cfg, "build_model"):
    return cfg.build_model(**kw)
  return UFM(cfg, **kw)


def variables(tree) -> Dict[str, Any]:
  """The variables for `model.apply` ({"params"[, "batch_stats"]}, what every loader returns)
  from those variables (passed through) or from a bare parameter tree (wrapped): the one
  normalisation of what users hand to predict, match, export and save_official."""
  return tree if "params" in tree else {"params": tree}


def check_variables(tree) -> None:
  """Raises a TypeError saying what to write instead when `tree` is not a variables dict."""
  if not isinstance(tree, Mapping):
    return   # flax's own error for non-mappings
  inner = tree.get("params")
  if isinstance(inner, Mapping) and ("params" in inner or "batch_stats" in inner):
    raise TypeError(
        "model.apply got the variables wrapped in another {'params': ...}: the ufm_jax loaders "
        "return (model, variables) with variables = {'params': ...[, 'batch_stats': ...]}; call "
        "model.apply(variables, ...), not model.apply({'params': variables}, ...)")
  if inner is None and tree and not set(tree) & {"batch_stats", "intermediates", "cache"}:
    raise TypeError(
        f"model.apply got a bare parameter tree (top-level keys {sorted(tree)[:4]}...): pass the "
        "variables {'params': params}, as the ufm_jax loaders return them "
        "(ufm_jax.models.ufm.variables(params) wraps a bare tree)")


def variable_shapes(model: UFM) -> Dict[str, Any]:
  """Shape/dtype trees of every variable collection the model has ("params", and "batch_stats"
  with BatchNorm), without allocating them."""
  p = model.config.encoder.patch_size
  x = jax.ShapeDtypeStruct((1, 2 * p, 2 * p, 3), jnp.uint8)
  out = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b), x, x)
  return {k: v for k, v in out.items() if k != "intermediates"}


def random_param_values(model: UFM, seed: int = 0, small_names=()) -> dict:
  """A numpy draw for every parameter of `model` (shapes via `param_shapes`; compiling flax's
  initialisers costs seconds to minutes on CPU where only shapes and plausible scales matter):
  N(0, 1 / fan_in) for tensors of 2 or more dimensions, N(0, 0.05^2) for vectors and the
  parameters named in `small_names`, "scale" and "gamma" around 1. Nested like the params."""
  rng = np.random.default_rng(seed)
  flat = {}
  for path, leaf in traverse_util.flatten_dict(param_shapes(model)).items():
    shape = tuple(leaf.shape)
    small = len(shape) < 2 or path[-1] in small_names
    scale = 0.05 if small else (1.0 / int(np.prod(shape[:-1]))) ** 0.5
    base = 1.0 if path[-1] in ("scale", "gamma") else 0.0
    flat[path] = (base + scale * rng.standard_normal(shape)).astype(np.float32)
  return traverse_util.unflatten_dict(flat)


def param_shapes(model: UFM):
  """Shape/dtype tree of the parameters, without allocating them (jax.eval_shape)."""
  p = model.config.encoder.patch_size
  x = jax.ShapeDtypeStruct((1, 2 * p, 2 * p, 3), jnp.uint8)
  return jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b), x, x)["params"]
