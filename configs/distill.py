r"""Distillation: a small student learns from a UFM teacher's predictions on unlabeled pairs.

  python train.py --config=configs/distill.py:teacher=workdirs/synthetic,student=synth_small,data=synthetic --workdir=workdirs/student
  python train.py --config=configs/distill.py:teacher=infinity1096/UFM-Base,student=ufm_small,data=frames,data_root=/data/robot_frames,strides=1-2-4 \
      --workdir=DIR --config.model_init=dinov2:/path/to/facebook-dinov2-small

The teacher (`teacher=`: anything `ufm_jax.load` takes, a converted checkpoint, a train.py
workdir, a snapshot folder or a Hugging Face ID, or variant:NAME for a structure with random
weights) runs inside the jitted train step on the same mesh, its variables sharded by the
student's rules and never updated (ufm_jax.training.distill: why they are a step argument, neither
train state nor constants). It predicts on the un-augmented pair at its resolution; its flow,
covisibility and (where it has one) flow covariance are warped into the student's crop. The
student (`student=`: a ufm_jax/models/variants.py variant: ufm_small, ufm_tiny, synth_small, ...)
sees the pair through the official flow-pathway augmentation (resize, shared crop, colour).
No label is read: `data=` is a registered source (its labels ignored), `pairs_folder` (pair
folders, image0.png and image1.png suffice) or `frames` (a folder of video frames, or of
recordings, paired at `strides`, as `infer --frames` reads them), the latter two under
`data_root`. `labels=W` (W > 0) mixes a labelled source's labels back in: the official two
terms at weight W beside the teacher's.

Loss (each term a named key of config.loss, ufm_jax/training/distill_loss.py): teacher_robust, the
official robust EPE (alpha 0.5, c 0.24) against the teacher's flow on the teacher's covisible
pixels, each pixel weighted by the teacher's covariance where it has one
(`--config.loss.teacher_robust.covariance=off` to ignore it); teacher_bce, the covisibility BCE
(x 10) against the teacher's covisibility as a soft target. `loss=l1` is the synthetic config's
(alpha 1, c 0.01), the default of recipe=synthetic as in configs/synthetic.py.

Args: teacher, student, data, data_root, strides (frames: e.g. 1-2-4), pairs (pairs per
epoch of a source), steps, batch (global rows, both directions counted), size (recipe
synthetic: the square image side), lr (peak learning rate of the groups that are not the
encoder), loss (paper|l1), labels (weight of the label terms; 0: none read), teacher_res (HxW
the teacher sees; default: a workdir's training shape, else its inference resolution), eval
(the held-out evals on or off), recipe (synthetic|560; default synthetic for data=synthetic, else
560), init (teacher: the student starts from the teacher's parameters wherever their paths and
shapes agree, the rest at init, model_init=teacher:SRC, the log saying how many parameters it
copied; fresh, the default for every teacher: from its own init or --config.model_init, nothing
from the teacher, the log saying so), eval_root (a folder
of held-out pairs of the same kind as data=: every 1000 steps, 100 in recipe synthetic, the
student is scored against the teacher's predictions on 32 of them, `teacher_agreement`;
data=synthetic is also scored against the true flow of its val split), colour (the colour part
of the student's augmentation, `input.augment.photometric`: recipe 560, default true, the official
augmentation; recipe synthetic, default false, a departure docs/distillation.md explains;
colour=true restores it), tie
(the student's query/key tie at init, `info_sharing.tied_qk_init`; -1, the default, keeps the
variant's: 2.0 for synth_small).

recipe=synthetic follows configs/synthetic.py (56 px shift pairs, batches of 8 rows, lr 1e-3
everywhere, loss l1, float32, the student from its own init; with data=synthetic the held-out
eval every 100 steps), except for 4000 steps (twice the teacher's: docs/distillation.md has why)
and that the student's input takes the official flow-pathway augmentation's geometry (resize,
shared crop, the teacher's outputs warped into it; its colour jitter only with colour=true),
where configs/synthetic.py trains the teacher on its shift pairs without any;
recipe=560 follows the 560 recipe (configs/ufm560.py: its shapes, scaled to the student's
inference width for ufm_tiny's 392, AdamW, encoder lr 5e-6 and 1e-4 elsewhere, 10% warmup and
cosine to 1%, bf16, scan, remat, the official init). The
demonstration and the students' sizes and speed: docs/distillation.md.
"""

import os

import ml_collections

from ufm_jax.runtime import model_io
from ufm_jax.training import config_lib, optim
from ufm_jax.data import augment, mixture, pipeline
from ufm_jax.models import variants


def _teacher_block(arg) -> ml_collections.ConfigDict:
  checkpoint = arg.teacher
  hub = not os.path.exists(checkpoint) and model_io.official_hub_id(checkpoint)
  resolution = None
  if arg.teacher_res:
    resolution = tuple(int(v) for v in arg.teacher_res.lower().split("x"))
  return ml_collections.ConfigDict({
      "checkpoint": checkpoint, "snapshot": bool(hub),
      "revision": config_lib.unset(str), "step": config_lib.unset(int),
      "dtype": config_lib.unset(str), "resolution": resolution, "interpolation": "bilinear"})


def _datasets(arg, hw):
  if arg.data == "synthetic":
    return mixture.synthetic_mixture(num_pairs=arg.pairs or 100_000, size=hw, pair_type="shift",
                                     max_shift=10)
  if arg.data in ("pairs_folder", "frames") and not arg.data_root:
    raise ValueError(f"configs/distill.py: data={arg.data} reads its pairs from data_root=DIR")
  # A dataset of the official mixtures is looked for under the data root (its official or raw
  # layout, ufm_jax.data.mixture); any other source reads data_root itself.
  root = None
  if arg.data_root and arg.data not in mixture.LAYOUTS:
    root = os.path.abspath(os.path.expanduser(arg.data_root))
  options = {}
  if arg.data == "frames":
    options["strides"] = tuple(int(s) for s in str(arg.strides).split("-"))
  block = {arg.data: {"quota": arg.pairs or 100_000, "root": root, "options": options}}
  return ml_collections.ConfigDict(block)


def _shapes(student):
  """The 560 recipe's training shapes, scaled to the width the student infers at (ufm_tiny:
  392), each side a multiple of 14."""
  width = variants.get(student).inference_resolution[1]
  if width == 560:
    return augment.SHAPES_560
  return tuple((max(14, round(h * width / 560 / 14) * 14), width) for h, _ in augment.SHAPES_560)


def get_config(arg=None):
  arg = config_lib.parse_arg(arg, teacher="", student="ufm_small", data="synthetic",
                             data_root="", strides="1", pairs=0, steps=0, batch=0, size=56,
                             lr=0.0, loss="", labels=0.0, teacher_res="", eval=True,
                             recipe="", eval_root="", init="", colour="", tie=-1.0)
  if not arg.teacher:
    raise ValueError("configs/distill.py: name the teacher, e.g. "
                     "configs/distill.py:teacher=workdirs/synthetic,student=synth_small")
  recipe = arg.recipe or ("synthetic" if arg.data == "synthetic" else "560")
  if recipe not in ("synthetic", "560"):
    raise ValueError(f"configs/distill.py: recipe must be 'synthetic' or '560', got {recipe!r}")
  synthetic = recipe == "synthetic"
  if arg.colour.lower() not in ("", "true", "false", "1", "0"):
    raise ValueError(f"configs/distill.py: colour must be true or false, got {arg.colour!r}")
  # The synthetic recipe drops the colour jitter, with which its students stay on the zero-flow
  # plateau (docs/distillation.md); the 560 recipe keeps it.
  colour = arg.colour.lower() in ("true", "1") if arg.colour else not synthetic
  loss = arg.loss or ("l1" if synthetic else "paper")
  if loss not in ("paper", "l1"):
    raise ValueError(f"configs/distill.py: loss must be 'paper' or 'l1', got {arg.loss!r}")
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.teacher = _teacher_block(arg)
  # Twice the teacher's synthetic steps: the student first spends a few hundred on the zero-flow
  # plateau, and the cosine schedule must not run out before it has caught up.
  c.total_steps = arg.steps or (4000 if synthetic else 100_000)
  c.num_epochs = config_lib.unset(int)

  hw = (arg.size, arg.size)
  shapes = (hw,) if synthetic else _shapes(arg.student)
  c.input = pipeline.input_config(
      _datasets(arg, hw), batch_size=arg.batch or (8 if synthetic else 96), shapes=shapes,
      **({"data_root": arg.data_root} if arg.data_root and arg.data in mixture.LAYOUTS else {}),
      # Labels are read only when a loss term uses them.
      keep_labels=arg.labels > 0,
      **({"num_workers": 0, "read_threads": 2, "prefetch_buffer_size": 2,
          "augment": {"photometric": colour}} if synthetic else
         {"augment": {"fast_image_ops": True, "photometric": colour}}))

  alpha, scale = (1.0, 0.01) if loss == "l1" else (0.5, 0.24)
  terms = ("teacher_robust", "teacher_bce")
  c.loss = ml_collections.ConfigDict({
      "teacher_robust": {"type": "teacher_robust", "alpha": alpha, "c": scale,
                         "multiplier": 1.0, "covisible_threshold": 0.5, "covariance": "auto",
                         "covariance_scale": 1.0, "eps": 1e-4},
      "teacher_bce": {"type": "teacher_bce", "multiplier": 10.0, "out_of_crop": "not_covisible",
                      "eps": 1e-6},
      "shared_cleanup": True, "groups": 1})
  if arg.labels > 0:
    terms += ("robust_epe", "covisibility_ce")
    c.loss.robust_epe = {"type": "robust", "range": "covisible", "alpha": alpha, "c": scale,
                         "multiplier": arg.labels, "multiplier_applied": True,
                         "invalid_gt": "zero", "eps": 1e-4}
    c.loss.covisibility_ce = {"type": "bce", "multiplier": 10.0 * arg.labels, "eps": 1e-6}
  c.loss.terms = terms

  c.model_name = arg.student
  if synthetic:
    c.model = config_lib.model_options(dtype="float32", remat=False, scan_blocks=False)
    # The student infers at the size it trained at (`ufm_jax.predict`, evaluate.py).
    c.model.inference_resolution = hw
  else:
    c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
    c.model.param_init = "official"
    c.model.flow_adaptor = ml_collections.ConfigDict({
        "flow_mean": (0.0, 0.0), "flow_std": (25.0, 25.0), "base_shape": (224, 224),
        "scale_strategy": "scale_both"})
  if arg.tie >= 0:
    c.model.info_sharing = {"tied_qk_init": arg.tie}
  # dinov2:PATH (facebook/dinov2-small for ufm_small / ufm_tiny), snapshot:DIR or ckpt:WORKDIR;
  # init=teacher: every parameter the student shares with the teacher (path and shape) from it.
  init = arg.init or "fresh"
  if init not in ("teacher", "fresh"):
    raise ValueError(f"configs/distill.py: init must be 'teacher' or 'fresh', got {arg.init!r}")
  c.model_init = config_lib.unset(str)
  if init == "teacher":
    c.model_init = "teacher:" + ("snapshot:" if c.teacher.snapshot else "") + arg.teacher

  if synthetic:
    lr = {g: arg.lr or 1e-3 for g in optim.PARAM_GROUPS}
    schedule = {"warmup_epochs": config_lib.unset(float), "warmup_frac": 0.05, "min_lr_rate": 0.0}
  else:
    lr = {"encoder": 5e-6, **{g: arg.lr or 1e-4 for g in optim.PARAM_GROUPS if g != "encoder"}}
    schedule = {"warmup_epochs": config_lib.unset(float), "warmup_frac": 0.1,
                "min_lr_rate": 0.01}
  c.optim = ml_collections.ConfigDict({
      "lr": lr, "groups": dict(optim.PARAM_GROUPS), "b1": 0.9, "b2": 0.95, "eps": 1e-8,
      "weight_decay": 0.05, "no_decay": config_lib.unset(str), "grad_clip_norm": 1.0,
      **schedule, "frozen": config_lib.unset(str), "trainable": config_lib.unset(str)})

  c.ckpt_steps = 100 if synthetic else 1000
  c.keep_ckpt = 2 if synthetic else 3
  c.log_training_steps = 10 if synthetic else 50
  c.evals = ml_collections.ConfigDict()
  if arg.data == "synthetic" and arg.eval:
    # The held-out pairs' true flow scores the student; training never reads a label.
    c.evals.heldout = ml_collections.ConfigDict({
        "type": "heldout", "source": "synthetic", "root": None,
        "kwargs": {"split": "val", "num_pairs": 32, "size": hw, "pair_type": "shift",
                   "max_shift": 10},
        "num_pairs": 32, "shape": hw, "batch_size": 16, "every": 100, "num_images": 2})
  if arg.eval_root and arg.eval:
    # Held-out pairs of the run's own domain, scored against the teacher (no ground truth).
    held_out = ml_collections.ConfigDict(arg.to_dict())
    held_out.data_root = arg.eval_root
    (source, spec), = _datasets(held_out, hw).items()
    c.evals.teacher = ml_collections.ConfigDict({
        "type": "teacher_agreement", "source": source, "root": spec.root,
        "kwargs": spec.options.to_dict(), "teacher": c.teacher.to_dict(), "num_pairs": 32,
        "shape": shapes[0], "batch_size": 8, "every": 100 if synthetic else 1000,
        "num_images": 2})
  return c
