"""What a covariance run's errors look like on the synthetic bench, and what its sparsification
could reach: on the held-out pairs `evaluate.py` scores (the workdir's task, test split, covisible
pixels), prints

  * how much of the squared flow residual is a per-image constant (an offset of the whole
    image's flow, which no per-pixel order within the image can rank),
  * the rank correlation of the predicted uncertainty (trace of Sigma) with the EPE, pooled and
    within images,
  * AUSE (pooled over the bench, and per image as Ilg et al.) for the model's order and for
    other orders: the model's trace averaged per image (its image-level part alone), the true
    shift's length, the distance to the image border, and the image-level oracle (each image's
    true mean EPE: the best any order that ranks images and not pixels can do); sigma_max and
    the determinant, other orders of the same covariance.

Orders other than the trace are diagnostics only; `evaluate.py` reports the trace's.

  python benchmarks/covariance_errors.py --checkpoint workdirs/synthetic_cov
"""

import argparse
import json
import pathlib

import numpy as np

from ufm_jax import evaluators
from ufm_jax.evaluators import metrics
from ufm_jax.runtime import model_io
from ufm_jax.models import covariance


def sparsification_area(epe, key, mask, per_image: bool) -> float:
  groups = [(e[m], k[m]) for e, k, m in zip(epe, key, mask)] if per_image else [
      (epe[mask], key[mask])]
  out = []
  for e, k in groups:
    oracle = metrics.Sparsification.curve(e, e)
    out.append(np.trapezoid(metrics.Sparsification.curve(e, k) - oracle,
                            metrics.Sparsification.FRACTIONS))
  return float(np.mean(out))


def rank_corr(a, b) -> float:
  return float(np.corrcoef(np.argsort(np.argsort(a)), np.argsort(np.argsort(b)))[0, 1])


def main():
  ap = argparse.ArgumentParser(description=__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--checkpoint", required=True, help="a train.py workdir of a synthetic run")
  args = ap.parse_args()
  cfg = json.loads((pathlib.Path(args.checkpoint) / "config.json").read_text())
  opts = cfg["input"]["datasets"]["synthetic"]["options"]
  task = {k: tuple(v) if isinstance(v, list) else v for k, v in opts.items()
          if k in ("pair_type", "size", "max_shift")}
  bench = evaluators.get_bench("synthetic", "native")
  source = evaluators.open_source(bench, bench.splits[0], None, **task)
  model, variables = model_io.load_workdir(args.checkpoint)
  runner = evaluators.Runner(model, variables, "native")
  epe, covs, mask, resid, gt = [], [], [], [], []
  for i in range(len(source)):
    s = source[i]
    pred = runner(s["image0"], s["image1"])
    if pred.get("flow_covariance") is None:
      raise SystemExit(f"{args.checkpoint}: the model predicts no flow covariance")
    cov = np.asarray(pred["flow_covariance"], np.float64)
    epe.append(metrics.endpoint_error(pred["flow"], s["flow"]))
    covs.append(cov)
    mask.append(np.asarray(s["flow_valid"], bool) & np.asarray(s["covisibility"], bool)
                & np.asarray(s["covis_valid"], bool))
    resid.append(np.asarray(pred["flow"], np.float64) - s["flow"])
    gt.append(np.asarray(s["flow"], np.float64))
  epe, covs, mask, resid, gt = map(np.stack, (epe, covs, mask, resid, gt))
  trace = covs[..., 0] + covs[..., 1]
  n, h, w = epe.shape
  per_image = [r[m] for r, m in zip(resid, mask)]
  total = sum(float((r ** 2).sum()) for r in per_image)
  within = sum(float(((r - r.mean(0)) ** 2).sum()) for r in per_image)
  print(f"{args.checkpoint}: {n} held-out pairs ({task}), {int(mask.sum())} covisible pixels, "
        f"mean EPE {epe[mask].mean():.3f} px")
  print(f"  squared residual that is a per-image constant: {100 * (1 - within / total):.1f}%")
  shift = np.array([np.linalg.norm(g[m], axis=-1).mean() for g, m in zip(gt, mask)])
  mean_epe = np.array([e[m].mean() for e, m in zip(epe, mask)])
  bins = [(lo, lo + 3) for lo in range(0, int(shift.max()) + 1, 3)]
  print("  mean EPE by shift length: " + ", ".join(
      f"{lo}-{hi} px {mean_epe[(shift >= lo) & (shift < hi)].mean():.2f} "
      f"({int(((shift >= lo) & (shift < hi)).sum())} pairs)"
      for lo, hi in bins if ((shift >= lo) & (shift < hi)).any()))
  print(f"  rank correlation of trace and EPE: pooled {rank_corr(trace[mask], epe[mask]):.3f}, "
        f"within images (mean) "
        f"{np.mean([rank_corr(t[m], e[m]) for t, e, m in zip(trace, epe, mask)]):.3f}")
  image = lambda v: np.broadcast_to(np.asarray(v)[:, None, None], epe.shape)  # noqa: E731
  yy, xx = np.mgrid[:h, :w]
  border = np.minimum(np.minimum(yy, h - 1 - yy), np.minimum(xx, w - 1 - xx))
  orders = {
      "trace of Sigma (the model's)": trace,
      "sigma_max of Sigma": covariance.sigma_max(covs),
      "determinant of Sigma": covariance.determinant(covs),
      "image mean of the trace": image([t[m].mean() for t, m in zip(trace, mask)]),
      "true shift length": np.linalg.norm(gt, axis=-1),
      "closeness to the border": -np.broadcast_to(border, epe.shape).astype(float),
      "image-level oracle": image([e[m].mean() for e, m in zip(epe, mask)]),
      "random (expected)": None,
  }
  print(f"  {'order':32s} {'ause pooled':>12s} {'ause per image':>15s}")
  for name, key in orders.items():
    if key is None:
      pooled = float(np.trapezoid(epe[mask].mean() - metrics.Sparsification.curve(
          epe[mask], epe[mask]), metrics.Sparsification.FRACTIONS))
      per = float(np.mean([np.trapezoid(e[m].mean() - metrics.Sparsification.curve(e[m], e[m]),
                                        metrics.Sparsification.FRACTIONS)
                           for e, m in zip(epe, mask)]))
    else:
      pooled = sparsification_area(epe, key, mask, False)
      per = sparsification_area(epe, key, mask, True)
    print(f"  {name:32s} {pooled:12.3f} {per:15.3f}")


if __name__ == "__main__":
  main()
