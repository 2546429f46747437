r"""UFM-Refine: the classification refiner on a frozen UFM-560 base (supplementary "Training the
Refinement").

  python train.py --config=configs/ufm560_refine.py --workdir=DIRREF \
      --config.model_init=ckpt:DIR560 --config.input.data_root=/data/ufm

The base model (encoder, fusion transformer, DPT heads) is frozen: it gets no gradient and no
optimizer state; only the U-Net, classification head, combiners and the offset bias train, with
the refinement cross-entropy (`ufm_jax.refine_training.refinement_loss`). 30 epochs, lr 1e-4,
otherwise the 560 optimizer; BlendedMVS, MegaDepth, ScanNet++, StaticThings and Habitat with the
official recipe's samples per epoch (`mixture.RECIPES['refine560']`: static_pinhole_100k.yaml).

Smoke run on a fresh machine (tiny refine model, embedded synthetic pairs, random base):
  python train.py --config=configs/ufm560_refine.py:model=tiny_refine,data=synthetic,steps=20 \
      --workdir=DIR
"""

import ml_collections

from ufm_jax import config_lib
from ufm_jax.data import augment, mixture, pipeline

# Top-level parameter collections of UFM-Refine that train (ufm_jax.refine_training.TRAINABLE).
REFINER = ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias")


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, model="ufm_refine", data="refine", steps=0)
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.num_epochs = 30
  if arg.data == "refine":
    # configs/dataset/static_pinhole.yaml: the 560_many_ar shapes (square included) and
    # Habitat's `cropping` yaml (crop augmentation and low light, unlike the 560 recipe).
    c.input = pipeline.input_config(
        mixture.recipe("refine560"), batch_size=96, longest_side=560,
        shapes=augment.SHAPES_560_SQUARE,
        augment={"no_crop_datasets": (), "low_light_datasets": ("flyingchairs", "habitat"),
                 "fast_image_ops": True})
  elif arg.data == "synthetic":
    c.input = pipeline.input_config(mixture.synthetic_mixture(num_pairs=10_000, size=(56, 56)),
                                    batch_size=2, longest_side=56, aspect_ratios=(1.0,),
                                    num_workers=0)
    c.log_training_steps = 1
  else:
    raise ValueError(f"configs/ufm560_refine.py: data={arg.data!r}; expected refine or synthetic")
  if arg.steps:
    c.total_steps = arg.steps
  c.model_name = arg.model
  c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  if arg.data == "synthetic":
    c.model = config_lib.model_options(dtype="float32", remat=False, scan_blocks=True)
  c.model_init = config_lib.unset(str)  # the UFM-560 base
  c.loss = "refine"
  c.loss_kwargs = {}
  c.optim = config_lib.ufm_optim(lr=1e-4, encoder_lr=1e-4)
  c.optim.trainable = r"^(" + "|".join(REFINER) + r")(/|$)"
  c.evals = ml_collections.ConfigDict(
      {"sintel": config_lib.bench_eval("sintel")} if arg.data == "refine" else {})
  return c
