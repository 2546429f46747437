"""Command line: `python -m ufm_jax infer|convert|to-official ...` (also installed as `ufm-jax`).

  python -m ufm_jax infer SOURCE TARGET --checkpoint DIR --out DIR [--snapshot] [--bidirectional]
      Writes, per direction (`forward`: SOURCE -> TARGET, `backward` with --bidirectional):
        <dir>.flo                Middlebury flow at the source image's size
        <dir>_flow.npy           the same flow, [H, W, 2] float32
        <dir>_covisibility.npy   covisibility probability, [H, W] float32
        <dir>_covisibility.png   covisibility as 8-bit grey (255 = covisible)
        <dir>_panel.png          source | target | flow colours | target warped into the source
  python -m ufm_jax convert SNAPSHOT_DIR OUT_DIR ...
      Converts an official Hugging Face snapshot (see `ufm_jax.convert`).
  python -m ufm_jax to-official CHECKPOINT OUT_DIR [--step N]
      The inverse: a converted checkpoint or a train.py workdir (newest step, or step N) -> an
      official snapshot (config.json, model.safetensors, README.md; `ufm_jax.save_official`).

`--checkpoint` takes a converted checkpoint (`python -m ufm_jax convert`), a train.py workdir
(latest step) or, with `--snapshot` (or when the folder holds config.json + model.safetensors),
an official snapshot.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys

import numpy as np


def is_snapshot(path: str | os.PathLike) -> bool:
  """A Hugging Face snapshot folder as written by `save_pretrained`."""
  p = pathlib.Path(path)
  return (p / "config.json").is_file() and (p / "model.safetensors").is_file()


def model_from_name(name: str, **overrides):
  """A model (no params) from a variant name of configs/models.py, with UFMConfig overrides
  (e.g. dtype="bfloat16"); `ufm_jax.models.build_model` is used when it exists."""
  try:
    from ufm_jax.models import build_model
  except ImportError:
    build_model = None
  if build_model is not None:
    return build_model(name, **overrides)
  try:
    from configs import models
  except ImportError:  # configs/ sits beside the package in a source checkout, not installed
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from configs import models
  from ufm_jax.models import ufm
  fn = getattr(models, name, None)
  if not callable(fn):
    raise ValueError(f"unknown model config {name!r} in configs/models.py")
  return ufm.model_from_config(fn(**overrides))


def is_workdir(path: str | os.PathLike) -> bool:
  """A train.py workdir: its config.json plus orbax steps under checkpoints/."""
  p = pathlib.Path(path)
  return (p / "config.json").is_file() and (p / "checkpoints").is_dir()


def load_workdir(path: str | os.PathLike, step: int | None = None):
  """(model, params) of the latest (or given) checkpoint step of a train.py workdir."""
  import importlib
  import json

  from ufm_jax import checkpoint

  p = pathlib.Path(path)
  cfg = json.loads((p / "config.json").read_text())
  model_kw = dict(cfg.get("model") or {})
  if cfg.get("model_fn"):
    import ml_collections
    module, attr = cfg["model_fn"].split(":")
    model = getattr(importlib.import_module(module), attr)(ml_collections.ConfigDict(model_kw))
  else:
    if not cfg.get("model_name"):
      raise ValueError(f"{p / 'config.json'}: neither model_fn nor model_name; cannot rebuild the model")
    model = model_from_name(cfg["model_name"], **model_kw)
  state, _ = checkpoint.read_state_numpy(p, step)
  return model, state["params"]


def load_model(path: str | os.PathLike, snapshot: bool = False):
  """(model, params) from an official snapshot, a train.py workdir or a converted checkpoint."""
  p = pathlib.Path(path)
  if not p.is_dir():
    raise FileNotFoundError(f"checkpoint directory not found: {p}")
  import ufm_jax
  if snapshot or is_snapshot(p):
    if not is_snapshot(p):
      raise FileNotFoundError(f"{p} is not a Hugging Face snapshot: expected config.json and "
                              "model.safetensors in it")
    return ufm_jax.load_official(p)
  if is_workdir(p):
    return load_workdir(p)
  return ufm_jax.load(p)


def _to_official_main(args) -> int:
  import ufm_jax
  from ufm_jax import checkpoint

  p = pathlib.Path(args.checkpoint)
  if pathlib.Path(args.out_dir).exists():  # before loading: the export never overwrites
    raise FileExistsError(f"{args.out_dir} already exists; refusing to overwrite it")
  step = None
  if is_workdir(p):
    model, params = load_workdir(p, args.step)
    step = args.step if args.step is not None else checkpoint.checkpoint_steps(p)[-1]
  elif args.step is not None:
    raise ValueError(f"--step {args.step}: {p} is not a train.py workdir (config.json + "
                     "checkpoints/)")
  else:
    model, params = load_model(p)
  notes = ufm_jax.save_official(model, params, args.out_dir, source=str(p.absolute()), step=step)
  print(f"wrote {args.out_dir} ({type(model).__name__}" + (f", step {step})" if step is not None else ")"))
  for n in notes:
    print(f"  {n}")
  return 0


def write_direction(out_dir: pathlib.Path, name: str, source, target, pred) -> list[pathlib.Path]:
  """Writes the files of one direction (atomically); returns their paths."""
  from ufm_jax import viz
  from ufm_jax.data.io import write_flo

  flow = np.asarray(pred["flow"], np.float32)
  covis = np.asarray(pred["covisibility"], np.float32)
  paths = {k: out_dir / f"{name}{suffix}" for k, suffix in (
      ("flo", ".flo"), ("npy", "_flow.npy"), ("cnpy", "_covisibility.npy"),
      ("cpng", "_covisibility.png"), ("panel", "_panel.png"))}
  write_flo(paths["flo"], flow)
  _save_npy(paths["npy"], flow)
  _save_npy(paths["cnpy"], covis)
  viz.write_png(paths["cpng"], viz.covisibility_to_image(covis))
  viz.write_png(paths["panel"], viz.panel(source, target, flow, covis))
  return list(paths.values())


def _save_npy(path: pathlib.Path, array: np.ndarray) -> None:
  tmp = path.with_name(path.name + f".tmp{os.getpid()}")
  with open(tmp, "wb") as f:
    np.save(f, array)
  os.replace(tmp, path)


def run_infer(model, params, source_path, target_path, out_dir, bidirectional=False):
  """Reads the two images, predicts, writes the outputs; returns the written paths."""
  from ufm_jax import inference, viz

  source, target = viz.read_image(source_path), viz.read_image(target_path)
  out_dir = pathlib.Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  if bidirectional:
    fwd, bwd = inference.predict(model, params, [source, target], [target, source])
  else:
    fwd, bwd = inference.predict(model, params, source, target), None
  written = write_direction(out_dir, "forward", source, target, fwd)
  if bwd is not None:
    written += write_direction(out_dir, "backward", target, source, bwd)
  return written


def _infer_main(args) -> int:
  for p in (args.source, args.target):
    if not os.path.isfile(p):
      raise FileNotFoundError(f"image not found: {p}")
  model, params = load_model(args.checkpoint, snapshot=args.snapshot)
  written = run_infer(model, params, args.source, args.target, args.out, args.bidirectional)
  for p in written:
    print(p)
  return 0


def main(argv: list[str] | None = None) -> int:
  argv = list(sys.argv[1:] if argv is None else argv)
  parser = argparse.ArgumentParser(prog="python -m ufm_jax", description=__doc__.split("\n")[0])
  sub = parser.add_subparsers(dest="command", required=True)
  p = sub.add_parser("infer", help="flow + covisibility for one image pair")
  p.add_argument("source", help="source image (flow is defined on its pixels)")
  p.add_argument("target", help="target image")
  p.add_argument("--checkpoint", required=True, help="converted checkpoint or HF snapshot folder")
  p.add_argument("--out", required=True, help="output folder (created)")
  p.add_argument("--snapshot", action="store_true",
                 help="--checkpoint is an official Hugging Face snapshot (config.json + safetensors)")
  p.add_argument("--bidirectional", action="store_true", help="also write target -> source")
  sub.add_parser("convert", help="official HF snapshot -> orbax checkpoint (ufm_jax.convert)",
                 add_help=False)
  p = sub.add_parser("to-official", help="checkpoint or train.py workdir -> official HF snapshot")
  p.add_argument("checkpoint", help="converted checkpoint or train.py workdir")
  p.add_argument("out_dir", help="new folder for config.json, model.safetensors, README.md")
  p.add_argument("--step", type=int, help="workdir checkpoint step (default: the newest)")
  if argv and argv[0] == "convert":
    from ufm_jax import convert
    return convert.main(argv[1:]) or 0
  args = parser.parse_args(argv)
  try:
    return _to_official_main(args) if args.command == "to-official" else _infer_main(args)
  except (FileNotFoundError, FileExistsError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2


if __name__ == "__main__":
  sys.exit(main())
