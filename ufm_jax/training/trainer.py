"""The pieces train.py wires together: model, input, loss, the jitted train step, predictions for
the evaluators, and the metrics writer. Each is built from the config alone.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import json
import math
import pathlib
from typing import Any, Callable

from absl import logging


def import_attr(spec: str):
  """'package.module:attr' -> the attribute."""
  module, attr = spec.split(":")
  return getattr(importlib.import_module(module), attr)


def build_model(config, activation_sharding=None, layer_gather=None):
  """The flax module of a training config (ufm_jax.models.variants.from_config)."""
  from ufm_jax.models import variants
  return variants.from_config(config, activation_sharding, layer_gather)


# The variable collections a training run keeps: parameters, and BatchNorm running statistics
# where the model has them (the refinement recipe's U-Net). "intermediates" (sown) are not state.
STATE_COLLECTIONS = ("params", "batch_stats")


def init_variables(model, image_shape, rng):
  """The model's own initializers (`model.init`) traced on one (H, W) pair: the one init path of
  training from scratch (jit it, or eval_shape it for the abstract tree). {"params"}, plus
  "batch_stats" for a model with BatchNorm."""
  import jax.numpy as jnp
  dummy = jnp.zeros((1, *image_shape, 3), jnp.uint8)
  variables = model.init(rng, dummy, dummy)
  return {k: variables[k] for k in STATE_COLLECTIONS if k in variables}


def init_params(model, image_shape, rng):
  """The parameters of `init_variables`."""
  return init_variables(model, image_shape, rng)["params"]


# Initialisation runs once, so for small models XLA's backend optimisations only cost compile time
# (fixture_small, 6.5M params: 11.3 s in all with them, 6.7 s without). Without them the random
# number generators run ~45 ns per parameter instead of ~7, which at full size costs more than
# the compile saves (UFM-Base, 428M: 26.6 s with them, 37.1 s without); the two meet somewhere
# past 100M. Figures from `python benchmarks/init_time.py` on the 2-core host.
_INIT_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0,
                          "xla_llvm_disable_expensive_passes": True}
_UNOPTIMIZED_INIT_MAX_PARAMS = 100_000_000


def init_compiler_options(num_params: int) -> dict:
  """XLA options for compiling `init_params` of a model with `num_params` parameters."""
  return _INIT_COMPILER_OPTIONS if num_params <= _UNOPTIMIZED_INIT_MAX_PARAMS else {}


def random_params(model, seed: int = 0, image_shape=None):
  """`init_params` compiled and run now on the default device, from PRNGKey(seed): the start
  from scratch of tests, benchmarks and tools. The parameter shapes do not depend on the image
  size; the default is two patches square, the smallest the model accepts."""
  import jax
  from ufm_jax.training import optim
  if image_shape is None:
    image_shape = (2 * model.config.encoder.patch_size,) * 2
  key = jax.random.PRNGKey(seed)
  lowered = jax.jit(functools.partial(init_params, model, tuple(image_shape))).lower(key)
  options = init_compiler_options(optim.count_params(lowered.out_info)["total"])
  return lowered.compile(compiler_options=options)(key)


def build_input(config, process_batch: int, seed: int, teacher=None):
  """(iterator of numpy batches, info) from config.input (grain pipeline of ufm_jax.data).
  `teacher` (ufm_jax.training.distill.Teacher): distillation rows with the teacher's view of each pair at
  its resolution (ufm_jax.data.distill_rows)."""
  if config.input.get("data_fn"):
    return import_attr(config.input.data_fn)(config.input, process_batch, seed)
  from ufm_jax.data import pipeline
  block = config.input
  if teacher is not None:
    block = block.to_dict()
    given = block.get("teacher_shape")
    if given and tuple(given) != tuple(teacher.resolution):
      raise ValueError(f"config.input.teacher_shape={tuple(given)} but the teacher sees "
                       f"{teacher.resolution}: set config.teacher.resolution instead")
    block["teacher_shape"] = tuple(teacher.resolution)
  return pipeline.make_train_iterator(block, process_batch=process_batch, seed=seed)


def schedule_steps(config, pairs_per_epoch):
  """(total optimizer steps, steps per epoch or None) of a run: config.total_steps, or
  config.num_epochs whole batches of the epoch's `pairs_per_epoch` rows (drop_last, as the
  official loaders; epochs and warmup count these)."""
  steps_per_epoch = int(pairs_per_epoch or 0) // int(config.input.batch_size) or None
  if config.total_steps:
    return int(config.total_steps), steps_per_epoch
  if config.get("num_epochs") and steps_per_epoch:
    return int(config.num_epochs * steps_per_epoch), steps_per_epoch
  raise ValueError("config needs total_steps, or num_epochs with a pipeline that knows its "
                   "pairs per epoch")


def build_loss(config, model=None, dataset_names=None):
  """loss(model outputs, batch, rng) -> (loss, aux dict of scalars): the recipe of config.loss
  (`ufm_jax.training.losses.recipe_from_config`). `model` supplies the refinement temperature,
  `dataset_names` (the pipeline's, in dataset_id order) the rows that may train the refiner."""
  from ufm_jax.training import losses
  if not config.get("loss"):
    raise ValueError("config.loss is missing: the loss terms of the recipe (see configs/ufm560.py)")
  temperature = getattr(getattr(model, "config", None), "temperature", None)
  recipe = losses.recipe_from_config(config.loss, temperature=temperature,
                                     dataset_names=dataset_names)

  def loss_fn(out, batch, rng=None):
    return recipe(out, batch, rng=rng)
  return loss_fn


def make_train_step(model, loss_fn, tx, labels, apply_kwargs, gather_params=None, seed: int = 0,
                    grad_accum: int = 1, mesh=None, param_sh=None, targets_fn=None,
                    skip_advances_schedule: bool = True):
  """train_step(state, batch[, teacher_variables]) -> (state, metrics): one optimizer update.

  `targets_fn(teacher_variables, batch) -> batch` (distillation, ufm_jax.training.distill): the frozen
  teacher's targets, computed per microbatch before the student's forward; its outputs leave
  through stop_gradient and its variables are no argument of the gradient.

  Gradients are taken w.r.t. the trainable params only (frozen ones enter through stop_gradient,
  so e.g. the refine stage runs no backward pass through the base model). `gather_params`
  (sharding.gathered) is applied to the params the forward pass uses. The loss gets a key of its
  own per step (PRNGKey(seed) folded with the step: the refinement loss draws its pixel cap).

  A model with BatchNorm (`state.batch_stats`) runs with train=True: it normalises with the
  batch's statistics (per group of `unet_batchnorm_group_rows` rows, else over the global batch)
  and the step stores the running statistics it returns, unless the update is skipped as
  non-finite. Other models are called exactly as before (no `train` argument).

  grad_accum=k > 1 runs the global batch as k microbatches in a loop (`accumulation.microbatches`)
  and applies one update with the mean of their gradients: the loss is the mean of k microbatch
  losses (each its own means and pixel cap), as the official trainer's accumulate_grad_batches
  (train_pl.py:543) or k more DDP replicas take it. BatchNorm normalises with each microbatch's
  statistics; the running statistics take one momentum step towards the mean of the
  microbatches' (for the running mean exactly the whole batch's step at k=1; the variance leaves
  out the spread between microbatches). Activation memory is that of one microbatch. `mesh`,
  `param_sh`: the batch's mesh and the params' shardings, which keep each microbatch on every
  device and the summed gradients sharded like the params. `skip_advances_schedule`: whether a
  skipped (non-finite) update moves the learning-rate schedules on (`optim.apply_gradients`).
  """
  import jax
  import jax.numpy as jnp
  import optax
  from ufm_jax.training import accumulation, optim

  if grad_accum < 1:
    raise ValueError(f"grad_accum={grad_accum}: the microbatches per step must be 1 or more")

  def loss_and_aux(trainable, frozen, batch_stats, batch, rng, teacher=None):
    if targets_fn is not None:
      batch = targets_fn(teacher, batch)
    params = optim.merge_params(trainable, jax.lax.stop_gradient(frozen))
    if gather_params is not None:
      params = gather_params(params)
    if batch_stats is None:
      out = model.apply({"params": params}, batch["image0"], batch["image1"], **apply_kwargs)
      new_stats = None
    else:
      out, updated = model.apply({"params": params, "batch_stats": batch_stats}, batch["image0"],
                                 batch["image1"], **apply_kwargs, train=True,
                                 mutable=["batch_stats"])
      new_stats = updated["batch_stats"]
    loss, aux = loss_fn(out, batch, rng)
    return loss, (aux, new_stats)

  grad_fn = jax.value_and_grad(loss_and_aux, has_aux=True)
  grad_sh = None if param_sh is None else optim.split_trainable(param_sh, labels)[0]

  def accumulated(trainable, frozen, batch_stats, batch, rng, teacher=None):
    micro = accumulation.microbatches(batch, grad_accum, mesh,
                                      accumulation.pair_rows(apply_kwargs))

    def body(g_sum, xs):
      j, mb = xs
      (loss, (aux, stats)), g = grad_fn(trainable, frozen, batch_stats, mb,
                                        jax.random.fold_in(rng, j), teacher)
      g_sum = jax.tree.map(lambda a, b: a + b.astype(a.dtype), g_sum, g)
      return accumulation.constrain(g_sum, grad_sh), (loss, aux, stats)

    zeros = accumulation.constrain(jax.tree.map(jnp.zeros_like, trainable), grad_sh)
    g_sum, (losses, aux, stats) = jax.lax.scan(body, zeros, (jnp.arange(grad_accum), micro))
    mean = lambda x: jnp.mean(x, axis=0).astype(x.dtype)   # noqa: E731
    g = jax.tree.map(lambda x: x / grad_accum, g_sum)
    stats = None if stats is None else jax.tree.map(mean, stats)
    return (jnp.mean(losses), (jax.tree.map(jnp.mean, aux), stats)), g

  def train_step(state, batch, teacher=None):
    trainable, frozen = optim.split_trainable(state.params, labels)
    rng = jax.random.fold_in(jax.random.PRNGKey(seed), state.step)
    step_fn = grad_fn if grad_accum == 1 else accumulated
    (loss, (aux, new_stats)), g = step_fn(trainable, frozen, state.batch_stats, batch, rng,
                                          teacher)
    grads = optim.merge_params(g, jax.tree.map(jnp.zeros_like, frozen))
    new_state, ok = optim.apply_gradients(state, grads, loss, tx, skip_advances_schedule)
    if new_stats is not None:   # a skipped (non-finite) step leaves the running statistics too
      new_state = new_state.replace(batch_stats=jax.tree.map(
          lambda new, old: jnp.where(ok, new, old), new_stats, state.batch_stats))
    metrics = dict(aux, loss=loss, grad_norm=optax.global_norm(g), update_ok=ok)
    return new_state, metrics

  return train_step


def make_predict(model, apply_kwargs, gather_params=None):
  """predict(variables, batch) -> {"flow", "covisibility"} for evaluation batches; "covisibility"
  only from a model that has an uncertainty head, plus "flow_covariance" from one that has a
  flow covariance adaptor. `variables`: {"params"[, "batch_stats"]} (`TrainState.variables`); a
  model with BatchNorm normalises with its running statistics (train=False).

  Training batches are symmetrized ((a, b), (b, a) rows whose images are encoded once); evaluation
  pairs are not, so `symmetrized` is dropped: with it every odd row would be predicted for the
  reverse of the pair before it.
  """
  kwargs = {k: v for k, v in apply_kwargs.items() if k != "symmetrized"}

  def predict(variables, batch):
    if gather_params is not None:
      variables = dict(variables, params=gather_params(variables["params"]))
    out = model.apply(variables, batch["image0"], batch["image1"], **kwargs)
    return {k: out[k] for k in ("flow", "covisibility", "flow_covariance") if k in out}

  return predict


@dataclasses.dataclass
class TrainSetup:
  """Everything train.py compiles, from the config: model, optimizer, shardings, jitted fns."""
  model: Any
  tx: Any
  labels: Any
  schedules: Any
  init_fn: Callable            # rng -> {"params"[, "batch_stats"]} (the modules' initializers)
  abstract_params: Any
  abstract_state: Any
  param_sh: Any
  state_sh: Any
  batch_sh: Any
  train_step: Callable         # jitted (state, batch) -> (state, metrics); state donated
  predict: Callable            # jitted (state.variables(), batch) -> {"flow"[, "covisibility"]}
  variables_sh: Any = None     # shardings of init_fn's output
  teacher: Any = None          # ufm_jax.training.distill.Teacher of a distillation run
  labelled: bool = True        # the batches carry labels (a distillation run: keep_labels)

  def row_shapes(self, image_shape) -> dict:
    """{key: (per-row shape, numpy dtype)} of a training row at (H, W) `image_shape`."""
    import numpy as np
    h, w = image_shape
    rows = {"image0": ((h, w, 3), np.uint8), "image1": ((h, w, 3), np.uint8)}
    if self.labelled:
      rows.update({"flow": ((h, w, 2), np.float32), "covisibility": ((h, w), np.bool_),
                   "flow_valid": ((h, w), np.bool_), "covis_valid": ((h, w), np.bool_)})
    if self.teacher is not None:
      from ufm_jax.data import distill_rows
      rows.update(distill_rows.row_shapes(self.teacher.resolution))
    return rows

  def abstract_batch(self, batch_size: int, image_shape, row_ids: bool = False):
    """ShapeDtypeStructs of a global training batch, sharded as the step expects (AOT).
    `row_ids`: with the per-row dataset_id and epoch the training pipeline adds
    (ufm_jax.data.pipeline; the refinement loss reads dataset_id)."""
    import jax
    rows = self.row_shapes(image_shape)
    if row_ids:
      import numpy as np
      rows.update(dataset_id=((), np.int32), epoch=((), np.int32))
    return {k: jax.ShapeDtypeStruct((batch_size,) + s, d, sharding=self.batch_sh)
            for k, (s, d) in rows.items()}

  def init_state(self, seed: int = 0):
    """A fresh sharded TrainState from the modules' initializers (benchmarks, smoke runs)."""
    import jax
    variables = jax.jit(self.init_fn, out_shardings=self.variables_sh)(jax.random.PRNGKey(seed))
    return self.create_state(variables)

  def create_state(self, variables):
    """The sharded TrainState (step 0, fresh optimizer state) of {"params"[, "batch_stats"]}."""
    import jax
    from ufm_jax.training import optim
    return jax.jit(lambda v: optim.TrainState.create(v["params"], self.tx, v.get("batch_stats")),
                   out_shardings=self.state_sh)(variables)

  def random_batch(self, mesh, batch_size: int, image_shape, seed: int = 0):
    """A global batch of random images and labels in the training layout (benchmarks); for a
    distillation run the teacher's view of each row is its crop stretched to the teacher's
    resolution."""
    import numpy as np
    from ufm_jax.training import sharding
    rng = np.random.default_rng(seed)
    b, (h, w) = batch_size, image_shape
    host = {"image0": rng.integers(0, 256, (b, h, w, 3), dtype=np.uint8),
            "image1": rng.integers(0, 256, (b, h, w, 3), dtype=np.uint8)}
    if self.labelled:
      host.update({"flow": rng.normal(0, 5, (b, h, w, 2)).astype(np.float32),
                   "covisibility": rng.random((b, h, w)) < 0.7,
                   "flow_valid": np.ones((b, h, w), bool),
                   "covis_valid": np.ones((b, h, w), bool)})
    if self.teacher is not None:
      from ufm_jax.data import distill_rows
      th, tw = self.teacher.resolution
      m = distill_rows.crop_map((h, w), (0, 0), (th, tw))
      host.update({"teacher_image0": rng.integers(0, 256, (b, th, tw, 3), dtype=np.uint8),
                   "teacher_image1": rng.integers(0, 256, (b, th, tw, 3), dtype=np.uint8),
                   "teacher_to_crop0": np.repeat(m[None], b, 0),
                   "teacher_to_crop1": np.repeat(m[None], b, 0)})
    return sharding.make_global_batch(host, mesh)

  def sharded_abstract_state(self):
    import jax
    return jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                        self.abstract_state, self.state_sh)


def setup(config, mesh, image_shape, total_steps: int, steps_per_epoch=None,
          dataset_names=None, teacher=None) -> TrainSetup:
  """Model (activations constrained to the batch sharding of `mesh`), optimizer, parameter and
  state shardings (config.sharding_rules, config.sharding_min_size), the jitted train step and
  eval predict. Nothing is allocated: params exist only as shapes until `init_fn` runs.

  steps_per_epoch: optimizer steps per epoch (for warmup counted in epochs; default
  total_steps / config.num_epochs). dataset_names: the pipeline's, in dataset_id order.
  A distillation config (`config.teacher`): the step runs `teacher` (required there:
  ufm_jax.training.teacher.from_config(config, mesh), which puts nothing on the devices) before the
  student, its variables an argument the step binds on its first call (distill.BoundStep); the
  planner and the FLOP count lower it with the teacher's abstract variables."""
  import jax
  from ufm_jax.training import optim, sharding
  gather_params, layer_gather = sharding.fsdp_gathers(mesh, config)
  model = build_model(config, sharding.activation_constraint(mesh), layer_gather)
  apply_kwargs = dict(config.apply_kwargs)
  init_fn = functools.partial(init_variables, model, tuple(image_shape))
  abstract_variables = jax.eval_shape(init_fn, jax.random.PRNGKey(0))
  # Parameter groups, learning rates and weight decay see the parameters only.
  abstract_params = abstract_variables["params"]
  trainable_fn = import_attr(config.trainable_filter) if config.get("trainable_filter") else None
  if steps_per_epoch is None and config.get("num_epochs"):
    steps_per_epoch = total_steps / config.num_epochs
  tx, labels, schedules = optim.make_optimizer(config.optim, abstract_params, total_steps,
                                               trainable_fn=trainable_fn,
                                               steps_per_epoch=steps_per_epoch)
  min_size = config.sharding_min_size
  param_sh = sharding.tree_shardings(abstract_params, mesh, config.sharding_rules, min_size)
  abstract_state = jax.eval_shape(
      lambda v: optim.TrainState.create(v["params"], tx, v.get("batch_stats")), abstract_variables)
  state_sh = sharding.tree_shardings(abstract_state, mesh, config.sharding_rules, min_size)
  variables_sh = {"params": param_sh}
  if abstract_state.batch_stats is not None:
    variables_sh["batch_stats"] = state_sh.batch_stats
  batch_sh = sharding.batch_sharding(mesh)
  repl = sharding.replicated(mesh)
  loss_fn = build_loss(config, model, dataset_names)
  targets_fn = None
  if config.get("teacher") and teacher is None:
    # Loading it here would import model_io, which imports this module (a cycle): the callers
    # (train.py, the planner, flops.model_flops) load it.
    raise ValueError("config.teacher is set: pass setup(..., teacher=ufm_jax.training.teacher."
                     "from_config(config, mesh))")
  if teacher is not None:
    from ufm_jax.training import distill
    targets_fn = distill.make_targets_fn(teacher, gather_params,
                                         symmetrized=bool(apply_kwargs.get("symmetrized")))
  step = make_train_step(model, loss_fn, tx, labels, apply_kwargs, gather_params,
                         seed=config.seed, grad_accum=config.grad_accum, mesh=mesh,
                         param_sh=param_sh, targets_fn=targets_fn,
                         skip_advances_schedule=config.optim.get("skip_advances_schedule", True))
  if teacher is None:
    train_step = jax.jit(step, in_shardings=(state_sh, batch_sh),
                         out_shardings=(state_sh, repl), donate_argnums=(0,))
  else:
    train_step = distill.BoundStep(jax.jit(
        step, in_shardings=(state_sh, batch_sh, teacher.shardings),
        out_shardings=(state_sh, repl), donate_argnums=(0,)), teacher)
  predict = jax.jit(make_predict(model, apply_kwargs, gather_params),
                    in_shardings=(variables_sh, batch_sh), out_shardings=repl)
  labelled = teacher is None or bool(config.input.get("keep_labels"))
  return TrainSetup(model, tx, labels, schedules, init_fn, abstract_params, abstract_state,
                    param_sh, state_sh, batch_sh, train_step, predict, variables_sh, teacher,
                    labelled)


class Writer:
  """metrics.jsonl / eval.jsonl (process 0) + TensorBoard events (scalars and PNG images)."""

  def __init__(self, workdir: pathlib.Path, active: bool):
    self.active = active
    self.workdir = workdir
    self.tb = None
    if active:
      try:
        from tensorboardX import SummaryWriter
        self.tb = SummaryWriter(str(workdir / "tb"))
      except ImportError:  # pragma: no cover
        logging.warning("tensorboardX missing: no TensorBoard events")

  def _append(self, name, record):
    if self.active:
      # A metric with nothing to average (e.g. epe_occluded on pairs without occlusions) is NaN:
      # written as null, so that every line stays standard JSON for jq and friends.
      from ufm_jax.data.io import json_safe
      with open(self.workdir / name, "a") as f:
        f.write(json.dumps(json_safe(record), allow_nan=False) + "\n")

  def scalars(self, name, step, record, prefix):
    self._append(name, record)
    if self.tb is not None:
      for k, v in record.items():
        # Undefined (non-finite) values are left out of TensorBoard instead of warning per event.
        if isinstance(v, (int, float)) and k != "step" and math.isfinite(v):
          self.tb.add_scalar(f"{prefix}/{k}", v, step)
      self.tb.flush()

  def image(self, tag, step, img):
    """An RGB uint8 [H, W, 3] picture. tensorboardX's add_image PNG-encodes through PIL, which
    is not a dependency: encode with OpenCV and hand the bytes to the Summary proto."""
    if self.tb is None:
      return
    from tensorboardX.proto.summary_pb2 import Summary
    from ufm_jax.data.io import encode_png
    png = encode_png(img)
    summary = Summary(value=[Summary.Value(tag=tag, image=Summary.Image(
        height=img.shape[0], width=img.shape[1], colorspace=3, encoded_image_string=png))])
    self.tb.file_writer.add_summary(summary, step)

  def close(self):
    if self.tb is not None:
      self.tb.close()
