r"""UFM-560: the paper's recipe (sec. "Training Details", Table 1).

  python train.py --config=configs/ufm560.py:data=both --workdir=DIR \
      --config.model_init=dinov2:/path/to/facebook-dinov2-large --config.input.data_root=/data/ufm

Full UFM-Base (ViT-L/14 DINOv2 + 12 x 768 fusion + DPT heads), encoder initialised from pretrained
DINOv2 (`model_init`: the HF facebook/dinov2-large folder or its model.safetensors, or the original
dinov2_vitl14_pretrain.pth with the torch extra), the 12-dataset quota mixture, longest side 560
with aspect ratios 3:1..1:1, 48 epochs, AdamW (0.9, 0.95), weight decay 0.05, cosine decay with 10%
linear warmup, peak lr 1e-4 (transformer + heads) and 5e-6 (encoder), symmetrized batches of 96
pairs (48 unique). Arg `data=of|wb|both` selects the Table 4 data ablation (same number of epochs).
"""

import ml_collections

import configs.common as cc


def ufm_optim(lr=1e-4, encoder_lr=5e-6):
  return ml_collections.ConfigDict({
      "lr": {"default": lr, "encoder": encoder_lr}, "groups": {"encoder": r"^encoder/"},
      "b1": 0.9, "b2": 0.95, "eps": 1e-8, "weight_decay": 0.05, "no_decay": None,
      "warmup_frac": 0.1, "end_lr_frac": 0.0, "grad_clip_norm": None,
      "frozen": None, "trainable": None})


def common(c):
  c.seed = 0
  c.total_steps = None          # None: num_epochs * pairs per epoch / batch size
  c.mesh = "data:-1,fsdp:1"     # e.g. "data:2,fsdp:4" to shard params/opt state over 4 devices
  # FSDP over the largest divisible dimension for every tensor with >= 2^14 entries; small ones
  # (biases, norms, layer scales) are replicated.
  c.sharding_rules = [(r".*", "fsdp")]
  c.ckpt_steps = 1000
  c.keep_ckpt = 3
  c.async_checkpoint = True
  c.log_training_steps = 50
  c.loss = "ufm"
  c.loss_kwargs = ml_collections.ConfigDict(
      {"covis_weight": 10.0, "alpha": 0.5, "c": 0.24, "flow_pixels": "covisible"})
  c.apply_kwargs = {"symmetrized": True}  # rows (2i, 2i+1) are (a, b), (b, a): encode once
  c.matmul_precision = None
  return c


def sintel_eval(every=5000, max_pairs=200, resolution="560"):
  return ml_collections.ConfigDict({"type": "bench", "bench": "sintel", "every": every,
                                    "max_pairs": max_pairs, "resolution": resolution,
                                    "data_root": cc.DEFAULT_DATA_ROOT})


def get_config(arg=None):
  arg = cc.parse_arg(arg, data="both", model="ufm_base")
  names = {"both": cc.ALL, "of": cc.OPTICAL_FLOW, "wb": cc.WIDE_BASELINE}
  if arg.data not in names:
    raise ValueError(f"configs/ufm560.py: data={arg.data!r}; expected of, wb or both")
  c = common(ml_collections.ConfigDict())
  c.num_epochs = 48
  c.input = cc.input_config(cc.mixture(names[arg.data]), batch_size=96, longest_side=560)
  c.model_name = arg.model
  c.model = cc.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  # dinov2:PATH (facebook/dinov2-large), snapshot:DIR or ckpt:WORKDIR; typed so that
  # `--config.model_init=...` parses (a plain None field cannot be overridden from the flags).
  c.model_init = ml_collections.FieldReference(None, field_type=str)
  c.optim = ufm_optim()
  c.evals = ml_collections.ConfigDict({"sintel": sintel_eval()})
  return c
