r"""Trains UFM (or its refiner) on a device mesh.

  python train.py --config=configs/synthetic.py --workdir=workdirs/synthetic
  python train.py --config=configs/ufm560.py:data=both --workdir=DIR --config.input.batch_size=96
  python train.py --config=configs/ufm560.py --compile_only --topology=v5e-8 --config.grad_accum=3

Sections: plan (--compile_only), mesh, teacher (distillation only), data,
model/optimizer/sharding/step (ufm_jax.training.trainer.setup), checkpoint, evals, loop. The run
resumes from the latest checkpoint in --workdir by itself; SIGTERM saves and exits cleanly. The
run accounts for its own time in WORKDIR/goodput.json across restarts (ufm_jax.training.goodput);
--config.profile_steps=A:B writes a jax.profiler trace of steps A..B-1 to WORKDIR/profile
(docs/training.md). --compile_only builds the same mesh, shardings and step from the config
alone, compiles the step (on these devices, or with --topology for a TPU slice through libtpu),
times the recipe's input pipeline on this host for the host feed (ufm_jax.testing.host_feed;
--host_ms_per_row instead), prints the plan (ufm_jax.planning.planner; its JSON is the last line)
and exits 0 when the step fits a device's memory (a TPU chip's HBM, a GPU's, or on a CPU host its
RAM shared by the CPU devices), 3 when it does not, 1 on an error (docs/scale.md).
"""

from __future__ import annotations

import json
import math
import pathlib
import re
import sys
import time

from absl import app, flags, logging
from ml_collections import config_flags

_STARTED = time.time()   # the run's wall time counts from here (goodput.json)

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "the training config, PATH[:ARG] (configs/*.py)", lock_config=True)
_WORKDIR = flags.DEFINE_string(
    "workdir", None, "checkpoints, logs and metrics; a run resumes from it")
_COMPILE_ONLY = flags.DEFINE_bool(
    "compile_only", False, "compile the run's step from the config, no data; print the plan; "
    "exit 0 if the step fits a device's memory, 3 if it does not, 1 on an error")
_TOPOLOGY = flags.DEFINE_string(
    "topology", None, "with --compile_only: compile for this TPU slice (v5e-8, ...) via libtpu")
_HOST_MS = flags.DEFINE_float(
    "host_ms_per_row", None, "with --compile_only: host CPU ms per training row for the host "
    "feed, instead of timing the recipe's input pipeline on this host")
_CAPACITY_GIB = flags.DEFINE_float(
    "capacity_gib", None, "with --compile_only: the memory one device may use, GiB (default: "
    "the chip's HBM, a GPU's allocator limit, or host RAM over the CPU devices)")
flags.mark_flag_as_required("config")
_FLAGS = (_CONFIG, _WORKDIR, _COMPILE_ONLY, _TOPOLOGY, _HOST_MS, _CAPACITY_GIB)
EXIT_DOES_NOT_FIT = 3   # --compile_only: the step needs more memory than a device has


def main(argv):
  del argv
  if not flags.FLAGS["verbosity"].present:
    # One console line per log step plus warnings; --verbosity=0 shows the INFO logs (orbax's too).
    logging.set_verbosity(logging.WARNING)
  config = _CONFIG.value
  for holder in (_TOPOLOGY, _HOST_MS, _CAPACITY_GIB):
    if holder.value is not None and not _COMPILE_ONLY.value:
      print(f"error: --{holder.name} plans a step: it needs --compile_only", file=sys.stderr)
      return 2
  if not _COMPILE_ONLY.value and not _WORKDIR.value:
    print("error: --workdir is required (except with --compile_only)", file=sys.stderr)
    return 2
  from ufm_jax.training import goodput, profiling
  try:
    profile = profiling.profile_steps(config.get("profile_steps"))
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  import jax
  if _TOPOLOGY.value:
    jax.config.update("jax_platforms", "cpu")   # the slice is only compiled for, from this host
  if config.matmul_precision:
    jax.config.update("jax_default_matmul_precision", config.matmul_precision)

  # ---------------------------------------------------------------------------------- plan
  if _COMPILE_ONLY.value:
    # What this run would build (mesh, shardings, grad_accum, the step), from the config alone.
    import dataclasses

    from ufm_jax.planning import planner
    from ufm_jax.testing import host_feed
    feed = host_feed.for_plan(config, _HOST_MS.value)   # before the compile takes the cores
    tgt = planner.target(_TOPOLOGY.value)
    if _CAPACITY_GIB.value is not None:
      tgt = dataclasses.replace(tgt, capacity=int(_CAPACITY_GIB.value * 2 ** 30),
                                capacity_is="--capacity_gib")
    result = planner.plan(config, tgt, host_feed=feed)
    planner.report(result)
    print(planner.to_json(result), flush=True)
    if result["fits"] is None:
      print(f"error: no memory capacity known for {tgt.device_kind}: pass --capacity_gib",
            file=sys.stderr)
      return 1
    return 0 if result["fits"] else EXIT_DOES_NOT_FIT

  # ---------------------------------------------------------------------------------- mesh
  workdir = pathlib.Path(_WORKDIR.value).absolute()
  from ufm_jax.training import sharding
  sharding.maybe_initialize_distributed()
  import numpy as np
  from ufm_jax.runtime import checkpoint as ckpt_lib
  from ufm_jax.training import accumulation, loop_control, losses, model_init, optim, trainer
  from ufm_jax.data import io
  from ufm_jax.evaluators import train_evals

  mesh = sharding.make_mesh(config.mesh)
  is_main = jax.process_index() == 0
  # The source's flow normalisation buffers into the config before it is written (official
  # resume_model; config.model_init_flow_adaptor).
  for line in model_init.adopt_flow_adaptor(config):
    if is_main:
      print(f"model_init: {line}", flush=True)
  workdir.mkdir(parents=True, exist_ok=True)
  if is_main:
    io.write_json_atomic(workdir / "config.json", json.loads(config.to_json_best_effort()))
    (workdir / "command.txt").write_text(" ".join([sys.executable] + sys.argv) + "\n")
  # Written now, so that a restart knows of this run; ended at the loop's end or at exit.
  gp = goodput.Tracker(workdir, is_main, started=_STARTED, at_exit=True)
  logging.info("mesh %s over %d devices (%d processes)", dict(mesh.shape), jax.device_count(),
               jax.process_count())

  # ---------------------------------------------------------------------------------- teacher
  # Distillation (configs/distill.py): a frozen teacher that the train step runs before the
  # student, on the un-augmented pair; its variables go to the mesh with the first step.
  from ufm_jax.training import teacher as teacher_lib
  teacher = teacher_lib.from_config(config, mesh)
  if teacher is not None and is_main:
    print(teacher.describe(), flush=True)

  # ---------------------------------------------------------------------------------- data
  process_batch = sharding.local_batch_size(config.input.batch_size, mesh)
  if config.grad_accum > 1:   # refused here, before the pipeline starts, rather than at trace time
    accumulation.check_divisible(config.input.batch_size, config.grad_accum,
                                 sharding.batch_divisor(mesh),
                                 accumulation.pair_rows(config.apply_kwargs))
    logging.info("gradient accumulation: %d microbatches of %d rows per step", config.grad_accum,
                 config.input.batch_size // config.grad_accum)
  if config.get("loss"):   # refused here, before the pipeline starts
    losses.check_groups(config.input.batch_size, int(config.loss.get("groups", 1)),
                        config.grad_accum, accumulation.pair_rows(config.apply_kwargs))
  host_iter, data_info = trainer.build_input(config, process_batch, config.seed, teacher)
  # Global batches, the next `device_prefetch` already on their way to the devices.
  train_iter = sharding.DevicePrefetch(host_iter, mesh, config.device_prefetch)
  total_steps, steps_per_epoch = trainer.schedule_steps(config, data_info.get("pairs_per_epoch"))
  sample_shape = data_info["image_shape"]  # (H, W) of the first training shape
  logging.info("data: %s", {k: v for k, v in data_info.items() if k != "iterator"})

  # --------------------------------------------------- model, optimizer, sharding, step
  ts = trainer.setup(config, mesh, sample_shape, total_steps, steps_per_epoch=steps_per_epoch,
                     dataset_names=tuple(data_info.get("datasets") or ()) or None,
                     teacher=teacher)
  model, tx, schedules, init_fn = ts.model, ts.tx, ts.schedules, ts.init_fn
  abstract_state, param_sh, state_sh = ts.abstract_state, ts.param_sh, ts.state_sh
  train_step, predict = ts.train_step, ts.predict
  rng = jax.random.PRNGKey(config.seed)
  logging.info("parameters per group: %s", optim.count_params(ts.abstract_params, ts.labels))
  sharding.log_shardings(param_sh, ts.abstract_params)

  # ---------------------------------------------------------------------------------- checkpoint
  manager = ckpt_lib.make_manager(workdir, config.ckpt_steps, config.keep_ckpt,
                                  config.async_checkpoint)
  with gp.timed("checkpoint"):
    state, start_step = ckpt_lib.restore_latest(manager, jax.tree.map(
        lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract_state,
        state_sh), train_iter)
  if state is None:
    start_step = 0
    # {"params"}, and "batch_stats" (BatchNorm running statistics) for a model that has them.
    variables = jax.jit(init_fn, out_shardings=ts.variables_sh)(rng)
    if config.model_init:
      host = jax.tree.map(np.asarray, variables)
      loaded, report = model_init.load_init_variables(
          config.model_init, host, getattr(model, "config", None), config.get("model"),
          flow_adaptor=config.get("model_init_flow_adaptor") or "check")
      if is_main:
        print(report.summary(), flush=True)
      variables = jax.device_put(loaded, ts.variables_sh)
    from_teacher = str(config.model_init or "").startswith("teacher:")
    if teacher is not None and is_main and not from_teacher:
      # configs/distill.py init=fresh: said in the log, as init=teacher's report says what it
      # copied (most of a synthetic student).
      n = optim.count_params(ts.abstract_params)["total"]
      scheme = getattr(getattr(model, "config", None), "param_init", None)
      start = (f"model_init {config.model_init}" if config.model_init else
               "its own initialisation" + (f" (param_init {scheme})" if scheme else ""))
      print(f"student init: {start}; 0 of its {n:,} parameters copied from the teacher",
            flush=True)
    state = ts.create_state(variables)
  else:
    print(f"resumed from step {start_step}", flush=True)

  # ---------------------------------------------------------------------------------- evals
  evaluators = train_evals.build_evaluators(config.evals, mesh, model)
  writer = trainer.Writer(workdir, is_main)

  def run_evals(step, force=False):
    for name, ev in evaluators.items():
      if force or (ev.every and step % ev.every == 0):
        with gp.timed("eval"):
          res = ev.run(predict, state.variables())
        if not res.scalars:
          continue
        rec = {"step": step, "eval": name, **res.scalars}
        if is_main:
          what = f" ({ev.describe()}, the params of step {step})" if hasattr(ev, "describe") else ""
          print(f"[eval {name}] step {step}{what}: " +
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
  gp.resumed(start_step)
  trace = profiling.StepTrace(profile, workdir / "profile", start_step)
  try:
    with loop_control.PreemptionGuard(mesh) as guard:
      keeper = loop_control.SaveAndStop(manager, guard, config.max_nonfinite_steps, start_step)
      while step < total_steps:
        trace.before_step(step + 1)
        with gp.timed("data_wait"):
          batch = next(train_iter)
        if step == start_step:   # the run's first call traces and compiles the step
          with gp.timed("compile"):
            state, metrics = train_step(state, batch)
        else:
          state, metrics = train_step(state, batch)
        step += 1
        trace.after_step(step, metrics)
        gp.step(step)
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
                 "lr": max(lrs.values(), default=None), **{f"lr_{g}": v for g, v in lrs.items()},
                 "pairs_per_s": pairs_s}
          writer.scalars("metrics.jsonl", step, rec, "train")
          logging.info("process %d metrics %s", jax.process_index(), json.dumps(rec))
          if is_main:
            ep = f" ep {rec['epoch']:.3f}" if rec["epoch"] is not None else ""
            terms = "".join(f"{k[5:]} {v:.5f} " for k, v in rec.items() if k.startswith("loss_"))
            print(f"step {step}/{total_steps}{ep} loss {rec['loss']:.5f} {terms}"
                  f"lr " + " ".join(f"{g}={v:.2e}" for g, v in lrs.items()) +
                  f" {pairs_s:.1f} pairs/s ETA {_fmt_eta(eta)}" +
                  (f" skipped {rec['skipped']}" if rec["skipped"] else ""), flush=True)
          if not m["update_ok"]:
            logging.warning("step %d: non-finite loss or gradient, update skipped (total %d)",
                            step, rec["skipped"])
          t_last, step_last = now, step
          gp.write()
        if manager.should_save(step) or step == total_steps:
          # A save step: the step itself ends here, not inside the checkpoint's time.
          jax.block_until_ready(metrics)
        t_save = time.monotonic()
        stop = keeper.end_of_step(step, state, train_iter, metrics["update_ok"],
                                  step == total_steps)
        if keeper.saved_step == step:
          gp.add("checkpoint", time.monotonic() - t_save)
          writer.scalars("goodput.jsonl", step, {"step": step, **gp.write()}, "goodput")
        if stop:
          print(keeper.message, flush=True)
          break
        run_evals(step, force=step == total_steps)
      with gp.timed("checkpoint"):
        keeper.wait()
    last_saved = manager.latest_step()
    with gp.timed("checkpoint"):
      manager.close()
  finally:
    trace.stop()
    figures = gp.close()
    if is_main:
      print(goodput.summary_line(figures), flush=True)
      writer.scalars("goodput.jsonl", step, {"step": step, **figures}, "goodput")
  writer.close()
  if is_main and step == total_steps and last_saved is not None:
    print(_next_steps(workdir, last_saved, config), flush=True)


def _next_steps(workdir: pathlib.Path, saved_step: int, config) -> str:
  """The lines a finished run ends with: its checkpoint and the commands that use it."""
  synthetic = "synthetic" in dict((config.input.get("datasets") or {}))
  bench = "" if synthetic else " --bench sintel --data_root DATA"
  return "\n".join([
      f"checkpoint: {workdir}/checkpoints/{saved_step} (step {saved_step} of {workdir})",
      f"evaluate:   python evaluate.py --checkpoint {workdir}{bench} --out {workdir}/results",
      f"infer:      python -m ufm_jax infer SOURCE.png TARGET.png --checkpoint {workdir} "
      f"--out {workdir}/infer"])


def _fmt_eta(sec):
  if not math.isfinite(sec):
    return "?"
  sec = int(sec)
  return f"{sec // 3600}h{sec % 3600 // 60:02d}m{sec % 60:02d}s"


def _usage() -> str:
  """--help: what train.py does and its flags, one line each."""
  lines = [__doc__.strip(), "", "flags:"]
  for holder in _FLAGS:
    lines.append(f"  --{holder.name}: {flags.FLAGS[holder.name].help}")
  lines += ["  --config.KEY=VALUE: override a key of the config, e.g. --config.grad_accum=2",
            "  --verbosity=0: INFO logs (default: one line per log step and warnings)",
            "  --helpfull: every absl flag"]
  return "\n".join(lines)


def _config_file_missing(argv) -> str | None:
  """The --config file named on the command line, if it does not exist (ml_collections reports
  that as a chain of tracebacks)."""
  for i, arg in enumerate(argv):
    value = None
    if arg.startswith("--config="):
      value = arg.split("=", 1)[1]
    elif arg == "--config" and i + 1 < len(argv):
      value = argv[i + 1]
    if value is not None:
      path = value.split(":", 1)[0]
      return None if pathlib.Path(path).is_file() else path
  return None


def _config_arg_error(argv) -> str | None:
  """One line for a bad `--config=FILE:key=value` argument (an unknown key, a value of the wrong
  type, a value the config refuses), which absl would report inside a traceback."""
  from ufm_jax.training import config_lib
  for i, arg in enumerate(argv):
    spec = arg.split("=", 1)[1] if arg.startswith("--config=") else (
        argv[i + 1] if arg == "--config" and i + 1 < len(argv) else None)
    if spec is not None and ":" in spec:
      try:
        config_lib.load_config(spec)
      except (config_lib.ConfigArgError, ValueError) as e:
        return f"error: --config={spec}: {' '.join(str(e).split())}"
  return None


def _run():
  if any(a in ("-h", "--help", "--helpshort", "-help") for a in sys.argv[1:]):
    print(_usage())
    sys.exit(0)
  missing = _config_file_missing(sys.argv[1:])
  if missing:
    print(f"error: --config: no such file {missing}", file=sys.stderr)
    sys.exit(2)
  bad_arg = _config_arg_error(sys.argv[1:])
  if bad_arg:
    print(bad_arg, file=sys.stderr)
    sys.exit(2)
  try:
    app.run(main)
  except AttributeError as e:
    # A mistyped --config.key=value: ml_collections' own message ("Did you mean ...") is the
    # useful part; the traceback around it is not.
    hint = re.search(r"Did you mean [^?]*\?", str(e))
    if hint is None:
      raise
    print(f"error: unknown --config key. {hint.group(0)}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
  _run()
