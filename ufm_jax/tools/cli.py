"""Command line: `python -m ufm_jax infer|export|match|demo|convert|to-official ...` (also installed
as `ufm-jax`).

  python -m ufm_jax infer SOURCE TARGET --checkpoint DIR --out DIR [--snapshot] [--bidirectional]
      Writes, per direction (`forward`: SOURCE -> TARGET, `backward` with --bidirectional):
        <dir>.flo                Middlebury flow at the source image's size
        <dir>_flow.npy           the same flow, [H, W, 2] float32
        <dir>_covisibility.npy   covisibility probability, [H, W] float32
        <dir>_covisibility.png   covisibility as 8-bit grey (255 = covisible)
        <dir>_flow_covariance.npy  flow covariance (var_x, var_y, cov_xy) px^2, [H, W, 3] float32
                                 (a model with a flow covariance head)
        <dir>_panel.png          source | target | flow colours | target warped into the source
                                 (| uncertainty, sigma_max in px over a legend, with a covariance)
  python -m ufm_jax infer (--frames DIR [--stride k] | --pairs LIST.txt | VIDEO.mp4) --checkpoint DIR
      --out DIR [--batch N] [--save npy,covis,panel] [--overwrite]   (see `ufm_jax.tools.sequence`)
  python -m ufm_jax export --checkpoint DIR --size HxW --out PATH [--batch N|dynamic]
      [--dtype float32|bfloat16] [--format stablehlo|onnx] [--outputs flow,covisibility]
      A deployable artifact of the forward pass plus PATH.json (see `ufm_jax.tools.export`).
  python -m ufm_jax match SOURCE TARGET --checkpoint DIR --out matches.npz [--draw m.png]
      [--num 5000] [--min-covisibility 0.5] [--bidirectional] [--max-sigma PX]
      (see `ufm_jax.tools.matching`; a flow covariance model adds each match's covariance and
      precision and ranks the matches, most certain first)
  python -m ufm_jax demo --checkpoint DIR [--port 7860] [--host 127.0.0.1] [--max-side 2048] [--share]
      A local Gradio page: flow, covisibility, warp and matches (see `ufm_jax.tools.demo`; [demo] extra).
  python -m ufm_jax convert SNAPSHOT_DIR OUT_DIR ...
      Converts an official Hugging Face snapshot into our checkpoint (see `ufm_jax.runtime.model_io`).
  python -m ufm_jax to-official CHECKPOINT OUT_DIR [--step N]
      The inverse: a converted checkpoint or a train.py workdir (newest step, or step N) -> an
      official snapshot (config.json, model.safetensors, README.md; `ufm_jax.save_official`).

`--checkpoint` takes a converted checkpoint (`python -m ufm_jax convert`), a train.py workdir
(latest step) or, with `--snapshot` (or when the folder holds config.json + model.safetensors),
an official snapshot: a folder or a Hugging Face model ID such as infinity1096/UFM-Base (the
standard Hugging Face cache; HF_HUB_OFFLINE=1 reads only the cache; `--revision` picks a
branch, tag or commit).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys

import numpy as np

from ufm_jax.runtime import compile_cache, model_io
from ufm_jax.runtime.model_io import load_model


def _to_official_main(args) -> int:
  import ufm_jax
  from ufm_jax.runtime import checkpoint

  p = pathlib.Path(args.checkpoint)
  if pathlib.Path(args.out_dir).exists():  # before loading: the export never overwrites
    raise FileExistsError(f"{args.out_dir} already exists; refusing to overwrite it")
  model, variables = load_model(p, step=args.step)
  step = None
  if model_io.what_is(p) == model_io.WORKDIR:
    step = args.step if args.step is not None else checkpoint.checkpoint_steps(p)[-1]
  notes = ufm_jax.save_official(model, variables, args.out_dir, source=str(p.absolute()),
                                step=step)
  print(f"wrote {args.out_dir} ({type(model).__name__}" + (f", step {step})" if step is not None else ")"))
  for n in notes:
    print(f"  {n}")
  return 0


def run_infer(model, variables, source_path, target_path, out_dir, bidirectional=False):
  """Reads the two images, predicts, writes every output of `ufm_jax.runtime.outputs`; returns their
  paths."""
  from ufm_jax.runtime import inference, outputs
  from ufm_jax.data import io

  source, target = io.read_image(source_path), io.read_image(target_path)
  out_dir = pathlib.Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  if bidirectional:
    fwd, bwd = inference.predict(model, variables, [source, target], [target, source])
  else:
    fwd, bwd = inference.predict(model, variables, source, target), None
  written = outputs.write(outputs.paths(out_dir, "forward"), source, target, fwd)
  if bwd is not None:
    written += outputs.write(outputs.paths(out_dir, "backward"), target, source, bwd)
  return written


def _infer_many(args) -> int:
  from ufm_jax.tools import sequence
  save = [k for k in args.save.split(",") if k]
  bad = sorted(set(save) - set(sequence.SAVE_CHOICES))
  if bad:
    raise ValueError(f"--save {','.join(bad)}: expected a comma list of {','.join(sequence.SAVE_CHOICES)}")
  if args.stride < 1 or args.batch < 1:
    raise ValueError("--stride and --batch must be >= 1")
  if args.frames:
    if not os.path.isdir(args.frames):
      raise FileNotFoundError(f"--frames folder not found: {args.frames}")
    from ufm_jax.data.sources import frames
    pairs = frames.frame_pairs(args.frames, args.stride)
  elif args.pairs:
    if not os.path.isfile(args.pairs):
      raise FileNotFoundError(f"--pairs list not found: {args.pairs}")
    pairs = sequence.list_pairs(args.pairs)
  else:
    pairs = sequence.video_frames(args.source, args.stride)
  model, variables = load_model(args.checkpoint, snapshot=args.snapshot, revision=args.revision)
  counts = sequence.run(model, variables, pairs, args.out, batch=args.batch, save=save,
                        overwrite=args.overwrite)
  print(f"{args.out}: {counts['done']} pairs written, {counts['skipped']} already there, "
        f"{counts['failed']} failed (see manifest.jsonl); "
        f"{counts['done'] / max(counts['seconds'], 1e-9):.2f} pairs/s end to end")
  return 0


def _infer_main(args) -> int:
  from ufm_jax.tools import sequence
  if args.frames or args.pairs or (args.source and args.target is None and
                                   pathlib.Path(args.source).suffix.lower() in sequence.VIDEO_SUFFIXES):
    return _infer_many(args)
  if not args.source or not args.target:
    raise ValueError("infer needs SOURCE and TARGET images, a video file, --frames DIR or --pairs LIST")
  for p in (args.source, args.target):
    if not os.path.isfile(p):
      raise FileNotFoundError(f"image not found: {p}")
  model, variables = load_model(args.checkpoint, snapshot=args.snapshot, revision=args.revision)
  written = run_infer(model, variables, args.source, args.target, args.out, args.bidirectional)
  for p in written:
    print(p)
  return 0


def _size_arg(text: str) -> tuple[int, int]:
  from ufm_jax.data.synthetic import parse_size
  try:
    return parse_size(text)
  except ValueError as e:
    raise argparse.ArgumentTypeError(str(e)) from None


def _batch_arg(text: str):
  if text == "dynamic":
    return text
  if not text.isdigit() or int(text) < 1:
    raise argparse.ArgumentTypeError(f"--batch must be a positive integer or 'dynamic', got {text!r}")
  return int(text)


def _add_checkpoint_args(p) -> None:
  p.add_argument("--checkpoint", required=True,
                 help="converted checkpoint, train.py workdir or HF snapshot folder; with "
                      "--snapshot also a Hugging Face model ID (infinity1096/UFM-Base)")
  p.add_argument("--snapshot", action="store_true",
                 help="--checkpoint is an official Hugging Face snapshot (config.json + safetensors): "
                      "a folder or a model ID, read through the Hugging Face cache")
  p.add_argument("--revision", default=None,
                 help="with a model ID: the Hub branch, tag or commit (default: main)")


def _add_infer_parser(sub) -> None:
  p = sub.add_parser("infer", help="flow + covisibility for one image pair")
  p.add_argument("source", nargs="?", help="source image (flow is defined on its pixels), or a "
                 "video file (consecutive frames)")
  p.add_argument("target", nargs="?", help="target image")
  _add_checkpoint_args(p)
  p.add_argument("--out", required=True, help="output folder (created)")
  p.add_argument("--bidirectional", action="store_true", help="also write target -> source")
  g = p.add_argument_group("many pairs (see ufm_jax.tools.sequence)")
  g.add_argument("--frames", help="folder of frames: consecutive pairs in natural sort order")
  g.add_argument("--pairs", help="text file, two image paths per line (relative to the file)")
  g.add_argument("--stride", type=int, default=1, help="frame i is paired with frame i + stride")
  g.add_argument("--batch", type=int, default=1, help="pairs per forward (last batch padded)")
  g.add_argument("--save", default="", help="extra outputs besides .flo: comma list of npy,covis,panel")
  g.add_argument("--overwrite", action="store_true", help="redo pairs whose outputs exist")
  p.set_defaults(func=_infer_main)


def _add_export_parser(sub) -> None:
  from ufm_jax.tools import export
  p = sub.add_parser("export", help="StableHLO (jax.export) or ONNX artifact of the forward pass",
                     description=export.__doc__.split("\n")[0])
  _add_checkpoint_args(p)
  p.add_argument("--size", required=True, type=_size_arg,
                 help="HxW input size, multiples of the patch size (e.g. 420x560)")
  p.add_argument("--out", required=True, help="artifact path (PATH.json is written beside it)")
  p.add_argument("--batch", default=1, type=_batch_arg, help="pairs per call, or 'dynamic'")
  p.add_argument("--dtype", default="float32", choices=export.DTYPES,
                 help="compute dtype of encoder + transformer (heads stay float32)")
  p.add_argument("--format", default="stablehlo", choices=export.FORMATS)
  p.add_argument("--outputs", default=None,
                 help="comma-separated model outputs to keep (default: "
                      f"{','.join(export.DEFAULT_OUTPUTS)}, flow alone for a model without "
                      "covisibility, plus flow_covariance for a model with one; refinement models "
                      "also have flow_before_refinement, residual, log_softmax, ...)")
  p.set_defaults(func=_export_main)


def _export_main(args) -> int:
  from ufm_jax.tools import export
  model, variables = load_model(args.checkpoint, snapshot=args.snapshot, revision=args.revision)
  outputs = (None if args.outputs is None else
             [k.strip() for k in args.outputs.split(",") if k.strip()])
  written = export.export(model, variables, args.size, args.out, fmt=args.format, batch=args.batch,
                          dtype=args.dtype, outputs=outputs,
                          checkpoint=(pathlib.Path(args.checkpoint).absolute()
                                      if os.path.exists(args.checkpoint) else args.checkpoint))
  for p in written:
    print(p)
  return 0


def _add_match_parser(sub) -> None:
  p = sub.add_parser("match", help="sparse matches (npz) for OpenCV / COLMAP from one image pair")
  p.add_argument("source")
  p.add_argument("target")
  _add_checkpoint_args(p)
  p.add_argument("--out", required=True, help="matches .npz: keypoints0, keypoints1, confidence "
                 "(+ covariance, precision, sigma from a flow covariance model)")
  p.add_argument("--draw", default=None, help="also draw the matches into this PNG")
  p.add_argument("--num", type=int, default=5000)
  p.add_argument("--min-covisibility", type=float, default=0.5)
  p.add_argument("--bidirectional", action="store_true",
                 help="keep forward-backward consistent matches only (--max-fb-error px)")
  p.add_argument("--max-fb-error", type=float, default=1.0)
  p.add_argument("--max-sigma", type=float, default=None,
                 help="drop matches whose predicted sigma (px, the error ellipse's long axis) is "
                      "above this (a flow covariance model)")
  p.add_argument("--seed", type=int, default=0)
  p.set_defaults(func=_match_main)


def _match_main(args) -> int:
  from ufm_jax.tools import matching
  from ufm_jax.data import io
  source, target = io.read_image(args.source), io.read_image(args.target)
  model, variables = load_model(args.checkpoint, snapshot=args.snapshot, revision=args.revision)
  m = matching.match(model, variables, source, target, num=args.num,
                     min_covisibility=args.min_covisibility, bidirectional=args.bidirectional,
                     max_fb_error_px=args.max_fb_error, seed=args.seed, max_sigma=args.max_sigma)
  out = matching.save_matches(args.out, m, source.shape, target.shape)
  why = matching.shortfall(m, args.num, args.min_covisibility, args.bidirectional)
  ranked = (f", most certain first (median sigma {float(np.median(m['sigma'])):.2f} px)"
            if "sigma" in m and len(m["sigma"]) else "")
  print(f"{out}: {len(m['keypoints0'])} matches{ranked}" + (f" ({why})" if why else ""))
  if args.draw:
    io.write_image(args.draw, matching.draw_matches(source, target, m["keypoints0"], m["keypoints1"]))
    print(args.draw)
  return 0


def _add_demo_parser(sub) -> None:
  from ufm_jax.tools import demo
  p = sub.add_parser("demo", help="local Gradio page: flow, covisibility, warp and matches of two "
                     "images (the [demo] extra)", description=demo.__doc__.split("\n")[0])
  _add_checkpoint_args(p)
  p.add_argument("--port", type=int, default=7860)
  p.add_argument("--host", default="127.0.0.1",
                 help="address to bind; anything but a loopback address exposes the page to the "
                      "network")
  p.add_argument("--share", action="store_true",
                 help="also open a PUBLIC gradio.live link (off unless given)")
  p.add_argument("--max-side", "--max_side", dest="max_side", type=int,
                 default=demo.DEFAULT_MAX_SIDE,
                 help="refuse images with a side longer than this many px")
  p.add_argument("--max-file-size", default=demo.DEFAULT_MAX_FILE_SIZE,
                 help="refuse uploads over this size (gradio syntax: 20mb, 500kb)")
  p.set_defaults(func=_demo_main)


def _demo_main(args) -> int:
  """Load the model, then serve the page until Ctrl-C (the [demo] extra checked first)."""
  from ufm_jax.tools import demo
  try:
    import gradio  # noqa: F401
  except ImportError:
    print(f"error: {demo.INSTALL_HINT}", file=sys.stderr)
    return 2
  if args.max_side < 14:
    raise ValueError(f"--max-side {args.max_side}: must be at least the 14 px patch size")
  model, variables = load_model(args.checkpoint, snapshot=args.snapshot, revision=args.revision)
  demo.serve(model, variables, host=args.host, port=args.port, share=args.share,
             max_side=args.max_side, max_file_size=args.max_file_size)
  return 0


def _convert_main(args) -> int:
  print(model_io.convert_snapshot(args.snapshot_dir, args.out_dir, revision=args.revision))
  return 0


def _add_convert_parser(sub) -> None:
  p = sub.add_parser("convert", help="official HF snapshot -> orbax checkpoint (ufm_jax.runtime.model_io)",
                     description="Converts an official Hugging Face snapshot into an orbax "
                     "checkpoint that ufm_jax.load reads back.")
  p.add_argument("snapshot_dir", help="Hugging Face snapshot (config.json + model.safetensors): "
                 "a folder or a model ID (infinity1096/UFM-Base)")
  p.add_argument("out_dir", help="new folder for the orbax params + model_config.json")
  p.add_argument("--revision", default=None,
                 help="with a model ID: the Hub branch, tag or commit (default: main)")
  p.set_defaults(func=_convert_main)


def _add_to_official_parser(sub) -> None:
  p = sub.add_parser("to-official", help="checkpoint or train.py workdir -> official HF snapshot")
  p.add_argument("checkpoint", help="converted checkpoint or train.py workdir")
  p.add_argument("out_dir", help="new folder for config.json, model.safetensors, README.md")
  p.add_argument("--step", type=int, help="workdir checkpoint step (default: the newest)")
  p.set_defaults(func=_to_official_main)


# Subcommands: each adds its parser (with set_defaults(func=...)) to the subparsers.
SUBCOMMANDS = [_add_infer_parser, _add_export_parser, _add_match_parser, _add_convert_parser,
               _add_to_official_parser, _add_demo_parser]


def main(argv: list[str] | None = None) -> int:
  argv = list(sys.argv[1:] if argv is None else argv)
  parser = argparse.ArgumentParser(prog="python -m ufm_jax",
                                   description=" ".join(__doc__.split("\n\n")[0].split()))
  sub = parser.add_subparsers(dest="command", required=True)
  for add in SUBCOMMANDS:
    add(sub)
  for p in sub.choices.values():
    compile_cache.add_argument(p)
  args = parser.parse_args(argv)
  compile_cache.enable(args.compile_cache)
  try:
    return args.func(args)
  except (FileNotFoundError, FileExistsError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2


if __name__ == "__main__":
  sys.exit(main())
