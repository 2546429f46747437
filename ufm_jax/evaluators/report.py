"""The Markdown table evaluate.py prints: one table per family, the paper's column order."""

from __future__ import annotations

import math

from ufm_jax import evaluators

# A model with a flow covariance (ufm_jax.evaluators.metrics.add_calibration); absent columns are dropped.
CALIBRATION_COLUMNS = ["nll", "nll_laplace", "coverage_1sigma", "coverage_2sigma",
                       "coverage_3sigma", "ause", "ause_random", "ause_pooled",
                       "ause_pooled_random"]
TABLE_COLUMNS = {  # the paper's column order per family (metric suffixes)
    "flow": ["epe_covis", "epe_all", "px1", "px3", "px5", "fl_all", "fl_bg", "fl_fg",
             "epe_matched", "epe_unmatched", "epe_s0-10", "epe_s10-40", "epe_s40+",
             "epe_d0-10", "epe_d10-60", "epe_d60-140"] + CALIBRATION_COLUMNS,
    "dense": ["epe", "epe_zero", "px1", "px2", "px5", "epe_occluded", "epe_all", "covis_acc"]
             + CALIBRATION_COLUMNS,
    "pose": ["auc5", "auc10", "auc15", "auc20", "auc30", "acc5", "acc10", "acc15", "acc20", "acc30"],
}


def markdown_table(results: dict[str, float], benches: list[str], runtime: dict[str, float]) -> str:
  lines = []
  for family in ("flow", "dense", "pose"):
    names = [b for b in benches if evaluators.BENCHES[b].family == family]
    rows = {}
    for b in names:
      for s in evaluators.BENCHES[b].splits:
        vals = {k.split("/", 1)[1]: v for k, v in results.items() if k.startswith(s.label + "/")}
        if vals:
          rows[s.label] = (vals, runtime.get(b, float("nan")))
    if not rows:
      continue
    # A metric undefined on every row (epe_occluded where nothing is occluded) gets no column.
    cols = [c for c in TABLE_COLUMNS[family]
            if any(_defined(v.get(c)) for v, _ in rows.values())]
    lines.append("| split | " + " | ".join(cols) + " | ms/pair |")
    lines.append("|---" * (len(cols) + 2) + "|")
    for label, (vals, ms) in rows.items():
      cells = [_fmt(vals.get(c)) for c in cols]
      lines.append(f"| {label} | " + " | ".join(cells) + f" | {_fmt(ms, 1)} |")
    lines.append("")
  return "\n".join(lines)


def _defined(v) -> bool:
  return v is not None and not (isinstance(v, float) and math.isnan(v))


def _fmt(v, digits=2):
  if v is None:
    return "-"
  return "nan" if isinstance(v, float) and math.isnan(v) else f"{v:.{digits}f}"
