"""The files `python -m ufm_jax infer` writes for one prediction: one suffix table, one writer,
shared by the single pair (`infer SOURCE TARGET`) and the many-pair runs (`ufm_jax.tools.sequence`).

  <name>.flo                Middlebury flow at the source image's size (always)
  <name>_flow.npy           the same flow, [H, W, 2] float32                     (--save npy)
  <name>_covisibility.npy   covisibility probability, [H, W] float32             (--save npy)
  <name>_flow_covariance.npy  flow covariance, [H, W, 3] float32 = (var_x, var_y, cov_xy) in px^2
                            of the source image (models with a flow_cov head)    (--save npy)
  <name>_covisibility.png   covisibility as 8-bit grey (255 = covisible)         (--save covis)
  <name>_panel.png          source | target | flow colours | warped target, and with a flow
                            covariance | its uncertainty over a legend           (--save panel)

A model without a covisibility output (`UFMConfig.has_covisibility`) predicts no covisibility:
its covisibility files are not written (`written`) and its panel greys nothing out; a model
without a flow covariance writes no covariance file and no uncertainty tile.
"""

from __future__ import annotations

import pathlib

import numpy as np

# File kind -> name suffix, in the order they are written (.flo last: its presence marks a pair
# done when a many-pair run resumes).
SUFFIXES = {"npy": "_flow.npy", "cnpy": "_covisibility.npy",
            "vnpy": "_flow_covariance.npy", "cpng": "_covisibility.png", "panel": "_panel.png",
            "flo": ".flo"}
# --save choice -> the kinds it adds to the .flo.
SAVE_CHOICES = {"npy": ("npy", "cnpy", "vnpy"), "covis": ("cpng",), "panel": ("panel",)}
# Kinds written only when the prediction has that output.
OPTIONAL_KINDS = {"cnpy": "covisibility", "cpng": "covisibility", "vnpy": "flow_covariance"}


def paths(out_dir, name: str, save=tuple(SAVE_CHOICES)) -> dict[str, pathlib.Path]:
  """{kind: path} of the files of prediction `name`: the .flo plus the `save` choices."""
  bad = sorted(set(save) - set(SAVE_CHOICES))
  if bad:
    raise ValueError(f"--save {','.join(bad)}: expected a comma list of {','.join(SAVE_CHOICES)}")
  kinds = {"flo"}.union(*(SAVE_CHOICES[s] for s in save))
  return {k: pathlib.Path(out_dir) / f"{name}{suffix}" for k, suffix in SUFFIXES.items()
          if k in kinds}


def written(files: dict[str, pathlib.Path], pred) -> dict[str, pathlib.Path]:
  """The files of `files` that `write` writes for `pred`: all, but the covisibility ones only
  when the prediction has covisibility, the covariance one only when it has a covariance."""
  return {k: p for k, p in files.items()
          if k not in OPTIONAL_KINDS or pred.get(OPTIONAL_KINDS[k]) is not None}


def predicted(model) -> dict:
  """Which optional outputs `model`'s predictions have, as a stand-in prediction for `written`
  (a model without a config, e.g. a test stand-in: covisibility, no covariance)."""
  cfg = getattr(model, "config", None)
  covis = cfg is None or bool(getattr(cfg, "has_covisibility", True))
  cov = getattr(cfg, "flow_covariance", None) is not None
  return {"flow": True, **({"covisibility": True} if covis else {}),
          **({"flow_covariance": True} if cov else {})}


def write(files: dict[str, pathlib.Path], source, target, pred) -> list[pathlib.Path]:
  """Writes `written(files, pred)` ({kind: path} from `paths`) of one prediction, each
  atomically; returns their paths. `pred`: {"flow": [H, W, 2], "covisibility": [H, W]
  (absent for a model without an uncertainty head), "flow_covariance": [H, W, 3] (only from a
  model with a flow covariance)} at the source image's size."""
  from ufm_jax.runtime import viz
  from ufm_jax.data import io
  files = written(files, pred)
  flow = np.asarray(pred["flow"], np.float32)
  covis = pred.get("covisibility")
  covis = None if covis is None else np.asarray(covis, np.float32)
  cov = pred.get("flow_covariance")
  cov = None if cov is None else np.asarray(cov, np.float32)
  writers = {
      "npy": lambda p: io.write_npy(p, flow),
      "cnpy": lambda p: io.write_npy(p, covis),
      "vnpy": lambda p: io.write_npy(p, cov),
      "cpng": lambda p: io.write_image(p, viz.covisibility_to_image(covis)),
      "panel": lambda p: io.write_image(p, viz.panel(source, target, flow, covis,
                                                     covariance=cov)),
      "flo": lambda p: io.write_flo(p, flow),
  }
  for kind in SUFFIXES:  # the table's order: .flo last
    if kind in files:
      writers[kind](files[kind])
  return list(files.values())
