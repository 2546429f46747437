r"""UFM-560: the paper's recipe (sec. "Training Details", Table 1).

  python train.py --config=configs/ufm560.py:data=both --workdir=DIR \
      --config.model_init=dinov2:/path/to/facebook-dinov2-large --config.input.data_root=/data/ufm

Full UFM-Base (ViT-L/14 DINOv2 + 12 x 768 fusion + DPT heads), encoder initialised from pretrained
DINOv2 (`model_init`: the HF facebook/dinov2-large folder or its model.safetensors, or the original
dinov2_vitl14_pretrain.pth with the torch extra), the 12 datasets with the samples per epoch of
the official recipe (`mixture.RECIPES['ufm560']`: old_setting_100k.yaml), the official training
shapes (H in {420, 364, 308, 280, 168} x 560) and augmentation, 48 epochs, AdamW (0.9, 0.95),
weight decay 0.05, cosine decay with 10% linear warmup, peak lr 1e-4 (transformer + heads) and
5e-6 (encoder), symmetrized batches of 96 pairs (48 unique). Arg `data=of|wb|both` selects the
Table 4 data ablation (same number of epochs).
"""

import ml_collections

from ufm_jax import config_lib
from ufm_jax.data import augment, mixture, pipeline


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, data="both", model="ufm_base")
  names = {"both": mixture.ALL, "of": mixture.OPTICAL_FLOW, "wb": mixture.WIDE_BASELINE}
  if arg.data not in names:
    raise ValueError(f"configs/ufm560.py: data={arg.data!r}; expected of, wb or both")
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.num_epochs = 48
  # The official shapes and augmentation (ufm_jax.data.augment, docs/recipe.md); the one
  # deviation, fast_image_ops (OpenCV's bicubic and HSV for PIL's), keeps the host CPU per row
  # within budget (docs/host_input.md).
  c.input = pipeline.input_config(mixture.recipe("ufm560", names[arg.data]), batch_size=96,
                                  longest_side=560, shapes=augment.SHAPES_560,
                                  augment={"fast_image_ops": True})
  c.model_name = arg.model
  c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  # dinov2:PATH (facebook/dinov2-large), snapshot:DIR or ckpt:WORKDIR; typed so that
  # `--config.model_init=...` parses (a plain None field cannot be overridden from the flags).
  c.model_init = config_lib.unset(str)
  c.optim = config_lib.ufm_optim()
  c.evals = ml_collections.ConfigDict({"sintel": config_lib.bench_eval("sintel")})
  return c
