r"""UFM-980: bootstrapped from UFM-560 (sec. "Training Details").

  python train.py --config=configs/ufm980.py --workdir=DIR980 \
      --config.model_init=ckpt:DIR560 --config.input.data_root=/data/ufm

Parameters from a 560 checkpoint (`model_init`: a training workdir, a converted checkpoint or the
official UFM-Base snapshot), a fresh optimizer, 10x lower learning rates (1e-5 / 5e-7), the
optical-flow datasets only (the official recipe's samples per epoch, `mixture.RECIPES['ufm980']`),
flow supervised on all pixels with ground truth (not only covisible ones:
`loss_kwargs.flow_pixels="all"`), H in {644, 560, 490, 308} x 980, 15 epochs.
"""

import ml_collections

from ufm_jax import config_lib
from ufm_jax.data import augment, mixture, pipeline


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, model="ufm_base")
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.num_epochs = 15
  # The official shapes (980_many_opticalflow_ar) and augmentation, as ufm560.py.
  c.input = pipeline.input_config(mixture.recipe("ufm980"), batch_size=96,
                                  longest_side=980, shapes=augment.SHAPES_980,
                                  augment={"fast_image_ops": True})
  # Optical-flow benchmarks evaluate every pixel with valid flow, not just covisible ones.
  c.loss_kwargs.flow_pixels = "all"
  c.model_name = arg.model
  c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  c.model_init = config_lib.unset(str)  # required: the 560 run
  c.optim = config_lib.ufm_optim(lr=1e-5, encoder_lr=5e-7)
  c.evals = ml_collections.ConfigDict({"sintel": config_lib.bench_eval("sintel", resolution="980")})
  return c
