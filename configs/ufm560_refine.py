r"""UFM-Refine: the official refinement recipe (`bash_scripts/training/megatraining_refinement_560.sh`
of the UFM `train` branch; every setting and its source: docs/recipe.md): the classification
refiner trained on a frozen UFM-560 base.

  python train.py --config=configs/ufm560_refine.py --workdir=DIRREF \
      --config.model_init=snapshot:infinity1096/UFM-Base --config.input.data_root=/data/ufm

The base (encoder, fusion transformer, DPT heads) has lr 0, so it is frozen: no gradient, no
optimizer state. Only the U-Net, classification head, combiners and the classification bias
train (official groups `classification_head` and `unet_feature`), with two terms summed in this
order: the plain EPE of the regressed flow (multiplier 0, which the official code ignores: it adds
a constant, the base being frozen) and 10 x the refinement cross-entropy
(`ufm_jax.training.refine_training.RefinementCE`) on at most 400k pixels, only on rows whose dataset the
official code marks suitable for refinement. 24 unique pairs per step (48 symmetrized rows), 30
epochs, lr 1e-4 with 3 warmup epochs, cosine to 1%, clipping at 1.0. Data: BlendedMVS, MegaDepth,
ScanNet++, StaticThings and Habitat with the official recipe's samples per epoch
(`mixture.RECIPES['refine560']`: static_pinhole_100k.yaml); of these only BlendedMVS trains the
refiner.

Model: the official recipe's refinement structure (`ufm_refine_recipe`, train branch
configs/model/uniflowmatch_refinement.yaml): a U-Net with BatchNorm (its running statistics are
train state, saved with the checkpoints and used for evaluation), `modulate` feature combination,
encoder taps [6, 23], no uncertainty head (so no covisibility output: evaluators skip the
covisibility metrics). This is NOT the released UFM-Refine; `:model=ufm_refine` trains the
released structure (conv combination, no BatchNorm, a covisibility head kept frozen).

model_init: UFM-Base, as the official script (`resume_model=infinity1096/UFM-Base`,
megatraining_refinement_560.sh:46; a Hub ID or snapshot folder, or `ckpt:DIR560` for a 560 run of ours). As the
official resume_model, the source's flow normalisation buffers (flow_mean, flow_std) replace the
config's and base_shape / scale_strategy stay the config's (`model_init_flow_adaptor="buffers"`);
any other difference that changes outputs stops the run before training, naming the --config
override (`ufm_jax.training.model_init.check_structure`).

Smoke run on a fresh machine (tiny recipe model, embedded synthetic pairs, random base):
  python train.py --config=configs/ufm560_refine.py:model=tiny_refine_recipe,data=synthetic,steps=20 \
      --workdir=DIR
(`model=tiny_refine` for the released structure's.)
"""

import ml_collections

from ufm_jax.training import config_lib, losses, optim
from ufm_jax.data import augment, mixture, pipeline


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, model="ufm_refine_recipe", data="refine", steps=0)
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.seed = 42
  c.num_epochs = 30
  # Rows of these datasets train the refiner (official `suitable_for_refinement`).
  refine_datasets = ("blendedmvs", "flyingthings", "hypersim")
  if arg.data == "refine":
    # configs/dataset/static_pinhole.yaml: the 560_many_ar shapes (square included) and
    # Habitat's `cropping` yaml (crop augmentation and low light, unlike the 560 recipe).
    c.input = pipeline.input_config(
        mixture.recipe("refine560"), batch_size=48, longest_side=560,
        shapes=augment.SHAPES_560_SQUARE,
        augment={"no_crop_datasets": (), "low_light_datasets": ("flyingchairs", "habitat"),
                 "fast_image_ops": False})   # official image operations (True: a deviation)
  elif arg.data == "synthetic":
    c.input = pipeline.input_config(mixture.synthetic_mixture(num_pairs=10_000, size=(56, 56)),
                                    batch_size=2, longest_side=56, aspect_ratios=(1.0,),
                                    num_workers=0)
    c.log_training_steps = 1
    refine_datasets = ("synthetic",)   # the smoke run's only source
  else:
    raise ValueError(f"configs/ufm560_refine.py: data={arg.data!r}; expected refine or synthetic")
  if arg.steps:
    c.total_steps = arg.steps

  c.model_name = arg.model
  if arg.data == "synthetic":
    c.model = config_lib.model_options(dtype="float32", remat=False, scan_blocks=True)
  else:
    c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  c.model.param_init = "official"      # the refiner starts as the official modules do
  # adaptor_map/flow_scale_both.yaml; model_init's flow_mean / flow_std buffers replace these
  # two (model_init_flow_adaptor below), base_shape and scale_strategy stay.
  c.model.flow_adaptor = ml_collections.ConfigDict({
      "flow_mean": (0.0, 0.0), "flow_std": (25.0, 25.0), "base_shape": (224, 224),
      "scale_strategy": "scale_both"})
  c.model.refinement_range = 7
  # Official: plain DDP (train_pl.py:531-533), so the U-Net's BatchNorm takes its statistics
  # over each GPU's rows: 24 pairs over the paper's 8 GPUs, symmetrized = 6 rows
  # (models/refine.py BatchNorm.group_rows; unset: over the whole global batch).
  c.model.unet_batchnorm_group_rows = (6 if arg.data == "refine" else config_lib.unset(int))
  c.model_init = config_lib.unset(str)  # UFM-Base (snapshot:ID) or a 560 run (ckpt:DIR)
  c.model_init_flow_adaptor = "buffers"   # official resume_model (train_pl.py:496-518)

  c.optim = ml_collections.ConfigDict({
      # uncertainty_head: official 0 as well. The recipe model has no such group, so the key is
      # ignored (as the official does); with model=ufm_refine it keeps that head frozen.
      "lr": {"encoder": 0.0, "info_sharing": 0.0, "output_head": 0.0, "uncertainty_head": 0.0,
             "classification_head": 1e-4, "unet_feature": 1e-4},
      "groups": dict(optim.PARAM_GROUPS),
      "b1": 0.9, "b2": 0.95, "eps": 1e-8, "weight_decay": 0.05, "no_decay": config_lib.unset(str),
      "grad_clip_norm": 1.0,
      "warmup_epochs": 3.0, "fractional_warmup": True, "warmup_frac": config_lib.unset(float),
      "min_lr_rate": 0.01,
      # Official: a skipped non-finite step still steps the scheduler (train_pl.py:79-81).
      "skip_advances_schedule": True,
      "frozen": config_lib.unset(str), "trainable": config_lib.unset(str)})
  if arg.data == "synthetic":   # a smoke run: warm up over its first 10% of steps, not 3 epochs
    c.optim.warmup_epochs, c.optim.warmup_frac = None, 0.1

  # configs/loss/refinement_only.yaml, terms summed in this order (temperature: the model's).
  c.loss = ml_collections.ConfigDict({
      "terms": ("epe", "refinement_cross_entropy"),
      "epe": {"type": "epe", "range": "covisible", "multiplier": 0.0, "multiplier_applied": False,
              "invalid_gt": "zero", "eps": 1e-4, "epe_eps": 0.0},
      "refinement_cross_entropy": {
          "type": "refinement_ce", "multiplier": 10.0, "datasets": refine_datasets,
          "max_pixels": 400_000, "window_margin": 1e-4, "taps": "truncate",
          "gather_dtype": "bfloat16", "eps": 1e-4},
      "shared_cleanup": True,
      # Official: DDP, each GPU's own loss over its rows (its own means and 400k-pixel cap),
      # gradients averaged: the mean of 8 group losses, one per GPU of the paper's run
      # (6 rows each), whatever our device count (losses.Recipe.groups; 1 pools the batch).
      "groups": losses.PAPER_GPUS if arg.data != "synthetic" else 1})   # smoke: 2 rows
  c.evals = ml_collections.ConfigDict(
      {"sintel": config_lib.bench_eval("sintel")} if arg.data == "refine" else {})
  return c
