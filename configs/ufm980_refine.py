r"""UFM-Refine-980: the official high-resolution refinement recipe
(`bash_scripts/training/megatraining_refinement_980.sh` of the UFM `train` branch; every setting and
its source: docs/recipe.md): the whole refinement model trained at 980 from UFM-560.

  python train.py --config=configs/ufm980_refine.py --workdir=DIRREF980 \
      --config.model_init=snapshot:infinity1096/UFM-Base --config.input.data_root=/data/ufm

As the official script, it starts from the 560 base (`resume_model=infinity1096/UFM-Base`), not
from the 560 refiner: the refiner (5 x 5 window) starts fresh and trains at lr 1e-4 while the base
trains at 5e-7 (encoder) / 1e-5 (fusion transformer, flow head). Loss: the robust EPE on every
pixel whose target lies within a 25% margin, plus 10 x the refinement cross-entropy on rows of the
datasets suitable for refinement (of the optical-flow sets: FlyingThings3D). 16 unique pairs per
step (32 symmetrized rows), 20 epochs, 2 warmup epochs, cosine to 1%, clipping at 1.0; the
optical-flow datasets with the official samples per epoch (`mixture.RECIPES['refine980']`),
shapes (H in {644, 560, 490, 308} x 980) and augmentation.

Model: the official recipe's refinement structure (`ufm_refine_recipe`) with a 5 x 5 window: a
U-Net with BatchNorm (running statistics in the train state), `modulate` combination, encoder
taps [6, 23], no uncertainty head (no covisibility output). `:model=ufm_refine` trains the
released UFM-Refine structure instead (its covisibility head stays frozen, see optim.lr).
model_init: UFM-Base, as the official script (`resume_model=infinity1096/UFM-Base`,
megatraining_refinement_980.sh:47; a Hub ID or snapshot folder, or `ckpt:DIR560` for a 560 run of ours). As the
official resume_model, the source's flow normalisation buffers (flow_mean, flow_std) replace the
config's and base_shape / scale_strategy stay the config's (`model_init_flow_adaptor="buffers"`);
any other difference that changes outputs stops the run before training, naming the --config
override (`ufm_jax.training.model_init.check_structure`).

Smoke run (tiny recipe model, embedded synthetic pairs, random base):
  python train.py --config=configs/ufm980_refine.py:model=tiny_refine_recipe,data=synthetic,steps=20 \
      --workdir=DIR
"""

import ml_collections

from ufm_jax.training import config_lib, losses, optim
from ufm_jax.data import augment, mixture, pipeline


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, model="ufm_refine_recipe", data="of", steps=0)
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.seed = 42
  c.num_epochs = 20
  refine_datasets = ("blendedmvs", "flyingthings", "hypersim")
  if arg.data == "of":
    # dataset=ufm_980_highres, as ufm980.py: its samples per epoch, shapes and augmentation;
    # FlyingChairs' second view with the official zero flow (the "all" range supervises it).
    chairs = {"flyingchairs": {"backward_zero_flow": True}}
    c.input = pipeline.input_config(mixture.recipe("refine980", options=chairs), batch_size=32,
                                    longest_side=980, shapes=augment.SHAPES_980,
                                    augment={"fast_image_ops": False})
  elif arg.data == "synthetic":
    c.input = pipeline.input_config(mixture.synthetic_mixture(num_pairs=10_000, size=(56, 56)),
                                    batch_size=2, longest_side=56, aspect_ratios=(1.0,),
                                    num_workers=0)
    c.log_training_steps = 1
    refine_datasets = ("synthetic",)
  else:
    raise ValueError(f"configs/ufm980_refine.py: data={arg.data!r}; expected of or synthetic")
  if arg.steps:
    c.total_steps = arg.steps

  c.model_name = arg.model
  if arg.data == "synthetic":
    c.model = config_lib.model_options(dtype="float32", remat=False, scan_blocks=True)
  else:
    c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  c.model.param_init = "official"
  c.model.detach_uncertainty_head = False
  # adaptor_map/flow_scale_both.yaml; model_init's flow_mean / flow_std buffers replace these
  # two (model_init_flow_adaptor below), base_shape and scale_strategy stay.
  c.model.flow_adaptor = ml_collections.ConfigDict({
      "flow_mean": (0.0, 0.0), "flow_std": (25.0, 25.0), "base_shape": (224, 224),
      "scale_strategy": "scale_both"})
  c.model.refinement_range = 5
  # Official: plain DDP (train_pl.py:531-533), so the U-Net's BatchNorm takes its statistics
  # over each GPU's rows: 16 pairs over the paper's 8 GPUs, symmetrized = 4 rows
  # (models/refine.py BatchNorm.group_rows; unset: over the whole global batch).
  c.model.unet_batchnorm_group_rows = (4 if arg.data == "of" else config_lib.unset(int))
  c.model_init = config_lib.unset(str)  # UFM-Base (snapshot:ID) or a 560 run (ckpt:DIR)
  c.model_init_flow_adaptor = "buffers"   # official resume_model (train_pl.py:496-518)

  c.optim = ml_collections.ConfigDict({
      # uncertainty_head: official 1e-5, ignored there: its refinement model has no uncertainty
      # head, and neither has ours (a key for a group the model lacks is ignored, optim.py).
      # With model=ufm_refine, 0 keeps the released structure's covisibility head as loaded (no
      # loss trains it; 1e-5 would only let weight decay shrink it).
      "lr": {"encoder": 5e-7, "info_sharing": 1e-5, "output_head": 1e-5, "uncertainty_head": 0.0,
             "classification_head": 1e-4, "unet_feature": 1e-4},
      "groups": dict(optim.PARAM_GROUPS),
      "b1": 0.9, "b2": 0.95, "eps": 1e-8, "weight_decay": 0.05, "no_decay": config_lib.unset(str),
      "grad_clip_norm": 1.0,
      "warmup_epochs": 2.0, "fractional_warmup": True, "warmup_frac": config_lib.unset(float),
      "min_lr_rate": 0.01,
      # Official: a skipped non-finite step still steps the scheduler (train_pl.py:79-81).
      "skip_advances_schedule": True,
      "frozen": config_lib.unset(str), "trainable": config_lib.unset(str)})
  if arg.data == "synthetic":   # a smoke run: warm up over its first 10% of steps, not 2 epochs
    c.optim.warmup_epochs, c.optim.warmup_frac = None, 0.1

  # configs/loss/robust_epe_all_pixels_and_refinement.yaml, terms summed in this order.
  c.loss = ml_collections.ConfigDict({
      "terms": ("epe_all", "refinement_cross_entropy"),
      "epe_all": {"type": "robust", "range": "all", "margin": 0.25, "alpha": 0.5, "c": 0.24,
                  "multiplier": 1.0, "multiplier_applied": False, "invalid_gt": "zero",
                  "eps": 1e-4},
      "refinement_cross_entropy": {
          "type": "refinement_ce", "multiplier": 10.0, "datasets": refine_datasets,
          "max_pixels": 400_000, "window_margin": 1e-4, "taps": "truncate",
          "gather_dtype": "bfloat16", "eps": 1e-4},
      "shared_cleanup": True,
      # Official: DDP, each GPU's own loss over its rows (its own means and 400k-pixel cap),
      # gradients averaged: the mean of 8 group losses, one per GPU of the paper's run
      # (4 rows each), whatever our device count (losses.Recipe.groups; 1 pools the batch).
      "groups": losses.PAPER_GPUS if arg.data != "synthetic" else 1})   # smoke: 2 rows
  c.evals = ml_collections.ConfigDict(
      {"sintel": config_lib.bench_eval("sintel", resolution="980")} if arg.data == "of" else {})
  return c
