r"""A tiny UFM on the embedded synthetic data: trains in minutes on 2 CPU cores, no download.

  python train.py --config=configs/synthetic.py --workdir=workdirs/synthetic

Pairs are rendered on the fly (ufm_jax.data.synthetic, small camera motion by default); the
held-out eval renders the synthetic `val` split (scenes never seen in training) and reports EPE
before training (step 0), every 100 steps and at the end.

Measured (2 shared CPU cores): held-out covisible EPE 4.23 -> 3.11 px at size=56 after 300 steps
(~3 min on a quiet machine), 8.7 -> 7.2 px (flow-valid pixels) at 112. Both plateau at about the
zero-flow EPE (3.13 px on the val pairs at 56); 1500 steps at 56 reach 3.08. The tiny model learns the flow
statistics and covisibility quickly but not yet matching: the 2x EPE goal is NOT reached.

Tried without reaching 2x (size=56, batch 8, all on the 2 cores shared with other jobs, load
average 5-7, so 5-10 min per run instead of ~3-5 quiet): `model=tiny_synth` (7 px patches,
8 x 8 tokens, sin-cos position init) 4.80 -> 3.10 px (300 steps, with DINOv2's learned random
position table) and 4.80 -> 3.12 (200 steps, sin-cos); with `pairs=pan` (4..10 degree pans)
7.93 -> 6.73 px at step 100 (lr 1e-3; 6.89 at lr 3e-3), 7.94 -> 6.68 at step 200 (sin-cos), and
with a 128-wide 4-block fusion 7.26 -> 6.71 at step 200. The zero-flow EPE of these 32 `val`
pairs is 3.13 px (flow) and 6.81 px (pan): every run ends at about predicting no motion, and its
training flow loss stops falling after ~50 steps. `model=tiny_synth,steps=1000,batch=4,lr=2e-3`
(4.5 min, load average ~3) gives 4.80 -> 3.124 / 3.127 / 3.125 / 3.125 px at steps 250..1000:
the zero-flow value to 3 decimals, i.e. the model collapses to (near) zero flow, the minimiser of
the alpha=0.5 robust loss when motion directions are random.

Args (`configs/synthetic.py:steps=100,size=56`): pairs=flow|wide|mixed|pan (pair types), steps,
batch (global pairs per step, both directions of 4 unique pairs by default), size (square images,
a multiple of 14), eval (the held-out evaluation on/off), model (a configs/models.py variant,
e.g. tiny_synth), lr (peak learning rate of every parameter group).
"""

import ml_collections

import configs.common as cc
from configs import ufm560


def get_config(arg=None):
  arg = cc.parse_arg(arg, pairs="flow", steps=300, batch=8, size=56, eval=True,
                    model="tiny", lr=1e-3)
  hw = (arg.size, arg.size)
  c = ufm560.common(ml_collections.ConfigDict())
  c.seed = 0
  c.total_steps = arg.steps
  c.num_epochs = None
  c.input = cc.input_config(
      cc.synthetic_mixture(num_pairs=100_000, size=hw, pair_type=arg.pairs),
      batch_size=arg.batch, longest_side=hw[1], aspect_ratios=(1.0,), num_workers=0,
      read_threads=2, prefetch_buffer_size=2)
  c.model_name = arg.model
  c.model = ml_collections.ConfigDict({"dtype": "float32", "remat": False})
  c.model_init = None
  c.optim = ufm560.ufm_optim(lr=arg.lr, encoder_lr=arg.lr)
  c.optim.warmup_frac = 0.05
  c.optim.grad_clip_norm = 1.0
  c.mesh = "data:-1,fsdp:1"
  c.ckpt_steps = 100
  c.keep_ckpt = 2
  c.log_training_steps = 10
  c.evals = ml_collections.ConfigDict()
  if not arg.eval:
    return c
  c.evals = ml_collections.ConfigDict({"heldout": {
      "type": "heldout", "source": "synthetic", "root": None,
      "kwargs": {"split": "val", "num_pairs": 32, "size": hw, "pair_type": arg.pairs},
      "num_pairs": 32, "shape": hw, "batch_size": 16, "every": 100, "num_images": 2}})
  return c
