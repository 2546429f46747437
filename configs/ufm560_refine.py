r"""UFM-Refine: the classification refiner on a frozen UFM-560 base (supplementary "Training the
Refinement").

  python train.py --config=configs/ufm560_refine.py --workdir=DIRREF \
      --config.model_init=ckpt:DIR560 --config.input.data_root=/data/ufm

The base model (encoder, fusion transformer, DPT heads) is frozen: it gets no gradient and no
optimizer state; only the U-Net, classification head, combiners and the offset bias train, with
the refinement cross-entropy (`ufm_jax.refine_training.refinement_loss`). 30 epochs, lr 1e-4,
otherwise the 560 optimizer; BlendedMVS, MegaDepth, Habitat and ScanNet++ (Table 1 quotas).
"""

import ml_collections

import configs.common as cc
from configs import ufm560

# Top-level parameter collections of UFM-Refine that train (ufm_jax.refine_training.TRAINABLE).
REFINER = ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias")


def get_config(arg=None):
  arg = cc.parse_arg(arg, model="ufm_refine")
  c = ufm560.common(ml_collections.ConfigDict())
  c.num_epochs = 30
  c.input = cc.input_config(cc.mixture(cc.REFINE), batch_size=96, longest_side=560)
  c.model_name = arg.model
  c.model = ml_collections.ConfigDict({"dtype": "bfloat16", "remat": True})
  c.model_init = ml_collections.FieldReference(None, field_type=str)  # the UFM-560 base
  c.loss = "refine"
  c.loss_kwargs = {}
  c.optim = ufm560.ufm_optim(lr=1e-4, encoder_lr=1e-4)
  c.optim.trainable = r"^(" + "|".join(REFINER) + r")(/|$)"
  c.evals = ml_collections.ConfigDict({"sintel": ufm560.sintel_eval()})
  return c
