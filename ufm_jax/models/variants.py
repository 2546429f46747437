"""Model variants by name: plain functions returning `ufm_jax.models.ufm.UFMConfig`, and
`build_model(name, **overrides)`, the one way to build a model that has no checkpoint yet.

    from ufm_jax.models import variants
    model = variants.build_model("ufm_base", dtype="bfloat16")

The released checkpoints carry their own config.json (`ufm_jax.load_official` reads it); these
functions describe the same structures for training from scratch, benchmarks and eval_shape.
"""

import dataclasses

from ufm_jax.models import dinov2, dpt, info_sharing, refine, ufm

# DPT head of the release: hooks on [encoder last, fusion layer 6, fusion layer 9, fusion final].
_UFM_LAYER_DIMS = (96, 192, 384, 768)
_UFM_FEATURE_DIM = 256


def _dpt(enc_dim: int, fusion_dim: int, output_dim: int, layer_dims=_UFM_LAYER_DIMS,
         feature_dim=_UFM_FEATURE_DIM) -> dpt.DPTConfig:
  return dpt.DPTConfig(input_feature_dims=(enc_dim, fusion_dim, fusion_dim, fusion_dim),
                       layer_dims=tuple(layer_dims), feature_dim=feature_dim, output_dim=output_dim)


def dinov2_small(**kw) -> dinov2.DinoV2Config:
  """ViT-S/14: 384 wide, 12 blocks, 6 heads (21M params)."""
  return dinov2.dinov2_config("small", **kw)


def dinov2_large(**kw) -> dinov2.DinoV2Config:
  """ViT-L/14: 1024 wide, 24 blocks, 16 heads (304M) - the UFM encoder."""
  return dinov2.dinov2_config("large", **kw)


def ufm_base(**kw) -> ufm.UFMConfig:
  """UFM-Base (UFM 560): DINOv2 ViT-L/14 (all 24 blocks), 12 x 768 fusion transformer with
  12 heads, DPT taps at fusion layers 6 and 9 (0-based indices 5, 8) plus the final layer,
  DPT layer dims [96, 192, 384, 768], feature dim 256; about 428.3M parameters.

  The flow adaptor normalisation of the release is read from its config.json by the loader; the
  values here (zero mean, unit std at a 420 x 560 base shape, scale_both) are for training from
  scratch.
  """
  cfg = ufm.UFMConfig(
      encoder=dinov2_large(indices=(23,)),
      info_sharing=info_sharing.InfoSharingConfig(
          input_embed_dim=1024, dim=768, depth=12, num_heads=12, mlp_ratio=4.0, qkv_bias=True,
          qk_norm=False, init_values=None, indices=(5, 8)),
      flow_head=_dpt(1024, 768, 2),
      covisibility_head=_dpt(1024, 768, 1),
      flow_adaptor=dpt.FlowAdaptorConfig(flow_mean=(0.0, 0.0), flow_std=(1.0, 1.0),
                                         base_shape=(420, 560), scale_strategy="scale_both"),
      detach_uncertainty_head=True,
      inference_resolution=(420, 560))
  return cfg.replace(**kw)


def ufm_base_980(**kw) -> ufm.UFMConfig:
  """UFM 980: same structure as UFM-Base, inferred at 980 px on the long side (H a multiple of
  14 near 3:4; the snapshot's config.json is authoritative)."""
  return ufm_base(**{"inference_resolution": (742, 980), **kw})


def ufm_refine(**kw) -> refine.UFMRefineConfig:
  """UFM-Refine (UniFlowMatchClassificationRefinement): UFM-Base plus the refiner: U-Net
  [64, 128, 256, 512] (hard-coded in the official ufm.py), 16-channel refinement features from
  the patch_mlp head on cat(encoder list[0], fusion final) (1024 + 768), a 7 x 7 window.
  mlp_ratio and temperature follow the public fixture (2, 4.0); a release's config.json is
  authoritative (`ufm_jax.load_official` reads it)."""
  base = ufm_base()   # encoder list[0] is then the last block's output (a single index)
  fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(ufm.UFMConfig)}
  cfg = refine.UFMRefineConfig(**fields, unet_features=(64, 128, 256, 512), refine_feature_dim=16,
                               refine_mlp_ratio=2.0, refinement_range=7, temperature=4.0)
  return cfg.replace(**kw)


def ufm_base_dinov2l_init(**kw) -> ufm.UFMConfig:
  """UFM-Base-DINOv2L-init (official README, main 3732a50: 0.3B parameters) as UniCeption
  ee7fa0b's scripts/convert_dino_to_info_sharing.py builds it from one DINOv2 ViT-L/14: the
  encoder is its first 12 blocks without the final norm (norm_returned_features=False), the
  fusion transformer its blocks 12-23 (1024 wide, 16 heads, LayerScale, no input projection);
  fusion taps (4, 8). The released config.json was not available here: `load_official` reads
  the release's own and is authoritative."""
  cfg = ufm_base(
      encoder=dinov2_large(depth=12, indices=(11,), norm_returned_features=False),
      info_sharing=info_sharing.InfoSharingConfig(
          input_embed_dim=1024, dim=1024, depth=12, num_heads=16, mlp_ratio=4.0, qkv_bias=True,
          init_values=1e-5, indices=(4, 8)),
      flow_head=_dpt(1024, 1024, 2), covisibility_head=_dpt(1024, 1024, 1))
  return cfg.replace(**kw)


def ufm_refine_recipe(**kw) -> refine.UFMRefineConfig:
  """The refinement model as the official training recipe builds it (train branch:
  configs/model/uniflowmatch_refinement.yaml with bash_scripts/training/
  megatraining_refinement_560.sh): UFM-Base's encoder, fusion and flow head, the encoder
  returning blocks (6, 23) (block 23 feeds the fusion and the DPT, block 6 the refiner), no
  uncertainty head, a U-Net [64, 128, 256, 512] with BatchNorm (`use_unet_batchnorm`, the
  "batch_stats" collection) combined by "modulate", the patch_mlp head (16 channels, mlp_ratio 2)
  and a 7 x 7 window at temperature 4 (the class default). The flow adaptor is the recipe's
  adaptor_map/flow_scale_both.yaml: std 25 px at a 224 x 224 base shape."""
  base = ufm_base(encoder=dinov2_large(indices=(6, 23)), covisibility_head=None,
                  flow_adaptor=dpt.FlowAdaptorConfig(flow_mean=(0.0, 0.0), flow_std=(25.0, 25.0),
                                                     base_shape=(224, 224),
                                                     scale_strategy="scale_both"))
  fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(ufm.UFMConfig)}
  cfg = refine.UFMRefineConfig(**fields, unet_features=(64, 128, 256, 512), refine_feature_dim=16,
                               refine_mlp_ratio=2.0, use_unet_feature=True,
                               use_unet_batchnorm=True, feature_combine_method="modulate",
                               refinement_range=7, temperature=4.0)
  return cfg.replace(**kw)


def fixture_small(**kw) -> ufm.UFMConfig:
  """The public parity fixture (ufm_reference/base): ViT-S/14 cut to 2 blocks, 4 x 96 fusion
  with 4 heads and taps [1, 2], DPT layer dims [24, 48, 96, 192], feature dim 48."""
  cfg = ufm.UFMConfig(
      encoder=dinov2_small(depth=2, indices=(0, 1)),
      info_sharing=info_sharing.InfoSharingConfig(
          input_embed_dim=384, dim=96, depth=4, num_heads=4, indices=(1, 2)),
      flow_head=_dpt(384, 96, 2, (24, 48, 96, 192), 48),
      covisibility_head=_dpt(384, 96, 1, (24, 48, 96, 192), 48),
      flow_adaptor=dpt.FlowAdaptorConfig(flow_mean=(1.5, -2.0), flow_std=(12.0, 9.0),
                                         base_shape=(120, 160), scale_strategy="scale_both"),
      inference_resolution=(168, 224))
  return cfg.replace(**kw)


def _student(dim: int, depth: int, heads: int, taps, layer_dims, feature_dim: int,
             **kw) -> ufm.UFMConfig:
  """UFM-Base's structure on a DINOv2 ViT-S/14 encoder (all 12 blocks) with a narrower fusion
  transformer and DPT heads: the distillation students."""
  return ufm_base(
      encoder=dinov2_small(),
      info_sharing=info_sharing.InfoSharingConfig(
          input_embed_dim=384, dim=dim, depth=depth, num_heads=heads, mlp_ratio=4.0,
          qkv_bias=True, qk_norm=False, init_values=None, indices=tuple(taps)),
      flow_head=_dpt(384, dim, 2, layer_dims, feature_dim),
      covisibility_head=_dpt(384, dim, 1, layer_dims, feature_dim), **kw)


def ufm_small(**kw) -> ufm.UFMConfig:
  """UFM-Small, a distillation student (configs/distill.py): DINOv2 ViT-S/14 (all 12 blocks,
  initialisable from facebook/dinov2-small with `model_init=dinov2:`), a 6 x 384 fusion
  transformer with 6 heads tapped after blocks 3 and 5 (0-based 2, 4: UFM-Base's 6 and 9 of 12
  scaled to 6), DPT heads at half UFM-Base's widths (layer dims [48, 96, 192, 384], feature dim
  128); 42.2M parameters, inferred at 420 x 560 like UFM-Base. Sizes and speed beside UFM-Base:
  docs/distillation.md."""
  return _student(384, 6, 6, (2, 4), (48, 96, 192, 384), 128).replace(**kw)


def ufm_tiny(**kw) -> ufm.UFMConfig:
  """UFM-Tiny, the smallest distillation student: UFM-Small's ViT-S/14 encoder (facebook/dinov2-
  small), a 4 x 256 fusion transformer with 4 heads tapped after blocks 2 and 3 (0-based 1, 2),
  DPT heads at a quarter of UFM-Base's widths (layer dims [24, 48, 96, 192], feature dim 64);
  27.7M parameters, inferred at 294 x 392 (3:4, 21 x 28 patches: half the tokens of 420 x 560).
  Sizes and speed: docs/distillation.md."""
  return _student(256, 4, 4, (1, 2), (24, 48, 96, 192), 64,
                  inference_resolution=(294, 392)).replace(**kw)


def tiny(**kw) -> ufm.UFMConfig:
  """A very small UFM for smoke tests and the synthetic training config (~1M parameters)."""
  cfg = ufm.UFMConfig(
      encoder=dinov2.DinoV2Config(embed_dim=64, depth=2, num_heads=2, indices=(1,)),
      info_sharing=info_sharing.InfoSharingConfig(
          input_embed_dim=64, dim=64, depth=3, num_heads=2, indices=(0, 1)),
      flow_head=_dpt(64, 64, 2, (16, 32, 64, 64), 32),
      covisibility_head=_dpt(64, 64, 1, (16, 32, 64, 64), 32),
      flow_adaptor=dpt.FlowAdaptorConfig(flow_mean=(0.0, 0.0), flow_std=(8.0, 8.0),
                                         base_shape=(112, 112), scale_strategy="scale_both"),
      inference_resolution=(112, 112))
  return cfg.replace(**kw)


def tiny_synth(**kw) -> ufm.UFMConfig:
  """`tiny` with 7 px patches (8 x 8 tokens per 56 px image instead of 4 x 4) and an 8 x 8
  position table (no resampling at 56 px) initialised with fixed 2D sin-cos, for finer matching
  of few-pixel motions (docs/synthetic_training.md)."""
  cfg = tiny()
  cfg = cfg.replace(encoder=dataclasses.replace(cfg.encoder, patch_size=7, pos_grid=8,
                                                pos_embed_init="sincos"))
  return cfg.replace(**kw)


def synth(**kw) -> ufm.UFMConfig:
  """`tiny_synth` with 16-wide DPT heads (~0.4M parameters) and fusion blocks whose key
  projections start equal to their query projections, both at 2x the default scale
  (`info_sharing.tied_qk_init=2.0`): the model of `configs/synthetic.py`, trained from scratch.
  The tie starts cross-view attention as feature similarity, the matching prior UFM otherwise
  gets from pretrained DINOv2 (why and how it was measured: docs/synthetic_training.md)."""
  cfg = tiny_synth()
  cfg = cfg.replace(flow_head=_dpt(64, 64, 2, (16, 16, 32, 32), 16),
                    covisibility_head=_dpt(64, 64, 1, (16, 16, 32, 32), 16),
                    info_sharing=dataclasses.replace(cfg.info_sharing, tied_qk_init=2.0))
  return cfg.replace(**kw)


def synth_small(**kw) -> ufm.UFMConfig:
  """The distillation student of the synthetic demonstration (docs/distillation.md): `synth`'s
  attention and flow head as they are (64 wide, 2 heads of 32, 2 encoder and 3 fusion blocks,
  the tied query/key init, the 16-wide flow DPT), MLPs of ratio 1/4 instead of 4 and a
  covisibility head of width 8 (layer dims [8, 8, 16, 16]): 198,223 parameters, 0.49 x
  `synth`'s 403,707. It shares synth's layout wherever it can, so that `init=teacher`
  (configs/distill.py; the default is init=fresh, its own init) can start it from the teacher's
  attention, patch embedding and flow head; narrower students stayed on the zero-flow plateau
  (docs/distillation.md)."""
  cfg = synth()
  cfg = cfg.replace(
      encoder=dataclasses.replace(cfg.encoder, mlp_ratio=0.25),
      info_sharing=dataclasses.replace(cfg.info_sharing, mlp_ratio=0.25),
      covisibility_head=_dpt(64, 64, 1, (8, 8, 16, 16), 8))
  return cfg.replace(**kw)


def tiny_refine(**kw) -> refine.UFMRefineConfig:
  """`tiny` plus a small refiner (U-Net [8, 16], 8 feature channels, 7 x 7 window): smoke tests
  and synthetic refine-stage training."""
  base = tiny()
  fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(ufm.UFMConfig)}
  cfg = refine.UFMRefineConfig(**fields, unet_features=(8, 16), refine_feature_dim=8,
                               refine_mlp_ratio=2.0, refinement_range=7, temperature=4.0)
  return cfg.replace(**kw)


def tiny_refine_recipe(**kw) -> refine.UFMRefineConfig:
  """`tiny_refine` built as `ufm_refine_recipe` is: encoder taps (0, 1) (the first feeds the
  refiner), no uncertainty head, a BatchNorm U-Net [8, 16] combined by "modulate"; for tests."""
  base = tiny(encoder=dataclasses.replace(tiny().encoder, indices=(0, 1)), covisibility_head=None)
  fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(ufm.UFMConfig)}
  cfg = refine.UFMRefineConfig(**fields, unet_features=(8, 16), refine_feature_dim=8,
                               refine_mlp_ratio=2.0, use_unet_batchnorm=True,
                               feature_combine_method="modulate", refinement_range=7,
                               temperature=4.0)
  return cfg.replace(**kw)


VARIANTS = {"fixture_small": fixture_small, "tiny": tiny, "tiny_synth": tiny_synth, "synth": synth,
            "synth_small": synth_small, "ufm_base": ufm_base, "ufm_small": ufm_small,
            "ufm_tiny": ufm_tiny,
            "ufm_base_980": ufm_base_980, "ufm_refine": ufm_refine, "tiny_refine": tiny_refine,
            "ufm_refine_recipe": ufm_refine_recipe, "tiny_refine_recipe": tiny_refine_recipe,
            "ufm_base_dinov2l_init": ufm_base_dinov2l_init}


def get(name: str, **kw) -> ufm.UFMConfig:
  """The config of variant `name` with UFMConfig field overrides (e.g. dtype="bfloat16")."""
  if name not in VARIANTS:
    raise ValueError(f"unknown model variant {name!r}; expected one of {sorted(VARIANTS)}")
  return VARIANTS[name](**kw)


def build_model(name: str, **overrides):
  """The flax module of variant `name` (UFM, or UFMRefine for refine variants), no params."""
  return ufm.model_from_config(get(name, **overrides))


def from_config(config, activation_sharding=None, layer_gather=None):
  """The flax module of a training config: `config.model_fn` ("module:fn", called with
  config.model) or the named variant `config.model_name` with `config.model` overrides.

  `activation_sharding`: the hook the model applies at block boundaries (from
  `ufm_jax.training.sharding.activation_constraint`), None on one device. `layer_gather`: FSDP's
  per-layer gather of the scanned blocks (`ufm_jax.training.sharding.layer_gather`).
  """
  if config.get("model_fn"):
    import importlib
    module, attr = config.model_fn.split(":")
    return getattr(importlib.import_module(module), attr)(config.model)
  cfg = get(config.model_name, **config.model.to_dict())
  return ufm.model_from_config(cfg, activation_sharding=activation_sharding,
                               layer_gather=layer_gather)
