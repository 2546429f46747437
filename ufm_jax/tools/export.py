"""Exported models: the UFM forward with its parameters baked in, for deployment without this code.

  python -m ufm_jax export --checkpoint DIR [--snapshot] --size HxW --out PATH
      [--batch N|dynamic] [--dtype float32|bfloat16] [--format stablehlo|onnx] [--outputs a,b]

Both formats take `source`, `target` uint8 [B, H, W, 3] RGB (H, W the export size) and return
`flow` [B, H, W, 2] float32 pixels and `covisibility` [B, H, W], and from a model with a flow
covariance `flow_covariance` [B, H, W, 3] (var_x, var_y, cov_xy in px^2 of the export size) (plus
any extra outputs named with --outputs, e.g. `flow_covariance_inv`, a refinement model's
`flow_before_refinement`); a model without an uncertainty head (the refinement training recipe's)
exports `flow` alone by default (a warning says so).
Images must already be at the export size: resize on the host (ufm_jax.predict does it the
official way) or export at the camera's resolution.

  stablehlo  PATH holds `jax.export.Exported.serialize()` bytes for platforms cpu and cuda (a
             symbolic batch with --batch dynamic). It runs with jax alone:
               exp = jax.export.deserialize(open(PATH, "rb").read()); out = exp.call(src, tgt)
  onnx       one graph through jax2onnx (the optional `[onnx]` extra), run by onnxruntime; a
             graph over 2 GB keeps its weights in PATH.data beside it.

PATH.json (the sidecar) records the format, input size, batch, dtype, input/output shapes, the
model class and config, the checkpoint and the ufm_jax/jax versions. `load_exported(PATH)` returns
a callable for either format; it never imports the model code (ufm_jax.models).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
from typing import Sequence

import numpy as np

FORMATS = ("stablehlo", "onnx")
DTYPES = ("float32", "bfloat16")
DEFAULT_OUTPUTS = ("flow", "covisibility")
# Added to the defaults when the model has them (no warning when it has not).
OPTIONAL_OUTPUTS = ("flow_covariance",)
PLATFORMS = ("cpu", "cuda")
INPUT_NAMES = ("source", "target")


class ExportError(ValueError):
  """An export that cannot be done as asked (bad size, unknown output, an op ONNX lacks)."""


def sidecar_path(path: str | os.PathLike) -> pathlib.Path:
  p = pathlib.Path(path)
  return p.with_name(p.name + ".json")


# ----------------------------------------------------------------------------------------------
# Export


def _prepare(model, variables, size, dtype, outputs, attention_impl=None):
  """(forward fn(source, target) -> {name: array}, the model as exported, output names).

  attention_impl None picks per platform inside the artifact (the CPU loop, XLA on CUDA); ONNX
  asks for "xla": one portable graph for other runtimes."""
  import jax
  import jax.numpy as jnp

  from ufm_jax.models import ufm
  variables = ufm.variables(variables)
  if dtype not in DTYPES:
    raise ExportError(f"--dtype {dtype!r}; expected one of {', '.join(DTYPES)}")
  cfg = model.config
  # remat only matters for gradients; the fused cuDNN attention cannot lower for the cpu platform.
  model = model.clone(config=dataclasses.replace(cfg, dtype=dtype, remat=False,
                                                 attention_impl=attention_impl))
  h, w = size
  patch = cfg.encoder.patch_size
  if h <= 0 or w <= 0 or h % patch or w % patch:
    raise ExportError(f"--size {h}x{w}: H and W must be positive multiples of the patch size "
                      f"{patch} (e.g. {max(patch, h // patch * patch)}x{max(patch, w // patch * patch)})")
  spec = jax.ShapeDtypeStruct((1, h, w, 3), jnp.uint8)
  available = jax.eval_shape(lambda s, t: model.apply(variables, s, t), spec, spec)
  outputs = resolve_outputs(outputs, available, model)
  missing = [k for k in outputs if k not in available]
  if missing or not outputs:
    raise ExportError(f"outputs {missing or list(outputs)} not produced by {type(model).__name__}; "
                      f"it returns {', '.join(sorted(available))}")

  def forward(source, target):
    out = model.apply(variables, source, target)
    return {k: out[k] for k in outputs}

  return forward, model, outputs


def resolve_outputs(outputs, available, model=None) -> tuple[str, ...]:
  """The output names to export: `outputs`, or for None the default ones the model produces
  (`DEFAULT_OUTPUTS`: no covisibility from a model that predicts none, with a warning;
  `OPTIONAL_OUTPUTS` where the model has them)."""
  if outputs is not None:
    return tuple(outputs)
  optional = tuple(k for k in OPTIONAL_OUTPUTS if k in available)
  chosen = tuple(k for k in DEFAULT_OUTPUTS if k in available)
  if chosen != DEFAULT_OUTPUTS:
    from absl import logging
    logging.log_first_n(logging.WARNING, "%s produces no %s (no non_occluded_mask adaptor in any "
                        "head): exporting %s",
                        1, type(model).__name__,
                        ", ".join(sorted(set(DEFAULT_OUTPUTS) - set(chosen))), ", ".join(chosen))
  return chosen + optional


def _batch_dim(batch):
  if batch == "dynamic":
    from jax import export as jax_export
    return jax_export.symbolic_shape("batch")[0]
  if int(batch) < 1:
    raise ExportError(f"--batch {batch}: expected a positive integer or 'dynamic'")
  return int(batch)


def export_stablehlo(model, variables, size, *, batch=1, dtype="float32",
                     outputs: Sequence[str] | None = None, platforms=PLATFORMS):
  """The forward as a `jax.export.Exported` (parameters are constants inside it)."""
  import jax
  import jax.numpy as jnp
  from jax import export as jax_export

  forward, model, outputs = _prepare(model, variables, size, dtype, outputs)
  spec = jax.ShapeDtypeStruct((_batch_dim(batch),) + tuple(size) + (3,), jnp.uint8)
  return jax_export.export(jax.jit(forward), platforms=tuple(platforms))(spec, spec), model


def _jax2onnx():
  try:
    import jax2onnx
  except ImportError as e:
    raise ExportError("--format onnx needs the optional extra: pip install 'ufm_jax[onnx]' "
                      f"({e})") from None
  return jax2onnx


def _equations(jaxpr, scope: str = ""):
  """(equation, its name stack) for every equation of a jaxpr and of its sub-jaxprs (jit, scan,
  cond, ...); a sub-jaxpr's name stacks continue its parent equation's."""
  for eqn in jaxpr.eqns:
    where = "/".join(p for p in (scope, str(eqn.source_info.name_stack)) if p)
    yield eqn, where
    for value in eqn.params.values():
      for sub in value if isinstance(value, (list, tuple)) else (value,):
        inner = getattr(sub, "jaxpr", sub)   # ClosedJaxpr -> Jaxpr
        if hasattr(inner, "eqns"):
          yield from _equations(inner, where)


def onnx_failure(exc: BaseException, fn, specs) -> str | None:
  """'primitive X in model part Y' for a jax2onnx conversion failure, else None.

  The op is the primitive the converter's message names, else the jax2onnx plugin module the
  error came from (`plugins/.../svd.py`: plugins are named after their op); the model part is
  the Flax module path of that primitive's first equation in `jax.make_jaxpr(fn)(*specs)`.
  Public APIs only (the message, traceback file names, the jaxpr)."""
  import re
  import traceback

  import jax

  m = re.search(r"primitive '([^']+)'", str(exc))
  if m is not None:
    name = m.group(1)
  else:
    plugins = [f.filename.replace(os.sep, "/").split("/jax2onnx/plugins/", 1)[1]
               for f in traceback.extract_tb(exc.__traceback__)
               if "/jax2onnx/plugins/" in f.filename.replace(os.sep, "/")]
    if not plugins:
      return None
    name = plugins[-1].rsplit("/", 1)[-1].removesuffix(".py")
  import flax.linen as nn
  try:
    with nn.override_named_call(True):   # Flax module paths in the equations' name stacks
      jaxpr = jax.make_jaxpr(fn)(*specs).jaxpr
  except Exception:  # noqa: BLE001 - the op's name alone is still worth saying
    return f"op {name!r}"
  parts = [where for e, where in _equations(jaxpr) if e.primitive.name == name]
  if not parts:
    return f"op {name!r}"
  part = next((p for p in parts if p), "(top level)")
  return f"primitive {name!r} in model part {part}"


def write_onnx(fn, specs, input_names, output_names, path) -> None:
  """jax2onnx conversion of fn(*specs) -> tuple to `path`, written whole or not at all; an
  ExportError names the primitive and the model part that could not be converted."""
  from ufm_jax.data import io
  jax2onnx = _jax2onnx()
  path = pathlib.Path(path).absolute()
  # Large graphs spill weights into a data file that the graph names: convert in a temp folder
  # under the final file name, then move both.
  with io.staging_dir(path) as tmp:
    try:
      jax2onnx.to_onnx(fn, list(specs), input_names=list(input_names),
                       output_names=list(output_names), model_name=path.stem,
                       return_mode="file", output_path=str(tmp / path.name))
    except Exception as e:  # noqa: BLE001 - any converter failure: say where, keep the cause
      what = onnx_failure(e, fn, specs)
      if what is None:
        raise
      raise ExportError(f"ONNX export: jax2onnx cannot convert {what}: "
                        f"{type(e).__name__}: {str(e)[:300]}") from e
    for f in sorted(tmp.iterdir(), key=lambda f: f.name == path.name):  # the graph last
      os.replace(f, path.parent / f.name)


def export_onnx(model, variables, size, path, *, batch=1, dtype="float32",
                outputs: Sequence[str] | None = None):
  """Writes the forward as one ONNX graph (inputs source/target, outputs named as `outputs`)."""
  import jax
  import jax.numpy as jnp

  if batch == "dynamic":
    # jax2onnx loses track of a symbolic batch at the two-view split (the encoder runs both views
    # as one batch, ufm.UFM.encode), so the ONNX graph has a fixed batch.
    raise ExportError("--format onnx needs a fixed --batch N (a symbolic batch does not survive "
                      "jax2onnx's conversion of the two-view split); use --format stablehlo for "
                      "a dynamic batch")
  forward, model, outputs = _prepare(model, variables, size, dtype, outputs, attention_impl="xla")
  spec = jax.ShapeDtypeStruct((_batch_dim(batch),) + tuple(size) + (3,), jnp.uint8)
  specs = [spec, spec]
  def fn(source, target):
    # forward once for every output: a call per output traces the model once each, and jax2onnx
    # merges the copies only after its quadratic transpose pass (minutes, larger files).
    out = forward(source, target)
    return tuple(out[k] for k in outputs)

  write_onnx(fn, specs, INPUT_NAMES, outputs, path)
  return model


def _sidecar(fmt, model, size, batch, dtype, outputs, shapes, checkpoint, platforms):
  import jax

  import ufm_jax
  from ufm_jax.official import config as official_config
  class_name = (official_config.class_name(model) if type(model) in official_config.CLASS_NAMES
                else type(model).__name__)
  h, w = size
  b = batch if batch == "dynamic" else int(batch)
  return {
      "format": fmt,
      "input_size": [int(h), int(w)],
      "batch": b,
      "dtype": dtype,
      "platforms": list(platforms) if fmt == "stablehlo" else ["onnxruntime"],
      "inputs": {n: {"shape": [b, h, w, 3], "dtype": "uint8", "layout": "NHWC RGB 0..255"}
                 for n in INPUT_NAMES},
      "outputs": {k: {"shape": [b] + list(shapes[k][1:]), "dtype": shapes[k + ":dtype"]}
                  for k in outputs},
      "model": {"class": class_name, "config": dataclasses.asdict(model.config)},
      "checkpoint": None if checkpoint is None else str(checkpoint),
      "ufm_jax_version": ufm_jax.__version__,
      "jax_version": jax.__version__,
  }


def export(model, variables, size, out, *, fmt="stablehlo", batch=1, dtype="float32",
           outputs: Sequence[str] | None = None, checkpoint=None,
           platforms=PLATFORMS) -> list[pathlib.Path]:
  """Exports (model, variables) at `size` (H, W) to `out` + its JSON sidecar; returns the paths."""
  import jax
  import jax.numpy as jnp

  from ufm_jax.data import io
  from ufm_jax.models import ufm
  variables = ufm.variables(variables)
  if fmt not in FORMATS:
    raise ExportError(f"--format {fmt!r}; expected one of {', '.join(FORMATS)}")
  out = pathlib.Path(out)
  out.parent.mkdir(parents=True, exist_ok=True)
  size = (int(size[0]), int(size[1]))
  if fmt == "stablehlo":
    exp, model = export_stablehlo(model, variables, size, batch=batch, dtype=dtype, outputs=outputs,
                                  platforms=platforms)
    with io.atomic_file(out) as tmp:
      pathlib.Path(tmp).write_bytes(bytes(exp.serialize()))
    written = [out]
  else:
    model = export_onnx(model, variables, size, out, batch=batch, dtype=dtype, outputs=outputs)
    written = [out] + ([out.with_name(out.name + ".data")] if out.with_name(out.name + ".data")
                       .exists() else [])
  spec = jax.ShapeDtypeStruct((1,) + size + (3,), jnp.uint8)
  avals = jax.eval_shape(lambda s, t: model.apply(variables, s, t), spec, spec)
  outputs = resolve_outputs(outputs, avals, model)
  shapes = {}
  for k in outputs:
    shapes[k], shapes[k + ":dtype"] = tuple(avals[k].shape), str(avals[k].dtype)
  meta = _sidecar(fmt, model, size, batch, dtype, outputs, shapes, checkpoint, platforms)
  side = sidecar_path(out)
  io.write_json_atomic(side, meta)
  return written + [side]


# ----------------------------------------------------------------------------------------------
# Loading


class ExportedModel:
  """Callable(source, target) -> {output name: numpy array} over an exported artifact.

  Takes uint8 [B, H, W, 3] (or one [H, W, 3] pair) at the export size. A fixed-batch export is
  fed in chunks of its batch, the last one padded, so any number of pairs works.
  """

  def __init__(self, path, meta: dict, run, batch):
    self.path, self.meta, self._run, self.batch = pathlib.Path(path), meta, run, batch
    self.input_size = tuple(meta["input_size"]) if meta else None

  def __call__(self, source, target) -> dict[str, np.ndarray]:
    source, target = np.asarray(source), np.asarray(target)
    single = source.ndim == 3
    if single:
      source, target = source[None], target[None]
    for name, x in (("source", source), ("target", target)):
      if x.ndim != 4 or x.shape[-1] != 3 or x.dtype != np.uint8:
        raise ValueError(f"{self.path}: {name} must be uint8 [B, H, W, 3] (or [H, W, 3]); got "
                         f"{x.dtype} {x.shape}")
      if self.input_size and tuple(x.shape[1:3]) != self.input_size:
        raise ValueError(f"{self.path}: exported for {self.input_size[0]}x{self.input_size[1]} "
                         f"images; {name} is {x.shape[1]}x{x.shape[2]} (resize first)")
    if source.shape != target.shape:
      raise ValueError(f"{self.path}: source {source.shape} and target {target.shape} differ")
    n = len(source)
    if self.batch is None or n == self.batch:
      out = self._run(source, target)
    else:
      chunks = []
      for s in range(0, n, self.batch):
        src, tgt = source[s:s + self.batch], target[s:s + self.batch]
        pad = self.batch - len(src)
        if pad:
          src = np.concatenate([src, np.repeat(src[-1:], pad, 0)])
          tgt = np.concatenate([tgt, np.repeat(tgt[-1:], pad, 0)])
        chunks.append({k: v[:len(v) - pad] for k, v in self._run(src, tgt).items()})
      out = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    return {k: v[0] for k, v in out.items()} if single else out


def _load_stablehlo(path, meta):
  import jax
  from jax import export as jax_export

  try:
    exp = jax_export.deserialize(bytearray(pathlib.Path(path).read_bytes()))
  except Exception as e:  # noqa: BLE001 - a truncated or foreign file
    raise ValueError(f"{path}: not a jax.export artifact ({type(e).__name__}: {e})") from None
  platform = jax.devices()[0].platform
  if platform not in exp.platforms:
    raise ValueError(f"{path}: exported for platforms {', '.join(exp.platforms)}; this machine "
                     f"runs {platform}")
  call = jax.jit(exp.call)
  b = exp.in_avals[0].shape[0]
  batch = b if isinstance(b, int) else None

  def run(source, target):
    return {k: np.asarray(v) for k, v in call(source, target).items()}

  return ExportedModel(path, meta, run, batch), exp


def _load_onnx(path, meta):
  try:
    import onnxruntime as ort
  except ImportError as e:
    raise ValueError(f"{path}: running an ONNX export needs onnxruntime (pip install "
                     f"'ufm_jax[onnx]'): {e}") from None
  session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
  names = [o.name for o in session.get_outputs()]
  b = session.get_inputs()[0].shape[0]
  batch = b if isinstance(b, int) else None

  def run(source, target):
    return dict(zip(names, session.run(names, {"source": source, "target": target})))

  return ExportedModel(path, meta, run, batch), session


def load_exported(path: str | os.PathLike) -> ExportedModel:
  """A callable(source, target) -> {"flow", "covisibility", ...} for an exported artifact.

  The format comes from the sidecar (PATH.json) when present, else from the suffix (.onnx) or
  the file itself. No model code is imported and no parameters are loaded separately.
  """
  p = pathlib.Path(path)
  if not p.is_file():
    raise FileNotFoundError(f"exported model not found: {p}")
  side = sidecar_path(p)
  meta = json.loads(side.read_text()) if side.is_file() else {}
  fmt = meta.get("format") or ("onnx" if p.suffix == ".onnx" else "stablehlo")
  if fmt not in FORMATS:
    raise ValueError(f"{side}: unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
  model, handle = (_load_onnx if fmt == "onnx" else _load_stablehlo)(p, meta)
  model.handle = handle  # the jax.export.Exported or the onnxruntime.InferenceSession
  return model


__all__ = ["ExportError", "ExportedModel", "export", "export_onnx", "export_stablehlo",
           "load_exported", "onnx_failure", "sidecar_path", "write_onnx"]
