r"""UFM-560: the official training recipe (`bash_scripts/training/megatraining_560.sh` of the UFM
`train` branch with `configs/default.yaml`; every setting and its source: docs/recipe.md).

  python train.py --config=configs/ufm560.py:data=both --workdir=DIR \
      --config.model_init=dinov2:/path/to/facebook-dinov2-large --config.input.data_root=/data/ufm

Full UFM-Base (ViT-L/14 DINOv2 + 12 x 768 fusion + DPT heads), encoder initialised from pretrained
DINOv2 (`model_init`: the HF facebook/dinov2-large folder or its model.safetensors, or the original
dinov2_vitl14_pretrain.pth with the torch extra), the rest initialised as the official modules are
(`model.param_init`). The 12 datasets with the samples per epoch of the official recipe
(`mixture.RECIPES['ufm560']`: old_setting_100k.yaml), the official training shapes (H in {420,
364, 308, 280, 168} x 560) and augmentation. 48 unique pairs per step, symmetrized into 96 rows;
48 epochs; AdamW (0.9, 0.95), weight decay 0.05 on every parameter; peak lr 5e-6 (encoder) and
1e-4 (the rest); warmup 4.8 epochs, then cosine to 1% of the peak; gradients clipped to global
norm 1.0. Loss: robust EPE on covisible pixels + 10 x covisibility BCE, whose gradient reaches
the trunk (`detach_uncertainty_head=False`). Arg `data=of|wb|both` selects the Table 4 data
ablation (same number of epochs). Arg `cov=True` adds a flow covariance to the uncertainty head
(before its covisibility channel, low_confidence_init) and the Gaussian NLL on the pixels the robust
EPE supervises (`config_lib.add_flow_covariance`, docs/uncertainty.md): not in the official recipe.

Each official quirk is one key below (`loss.*`, `optim.fractional_warmup`); the comment at its
definition (ufm_jax/training/losses.py, ufm_jax/training/optim.py) says what switching it changes, e.g.
`--config.loss.robust_epe.invalid_gt=drop`.
"""

import ml_collections

from ufm_jax.training import config_lib, losses, optim
from ufm_jax.data import augment, mixture, pipeline


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, data="both", model="ufm_base", cov=False)
  names = {"both": mixture.ALL, "of": mixture.OPTICAL_FLOW, "wb": mixture.WIDE_BASELINE}
  if arg.data not in names:
    raise ValueError(f"configs/ufm560.py: data={arg.data!r}; expected of, wb or both")
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.seed = 42
  c.num_epochs = 48
  # The official shapes and augmentation with the official image operations (ufm_jax.data.augment,
  # docs/recipe.md). fast_image_ops=True (a deviation: OpenCV's bicubic and HSV for PIL's) saves
  # host CPU per row (docs/host_input.md).
  c.input = pipeline.input_config(mixture.recipe("ufm560", names[arg.data]), batch_size=96,
                                  longest_side=560, shapes=augment.SHAPES_560,
                                  augment={"fast_image_ops": False})

  c.model_name = arg.model
  c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  # The model as trained (configs/model/uniflowmatch_covisibility.yaml).
  c.model.detach_uncertainty_head = False
  c.model.param_init = "official"
  c.model.flow_adaptor = ml_collections.ConfigDict({
      "flow_mean": (0.0, 0.0), "flow_std": (25.0, 25.0), "base_shape": (224, 224),
      "scale_strategy": "scale_both"})
  # dinov2:PATH (facebook/dinov2-large), snapshot:DIR or ckpt:WORKDIR; typed so that
  # `--config.model_init=...` parses (a plain None field cannot be overridden from the flags).
  c.model_init = config_lib.unset(str)
  # A snapshot or run given as model_init lends its flow normalisation buffers, as the official
  # resume_model (train_pl.py:496-518); DINOv2 weights have none.
  c.model_init_flow_adaptor = "buffers"

  c.optim = ml_collections.ConfigDict({
      "lr": {"encoder": 5e-6, "info_sharing": 1e-4, "output_head": 1e-4,
             "uncertainty_head": 1e-4},
      "groups": dict(optim.PARAM_GROUPS),
      "b1": 0.9, "b2": 0.95, "eps": 1e-8, "weight_decay": 0.05, "no_decay": config_lib.unset(str),
      "grad_clip_norm": 1.0,
      "warmup_epochs": 4.8, "fractional_warmup": True, "warmup_frac": config_lib.unset(float),
      "min_lr_rate": 0.01,
      # Official: a skipped non-finite step still steps the scheduler (train_pl.py:79-81).
      "skip_advances_schedule": True,
      "frozen": config_lib.unset(str), "trainable": config_lib.unset(str)})

  # configs/loss/robust_epe_covisibility.yaml, terms summed in this order.
  c.loss = ml_collections.ConfigDict({
      "terms": ("robust_epe", "covisibility_ce"),
      "robust_epe": {"type": "robust", "range": "covisible", "alpha": 0.5, "c": 0.24,
                     "multiplier": 1.0, "multiplier_applied": False, "invalid_gt": "zero",
                     "eps": 1e-4},
      "covisibility_ce": {"type": "bce", "multiplier": 10.0, "eps": 1e-6},
      "shared_cleanup": True,
      # Official: DDP, each GPU's own loss over its rows (its own means and 400k-pixel cap),
      # gradients averaged: the mean of 8 group losses, one per GPU of the paper's run
      # (12 rows each), whatever our device count (losses.Recipe.groups; 1 pools the batch).
      "groups": losses.PAPER_GPUS})
  if arg.cov:
    config_lib.add_flow_covariance(c, pixels="robust_epe")
  c.evals = ml_collections.ConfigDict({"sintel": config_lib.bench_eval("sintel")})
  return c
