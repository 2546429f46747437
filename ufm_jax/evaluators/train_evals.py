"""Evaluators that train.py runs on the current params, chosen by `type` in `config.evals`:

  heldout  fixed held-out pairs of a registered source, predicted by the sharded training-mesh
           forward; the dense metrics (`DenseMetrics` with baselines: epe, px1/2/5 as the
           paper's dense tables and evaluate.py, epe_occluded where the pairs have occluded
           pixels, epe_all, epe_zero, covis_acc; with a flow covariance its calibration)
  bench    a benchmark of ufm_jax.evaluators (evaluate.py's benches) through ufm_jax.predict
  teacher_agreement  held-out unlabeled pairs scored against a distillation teacher's
           predictions (the heldout metrics with the teacher's flow and covisibility as labels)
  "module:Class"  anything else, called with (cfg, mesh)
"""

from __future__ import annotations

import importlib

import numpy as np
from absl import logging

from ufm_jax.evaluators.dense import DenseMetrics
from ufm_jax.evaluators.pose import NoCovisibilityError


class EvalResult:
  def __init__(self, scalars, images=None):
    self.scalars, self.images = scalars, images or {}


class HeldoutEval:
  """EPE and covisibility accuracy on fixed held-out pairs of a registered source.

  Pixels as evaluate.py's dense benches (`DenseMetrics`): epe / px1,2,5 (% of pixels with
  EPE > t) pool the covisible pixels with valid flow and covisibility labels (where UFM is
  supervised); epe_all pools every pixel with valid flow; epe_zero is the zero-flow EPE on the
  `epe` pixels.

  Config: source, root, kwargs (source options), num_pairs, shape (H, W: centre crop, which keeps
  flow labels valid), batch_size, every, num_images (flow/covis pictures to TensorBoard).
  """

  KEYS = ("image0", "image1", "flow", "covisibility", "flow_valid", "covis_valid")

  def __init__(self, cfg, mesh):
    from ufm_jax.training import sharding
    from ufm_jax.data import get_source
    self.every = int(cfg.get("every", 0))
    self.mesh = mesh
    src = get_source(cfg.source, cfg.get("root"), **dict(cfg.get("kwargs", {})))
    self.samples = self.load_samples(cfg, src)
    div = sharding.batch_divisor(mesh)
    bs = int(cfg.get("batch_size", div))
    self.batch_size = -(-bs // div) * div
    self.num_images = int(cfg.get("num_images", 2))
    split = dict(cfg.get("kwargs", {})).get("split")
    self.what = f"{cfg.source}{f' {split} split' if split else ''}, {len(self.samples)} pairs"

  def describe(self) -> str:
    """What it scores, for the console line: e.g. "synthetic val split, 32 pairs"."""
    return self.what

  def load_samples(self, cfg, src) -> list:
    """The first num_pairs samples of `src`, centre-cropped to cfg.shape."""
    samples = []
    for i in range(min(int(cfg.num_pairs), len(src))):
      s = src[i]
      samples.append({k: np.asarray(v) for k, v in zip(
          self.KEYS, _centre_crop([s[k] for k in self.KEYS], cfg.shape, f"{cfg.source}[{i}]"))})
    return samples

  def run(self, predict, params) -> EvalResult:
    import jax
    from ufm_jax.runtime import viz
    from ufm_jax.training import sharding
    n, bs = len(self.samples), self.batch_size
    P, pid = jax.process_count(), jax.process_index()
    acc = DenseMetrics(thresholds=(1, 2, 5), baselines=True)
    images = {}
    for start in range(0, n, bs):
      chunk = self.samples[start:start + bs]
      real = len(chunk)
      chunk = chunk + [chunk[-1]] * (bs - real)  # pad to a fixed shape; padded rows are ignored
      batch = {k: np.stack([c[k] for c in chunk]) for k in chunk[0]}
      per = bs // P
      local = {k: v[pid * per:(pid + 1) * per] for k, v in batch.items()}
      out = jax.device_get(predict(params, sharding.make_global_batch(local, self.mesh)))
      for j in range(real):
        # No covisibility from a model without an uncertainty head: DenseMetrics then skips
        # covis_acc (and says so once), the panel greys nothing out.
        pred = {"flow": np.asarray(out["flow"][j], np.float32),
                **{k: np.asarray(out[k][j]) for k in ("covisibility", "flow_covariance")
                   if k in out}}
        acc(chunk[j], pred)
        i = start + j
        if i < self.num_images:
          images[f"pair{i}"] = viz.panel(chunk[j]["image0"], chunk[j]["image1"], pred["flow"],
                                         pred.get("covisibility"),
                                         covariance=pred.get("flow_covariance"))
          images[f"pair{i}_gt"] = viz.panel(chunk[j]["image0"], chunk[j]["image1"],
                                            chunk[j]["flow"], chunk[j]["covisibility"])
    # A metric with no pixels to pool (epe_occluded on pairs without occlusions) is left out.
    scalars = {k: v for k, v in acc.result().items() if not (isinstance(v, float) and np.isnan(v))}
    return EvalResult({**scalars, "num_pairs": float(n)}, images)


def _centre_crop(arrays, shape, where: str) -> list:
  """The (H, W) centre of each array (centre crops keep flow labels valid)."""
  h, w = shape
  H, W = np.shape(arrays[0])[:2]
  if H < h or W < w:
    raise ValueError(f"eval source {where}: the sample is {H}x{W}, smaller than the eval shape "
                     f"{h}x{w}")
  y0, x0 = (H - h) // 2, (W - w) // 2
  return [np.asarray(a)[y0:y0 + h, x0:x0 + w] for a in arrays]


class TeacherAgreementEval(HeldoutEval):
  """The student against its teacher on held-out unlabeled pairs (a distillation run's own
  domain, configs/distill.py `eval_root=`): the teacher predicts each centre-cropped pair once,
  at the start (`ufm_jax.predict` at its inference resolution), and its flow and covisibility
  (probability >= 0.5) serve as the labels of HeldoutEval's metrics: epe is the student's EPE
  against the teacher on the teacher's covisible pixels, covis_acc their covisibility
  agreement, epe_zero the teacher's mean motion. No ground truth is read.

  Config: as heldout (source, root, kwargs, num_pairs, shape, batch_size, every, num_images),
  plus teacher (the run's config.teacher block).
  """

  def load_samples(self, cfg, src) -> list:
    from ufm_jax.runtime import inference
    from ufm_jax.training import teacher as teacher_lib
    from ufm_jax.data import distill_rows
    from ufm_jax.models import ufm
    model, variables, _, _ = teacher_lib.load_spec(dict(cfg.teacher))
    variables = ufm.variables(variables() if callable(variables) else variables)
    samples = []
    for i in range(min(int(cfg.num_pairs), len(src))):
      where = f"{cfg.source}[{i}]"
      image0, image1 = _centre_crop(distill_rows.read_images(src, i, where), cfg.shape, where)
      pred = inference.predict(model, variables, image0, image1)
      ones = np.ones(image0.shape[:2], bool)
      covis = (pred["covisibility"] >= 0.5 if "covisibility" in pred else ones)
      samples.append({"image0": image0, "image1": image1, "flow": pred["flow"],
                      "covisibility": covis, "flow_valid": ones,
                      "covis_valid": ones if "covisibility" in pred else ~ones})
    return samples


class BenchEval:
  """A benchmark of ufm_jax.evaluators (evaluate.py's benches) run on the current params.

  Config: bench (e.g. sintel), every, max_pairs, resolution (560 | 980 | native), data_root,
  protocol (default "native"; "official" needs no resolution: docs/benchmarks.md).
  Benches whose data is absent, and pose benches of a model without covisibility, are skipped
  with a warning (once).
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
                                        max_pairs=self.cfg.get("max_pairs"), progress=False,
                                        protocol=self.cfg.get("protocol", "native"))
    except (evaluators.MissingDataError, NoCovisibilityError) as e:
      logging.warning("eval %s skipped from now on: %s", self.cfg.bench, e)
      self.missing = True
      return EvalResult({})
    return EvalResult({k.replace("/", "_"): float(v) for k, v in metrics.items()
                       if isinstance(v, (int, float))})


def build_evaluators(evals_cfg, mesh, model):
  """name -> evaluator, by each entry's `type` (see the module docstring)."""
  out = {}
  for name, cfg in dict(evals_cfg).items():
    kind = cfg.get("type", "heldout")
    if kind == "heldout":
      out[name] = HeldoutEval(cfg, mesh)
    elif kind == "bench":
      out[name] = BenchEval(cfg, model)
    elif kind == "teacher_agreement":
      out[name] = TeacherAgreementEval(cfg, mesh)
    else:
      module, attr = kind.split(":")
      out[name] = getattr(importlib.import_module(module), attr)(cfg, mesh)
  return out
