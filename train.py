r"""Trains UFM (or its refiner) on a device mesh.

  python train.py --config=configs/synthetic.py --workdir=workdirs/synthetic
  python train.py --config=configs/ufm560.py:data=both --workdir=DIR --config.input.batch_size=96

Sections: mesh, data, model and optimizer, sharding, step, checkpoint, evals, loop. The run resumes
from the latest checkpoint in --workdir by itself; SIGTERM saves and exits cleanly.
"""

from __future__ import annotations

import functools
import importlib
import json
import math
import os
import pathlib
import sys
import time

from absl import app, flags, logging
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file("config", None, "Training config file.", lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Where checkpoints, logs and metrics go.")
flags.mark_flags_as_required(["config", "workdir"])


def _import(spec: str):
  """'package.module:attr' -> the attribute."""
  module, attr = spec.split(":")
  return getattr(importlib.import_module(module), attr)


def build_model(config):
  """The flax module from config: `config.model_fn` ("module:fn", called with config.model) or the
  named variant of configs/models.py with `config.model` overrides."""
  if config.get("model_fn"):
    return _import(config.model_fn)(config.model)
  from configs import models as model_variants
  from ufm_jax.models import ufm
  return ufm.model_from_config(model_variants.get(config.model_name, **config.model.to_dict()))


def build_input(config, process_batch: int, seed: int):
  """(iterator of numpy batches, info) from config.input (grain pipeline of ufm_jax.data)."""
  if config.input.get("data_fn"):
    return _import(config.input.data_fn)(config.input, process_batch, seed)
  from ufm_jax.data import pipeline
  return pipeline.make_train_iterator(config.input, process_batch=process_batch, seed=seed)


def build_loss(config):
  """loss(model outputs, batch) -> (loss, aux dict of scalars)."""
  kwargs = dict(config.get("loss_kwargs", {}))
  if config.get("loss", "ufm") == "refine":
    from ufm_jax import losses, refine_training

    def refine_loss(out, batch):
      loss, aux = refine_training.refinement_loss(
          out["log_softmax"], out["flow_before_refinement"], batch["flow"],
          batch["covisibility"], batch["flow_valid"], **kwargs)
      epe = losses.end_point_error(out["flow"], batch["flow"])
      mask = losses.flow_supervision_mask(batch)
      aux = dict(aux, loss_refine=loss, epe=losses._masked_mean(epe, mask))  # pylint: disable=protected-access
      return loss, aux
    return refine_loss
  from ufm_jax import losses
  return functools.partial(losses.ufm_loss, **kwargs)


def make_train_step(model, loss_fn, tx, labels, apply_kwargs):
  """train_step(state, batch) -> (state, metrics): one optimizer update.

  Gradients are taken w.r.t. the trainable params only (frozen ones enter through stop_gradient,
  so e.g. the refine stage runs no backward pass through the base model).
  """
  import jax
  import jax.numpy as jnp
  import optax
  from ufm_jax import optim

  def loss_and_aux(trainable, frozen, batch):
    params = optim.merge_params(trainable, jax.lax.stop_gradient(frozen))
    out = model.apply({"params": params}, batch["image0"], batch["image1"], **apply_kwargs)
    return loss_fn(out, batch)

  def train_step(state, batch):
    trainable, frozen = optim.split_trainable(state.params, labels)
    (loss, aux), g = jax.value_and_grad(loss_and_aux, has_aux=True)(trainable, frozen, batch)
    grads = optim.merge_params(g, jax.tree.map(jnp.zeros_like, frozen))
    new_state, ok = optim.apply_gradients(state, grads, loss, tx)
    metrics = dict(aux, loss=loss, grad_norm=optax.global_norm(g), update_ok=ok)
    return new_state, metrics

  return train_step


def make_predict(model, apply_kwargs):
  """predict(params, batch) -> {"flow", "covisibility"} for evaluation batches.

  Training batches are symmetrized ((a, b), (b, a) rows whose images are encoded once); evaluation
  pairs are not, so `symmetrized` is dropped: with it every odd row would be predicted for the
  reverse of the pair before it.
  """
  kwargs = {k: v for k, v in apply_kwargs.items() if k != "symmetrized"}

  def predict(params, batch):
    out = model.apply({"params": params}, batch["image0"], batch["image1"], **kwargs)
    return {"flow": out["flow"], "covisibility": out["covisibility"]}

  return predict


class EvalResult:
  def __init__(self, scalars, images=None):
    self.scalars, self.images = scalars, images or {}


class HeldoutEval:
  """EPE and covisibility accuracy on fixed held-out pairs of a registered source.

  epe / px1,3,5 (% of pixels with EPE > t) pool all covisible pixels with valid flow (the pixels
  UFM is supervised on); epe_all pools every pixel with valid flow; epe_zero is the EPE that
  predicting no motion would get on the `epe` pixels (the bar a model that matches must beat).

  Config: source, root, kwargs (source options), num_pairs, shape (H, W: centre crop, which keeps
  flow labels valid), batch_size, every, num_images (flow/covis pictures to TensorBoard).
  """

  def __init__(self, cfg, mesh):
    import numpy as np
    from ufm_jax import sharding
    from ufm_jax.data import get_source
    self.every = int(cfg.get("every", 0))
    self.mesh = mesh
    src = get_source(cfg.source, cfg.get("root"), **dict(cfg.get("kwargs", {})))
    n = min(int(cfg.num_pairs), len(src))
    h, w = cfg.shape
    keys = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")
    samples = []
    for i in range(n):
      s = src[i]
      H, W = s["image0"].shape[:2]
      if H < h or W < w:
        raise ValueError(f"eval source {cfg.source}: sample {i} is {H}x{W}, smaller than the eval "
                         f"shape {h}x{w}")
      y0, x0 = (H - h) // 2, (W - w) // 2
      samples.append({k: np.asarray(s[k])[y0:y0 + h, x0:x0 + w] for k in keys})
    self.samples = samples
    div = sharding.batch_divisor(mesh)
    bs = int(cfg.get("batch_size", div))
    self.batch_size = -(-bs // div) * div
    self.num_images = int(cfg.get("num_images", 2))

  def run(self, predict, params) -> EvalResult:
    import jax
    import numpy as np
    from ufm_jax import sharding
    n, bs = len(self.samples), self.batch_size
    P, pid = jax.process_count(), jax.process_index()
    epe_sum = valid_sum = acc_sum = cv_sum = epe_all_sum = all_sum = zero_sum = 0.0
    px = {1: 0.0, 3: 0.0, 5: 0.0}
    images = {}
    for start in range(0, n, bs):
      chunk = self.samples[start:start + bs]
      real = len(chunk)
      chunk = chunk + [chunk[-1]] * (bs - real)  # pad to a fixed shape; padded rows are ignored
      batch = {k: np.stack([c[k] for c in chunk]) for k in chunk[0]}
      per = bs // P
      local = {k: v[pid * per:(pid + 1) * per] for k, v in batch.items()}
      out = jax.device_get(predict(params, sharding.make_global_batch(local, self.mesh)))
      flow = np.asarray(out["flow"], np.float64)[:real]
      covis = np.asarray(out["covisibility"])[:real]
      epe = np.linalg.norm(flow - batch["flow"][:real], axis=-1)
      fa = batch["flow_valid"][:real]
      fv = fa & batch["covisibility"][:real]  # the model is supervised (and used) there only
      epe_sum += float(epe[fv].sum())
      zero_sum += float(np.linalg.norm(batch["flow"][:real], axis=-1)[fv].sum())
      valid_sum += float(fv.sum())
      epe_all_sum += float(epe[fa].sum())
      all_sum += float(fa.sum())
      for t in px:
        px[t] += float((epe[fv] > t).sum())
      cvv = batch["covis_valid"][:real]
      acc_sum += float(((covis >= 0.5) == batch["covisibility"][:real])[cvv].sum())
      cv_sum += float(cvv.sum())
      for j in range(real):
        i = start + j
        if i < self.num_images:
          try:
            from ufm_jax import viz
          except ImportError:
            break
          images[f"pair{i}"] = viz.panel(batch["image0"][j], batch["image1"][j], flow[j].astype(
              np.float32), covis[j])
          images[f"pair{i}_gt"] = viz.panel(batch["image0"][j], batch["image1"][j],
                                            batch["flow"][j], batch["covisibility"][j])
    scalars = {"epe": epe_sum / max(valid_sum, 1.0), "epe_all": epe_all_sum / max(all_sum, 1.0),
               "epe_zero": zero_sum / max(valid_sum, 1.0),
               **{f"px{t}": 100.0 * v / max(valid_sum, 1.0) for t, v in px.items()},
               "covis_acc": acc_sum / max(cv_sum, 1.0), "num_pairs": float(n)}
    return EvalResult(scalars, images)


class BenchEval:
  """A benchmark of ufm_jax.evaluators (evaluate.py's benches) run on the current params.

  Config: bench (e.g. sintel), every, max_pairs, resolution (560 | 980 | native), data_root.
  Benches whose data is absent are skipped with a warning (once).
  """

  def __init__(self, cfg, model):
    self.cfg, self.model = cfg, model
    self.every = int(cfg.get("every", 0))
    self.missing = False

  def run(self, predict, params) -> EvalResult:
    del predict  # the benches run ufm_jax.predict pair by pair at their own resolution
    from ufm_jax import evaluators
    if self.missing:
      return EvalResult({})
    runner = evaluators.Runner(self.model, params, self.cfg.get("resolution"))
    try:
      metrics, _ = evaluators.run_bench(self.cfg.bench, runner, self.cfg.get("data_root"),
                                        max_pairs=self.cfg.get("max_pairs"), progress=False)
    except evaluators.MissingDataError as e:
      logging.warning("eval %s skipped from now on: %s", self.cfg.bench, e)
      self.missing = True
      return EvalResult({})
    return EvalResult({k.replace("/", "_"): float(v) for k, v in metrics.items()
                       if isinstance(v, (int, float))})


def build_evaluators(evals_cfg, mesh, model):
  """name -> evaluator: `type: heldout` (fixed pairs of a source, sharded forward), `type: bench`
  (a benchmark of ufm_jax.evaluators), or "module:Class" (called with (cfg, mesh))."""
  out = {}
  for name, cfg in dict(evals_cfg).items():
    kind = cfg.get("type", "heldout")
    if kind == "heldout":
      out[name] = HeldoutEval(cfg, mesh)
    elif kind == "bench":
      out[name] = BenchEval(cfg, model)
    else:
      out[name] = _import(kind)(cfg, mesh)
  return out


class Writer:
  """metrics.jsonl / eval.jsonl (process 0) + TensorBoard events + console lines."""

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
      with open(self.workdir / name, "a") as f:
        f.write(json.dumps(record) + "\n")

  def scalars(self, name, step, record, prefix):
    self._append(name, record)
    if self.tb is not None:
      for k, v in record.items():
        if isinstance(v, (int, float)) and k != "step":
          self.tb.add_scalar(f"{prefix}/{k}", v, step)
      self.tb.flush()

  def image(self, tag, step, img):
    """An RGB uint8 [H, W, 3] picture, PNG-encoded with OpenCV (tensorboardX's own add_image
    needs PIL)."""
    if self.tb is None:
      return
    import cv2
    from tensorboardX.proto.summary_pb2 import Summary
    ok, png = cv2.imencode(".png", img[..., ::-1])
    if not ok:
      return
    summary = Summary(value=[Summary.Value(tag=tag, image=Summary.Image(
        height=img.shape[0], width=img.shape[1], colorspace=3, encoded_image_string=png.tobytes()))])
    self.tb._get_file_writer().add_summary(summary, step)  # pylint: disable=protected-access

  def close(self):
    if self.tb is not None:
      self.tb.close()


def main(argv):
  del argv
  config = _CONFIG.value
  workdir = pathlib.Path(_WORKDIR.value).absolute()

  # ---------------------------------------------------------------------------------- mesh
  from ufm_jax import sharding
  sharding.maybe_initialize_distributed()
  import jax
  import jax.numpy as jnp
  import numpy as np

  if config.get("matmul_precision"):
    jax.config.update("jax_default_matmul_precision", config.matmul_precision)
  from ufm_jax import checkpoint as ckpt_lib
  from ufm_jax import optim

  mesh = sharding.make_mesh(config.mesh)
  is_main = jax.process_index() == 0
  workdir.mkdir(parents=True, exist_ok=True)
  if is_main:
    ckpt_lib.write_json_atomic(workdir / "config.json", json.loads(config.to_json_best_effort()))
    (workdir / "command.txt").write_text(" ".join([sys.executable] + sys.argv) + "\n")
  logging.info("mesh %s over %d devices (%d processes)", dict(mesh.shape), jax.device_count(),
               jax.process_count())

  # ---------------------------------------------------------------------------------- data
  process_batch = sharding.local_batch_size(config.input.batch_size, mesh)
  train_iter, data_info = build_input(config, process_batch, config.seed)
  pairs_per_epoch = int(data_info.get("pairs_per_epoch") or 0)
  if config.get("total_steps"):
    total_steps = int(config.total_steps)
  elif config.get("num_epochs") and pairs_per_epoch:
    total_steps = int(math.ceil(config.num_epochs * pairs_per_epoch / config.input.batch_size))
  else:
    raise ValueError("config needs total_steps, or num_epochs with a pipeline that knows its "
                     "pairs per epoch")
  steps_per_epoch = pairs_per_epoch / config.input.batch_size if pairs_per_epoch else None
  sample_shape = data_info["image_shape"]  # (H, W) of the first training shape
  logging.info("data: %s", {k: v for k, v in data_info.items() if k != "iterator"})

  # ----------------------------------------------------------------------- model and optimizer
  model = build_model(config)
  apply_kwargs = dict(config.get("apply_kwargs", {}))
  loss_fn_outer = build_loss(config)
  rng = jax.random.PRNGKey(config.seed)
  dummy = jnp.zeros((1, *sample_shape, 3), jnp.uint8)
  init_fn = lambda r: model.init(r, dummy, dummy)["params"]  # noqa: E731
  abstract_params = jax.eval_shape(init_fn, rng)
  trainable_fn = None
  if config.get("trainable_filter"):
    trainable_fn = _import(config.trainable_filter)
  tx, labels, schedules = optim.make_optimizer(config.optim, abstract_params, total_steps,
                                               trainable_fn=trainable_fn)
  counts = optim.count_params(abstract_params, labels)
  logging.info("parameters per group: %s", counts)

  # ---------------------------------------------------------------------------------- sharding
  param_sh = sharding.tree_shardings(abstract_params, mesh, config.sharding_rules)
  abstract_state = jax.eval_shape(lambda p: optim.TrainState.create(p, tx), abstract_params)
  state_sh = sharding.tree_shardings(abstract_state, mesh, config.sharding_rules)
  batch_sh = sharding.batch_sharding(mesh)
  repl = sharding.replicated(mesh)
  sharding.log_shardings(param_sh, abstract_params)

  # ---------------------------------------------------------------------------------- step
  train_step = make_train_step(model, loss_fn_outer, tx, labels, apply_kwargs)
  p_train_step = jax.jit(train_step, in_shardings=(state_sh, batch_sh),
                         out_shardings=(state_sh, repl), donate_argnums=(0,))

  p_predict = jax.jit(make_predict(model, apply_kwargs), in_shardings=(param_sh, batch_sh),
                      out_shardings=repl)

  # ---------------------------------------------------------------------------------- checkpoint
  manager = ckpt_lib.make_manager(workdir, config.ckpt_steps, config.keep_ckpt,
                                  config.get("async_checkpoint", True))
  state, start_step = ckpt_lib.restore_latest(manager, jax.tree.map(
      lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract_state, state_sh),
      train_iter)
  if state is None:
    start_step = 0
    params = jax.jit(init_fn, out_shardings=param_sh)(rng)
    if config.get("model_init"):
      host_params = jax.tree.map(np.asarray, params)
      loaded, report = ckpt_lib.load_init_params(config.model_init, host_params, model.config)
      if is_main:
        print(report.summary(), flush=True)
      params = jax.device_put(loaded, param_sh)
    state = jax.jit(lambda p: optim.TrainState.create(p, tx), out_shardings=state_sh)(params)
  else:
    print(f"resumed from step {start_step}", flush=True)

  # ---------------------------------------------------------------------------------- evals
  evaluators = build_evaluators(config.get("evals", {}), mesh, model)
  writer = Writer(workdir, is_main)

  def run_evals(step, force=False):
    for name, ev in evaluators.items():
      if force or (ev.every and step % ev.every == 0):
        res = ev.run(p_predict, state.params)
        if not res.scalars:
          continue
        rec = {"step": step, "eval": name, **res.scalars}
        if is_main:
          print(f"[eval {name}] step {step}: " +
                ", ".join(f"{k}={v:.4g}" for k, v in res.scalars.items()), flush=True)
        writer.scalars("eval.jsonl", step, rec, f"eval/{name}")
        for tag, img in res.images.items():
          writer.image(f"{name}/{tag}", step, img)

  # ---------------------------------------------------------------------------------- loop
  log_every = int(config.log_training_steps)
  if start_step == 0:
    run_evals(0)
  t_last, step_last = time.time(), start_step
  t_start, first_step = None, start_step
  step = start_step
  with ckpt_lib.PreemptionGuard() as guard:
    while step < total_steps:
      local = next(train_iter)
      batch = sharding.make_global_batch(local, mesh)
      state, metrics = p_train_step(state, batch)
      step += 1
      if step % log_every == 0 or step == total_steps:
        m = jax.device_get(metrics)
        now = time.time()
        if t_start is None:  # exclude compilation from the throughput and ETA
          t_start, first_step = now, step
        pairs_s = (step - step_last) * config.input.batch_size / max(now - t_last, 1e-9)
        done = step - first_step
        eta = (now - t_start) / done * (total_steps - step) if done > 0 else float("nan")
        lrs = optim.current_lrs(schedules, step - 1)
        rec = {"step": step, "epoch": step / steps_per_epoch if steps_per_epoch else None,
               **{k: float(v) for k, v in m.items()},
               "skipped": int(jax.device_get(state.skipped)),
               "lr": lrs.get("default"), **{f"lr_{g}": v for g, v in lrs.items()},
               "pairs_per_s": pairs_s}
        writer.scalars("metrics.jsonl", step, rec, "train")
        logging.info("process %d metrics %s", jax.process_index(), json.dumps(rec))
        if is_main:
          ep = f" ep {rec['epoch']:.3f}" if rec["epoch"] is not None else ""
          print(f"step {step}/{total_steps}{ep} loss {rec['loss']:.5f} "
                f"flow {rec.get('loss_flow', float('nan')):.5f} "
                f"covis {rec.get('loss_covis', float('nan')):.5f} "
                f"lr " + " ".join(f"{g}={v:.2e}" for g, v in lrs.items()) +
                f" {pairs_s:.1f} pairs/s ETA {_fmt_eta(eta)}" +
                (f" skipped {rec['skipped']}" if rec["skipped"] else ""), flush=True)
        if not m["update_ok"]:
          logging.warning("step %d: non-finite loss or gradient, update skipped (total %d)",
                          step, rec["skipped"])
        t_last, step_last = now, step
      ckpt_lib.save(manager, step, state, train_iter, force=step == total_steps)
      run_evals(step, force=step == total_steps)
      if guard.should_stop(step):
        ckpt_lib.save(manager, step, state, train_iter, force=True)
        manager.wait_until_finished()
        print(f"preempted: saved step {step}, exiting", flush=True)
        break
  manager.wait_until_finished()
  manager.close()
  writer.close()


def _fmt_eta(sec):
  if not math.isfinite(sec):
    return "?"
  sec = int(sec)
  return f"{sec // 3600}h{sec % 3600 // 60:02d}m{sec % 60:02d}s"


if __name__ == "__main__":
  app.run(main)
