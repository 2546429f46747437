r"""UFM-980: the official high-resolution recipe (`bash_scripts/training/megatraining_980.sh` of
the UFM `train` branch; every setting and its source: docs/recipe.md), bootstrapped from UFM-560.

  python train.py --config=configs/ufm980.py --workdir=DIR980 \
      --config.model_init=snapshot:infinity1096/UFM-Base --config.input.data_root=/data/ufm

Parameters from UFM-Base, as the official script (`resume_model=infinity1096/UFM-Base`,
megatraining_980.sh:41; `model_init`: a Hub ID or snapshot folder, or `ckpt:DIR560` for a 560
run of ours), a fresh optimizer. As the official resume_model, the source's flow normalisation
buffers (flow_mean, flow_std) replace the config's and its base_shape / scale_strategy stay the
config's (`model_init_flow_adaptor="buffers"`, ufm_jax/training/model_init.py). The optical-flow datasets only, with the official recipe's samples per
epoch (`mixture.RECIPES['ufm980']`), the official shapes (H in {644, 560, 490, 308} x 980) and
augmentation. 16 unique pairs per step (32 symmetrized rows), 15 epochs. Peak lr 5e-7 (encoder)
and 1e-5 (fusion transformer, flow head) with 2 warmup epochs, cosine to 1%; the covisibility head
is frozen (lr 0: no gradient, no optimizer state) and has no loss: the robust EPE is taken on every
pixel whose ground-truth target lies within a 25% margin around the image
(`loss.epe_all.range="all"`, margin 0.25).

Arg `cov=True` (docs/uncertainty.md; not in the official recipe) is for a 560 run trained with
`configs/ufm560.py:cov=True` (the same uncertainty head): the covariance is in px, so it is
trained again at 980 by the Gaussian NLL on the pixels `epe_all` supervises; for that the
uncertainty head trains (lr 1e-5, the flow head's) and keeps the 560 recipe's covisibility BCE,
which holds its covisibility channel while the layers it shares with the covariance move.
"""

import ml_collections

from ufm_jax.training import config_lib, losses, optim
from ufm_jax.data import augment, mixture, pipeline


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, model="ufm_base", cov=False)
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.seed = 42
  c.num_epochs = 15
  # The official shapes (980_many_opticalflow_ar) and augmentation, as ufm560.py.
  # FlyingChairs' second view carries the official zero flow, which the "all" range below
  # supervises on every pixel (quirk: docs/recipe.md; False drops those rows' supervision).
  chairs = {"flyingchairs": {"backward_zero_flow": True}}
  c.input = pipeline.input_config(mixture.recipe("ufm980", options=chairs), batch_size=32,
                                  longest_side=980, shapes=augment.SHAPES_980,
                                  augment={"fast_image_ops": False})

  c.model_name = arg.model
  c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  c.model.detach_uncertainty_head = False
  c.model.param_init = "official"
  # adaptor_map/flow_scale_both.yaml; model_init's flow_mean / flow_std buffers replace these
  # two (model_init_flow_adaptor below), base_shape and scale_strategy stay.
  c.model.flow_adaptor = ml_collections.ConfigDict({
      "flow_mean": (0.0, 0.0), "flow_std": (25.0, 25.0), "base_shape": (224, 224),
      "scale_strategy": "scale_both"})
  c.model_init = config_lib.unset(str)  # required: UFM-Base (snapshot:ID) or a 560 run (ckpt:DIR)
  c.model_init_flow_adaptor = "buffers"   # official resume_model (train_pl.py:496-518)

  c.optim = ml_collections.ConfigDict({
      "lr": {"encoder": 5e-7, "info_sharing": 1e-5, "output_head": 1e-5, "uncertainty_head": 0.0},
      "groups": dict(optim.PARAM_GROUPS),
      "b1": 0.9, "b2": 0.95, "eps": 1e-8, "weight_decay": 0.05, "no_decay": config_lib.unset(str),
      "grad_clip_norm": 1.0,
      "warmup_epochs": 2.0, "fractional_warmup": True, "warmup_frac": config_lib.unset(float),
      "min_lr_rate": 0.01,
      # Official: a skipped non-finite step still steps the scheduler (train_pl.py:79-81).
      "skip_advances_schedule": True,
      "frozen": config_lib.unset(str), "trainable": config_lib.unset(str)})

  # configs/loss/robust_epe_all_pixels.yaml: no covisibility term.
  c.loss = ml_collections.ConfigDict({
      "terms": ("epe_all",),
      "epe_all": {"type": "robust", "range": "all", "margin": 0.25, "alpha": 0.5, "c": 0.24,
                  "multiplier": 1.0, "multiplier_applied": False, "invalid_gt": "zero",
                  "eps": 1e-4},
      "shared_cleanup": True,
      # Official: DDP, each GPU's own loss over its rows (its own means and 400k-pixel cap),
      # gradients averaged: the mean of 8 group losses, one per GPU of the paper's run
      # (4 rows each), whatever our device count (losses.Recipe.groups; 1 pools the batch).
      "groups": losses.PAPER_GPUS})
  if arg.cov:
    c.optim.lr.uncertainty_head = 1e-5
    c.loss.terms = tuple(c.loss.terms) + ("covisibility_ce",)
    c.loss.covisibility_ce = {"type": "bce", "multiplier": 10.0, "eps": 1e-6}
    config_lib.add_flow_covariance(c, pixels="epe_all")
  c.evals = ml_collections.ConfigDict({"sintel": config_lib.bench_eval("sintel", resolution="980")})
  return c
