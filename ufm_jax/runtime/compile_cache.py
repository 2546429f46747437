"""JAX's persistent compilation cache for the tools: the CLI, evaluate.py and `predict`.

A second `python -m ufm_jax infer` (or evaluate, or a new process calling predict) on the same
shapes loads the compiled forward from disk instead of compiling it again (about 20 s for
UFM-Base at 560 on a 2-core CPU; `python benchmarks/cli_latency.py` prints cold and warm).

Where: `$UFM_JAX_COMPILE_CACHE`, else `$XDG_CACHE_HOME/ufm_jax/xla` (`~/.cache/ufm_jax/xla`).
`--compile_cache DIR|off` on the CLI and evaluate.py, or UFM_JAX_COMPILE_CACHE=off, turn it
elsewhere or off. A cache the caller configured already (`jax_compilation_cache_dir`, e.g. via
JAX_COMPILATION_CACHE_DIR) is left as it is: a library does not override its host program.
"""

from __future__ import annotations

import os
import pathlib

ENV = "UFM_JAX_COMPILE_CACHE"
OFF = ("off", "0", "none", "false")
_OFF_CHOSEN = False  # a tool's "off" holds for the library calls after it (predict)


def default_dir() -> pathlib.Path:
  base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
  return pathlib.Path(base) / "ufm_jax" / "xla"


def enable(where: str | os.PathLike | None = None) -> pathlib.Path | None:
  """Turns the persistent cache on at `where` (None: $UFM_JAX_COMPILE_CACHE or default_dir();
  "off": leave it off) unless one is configured already; returns the cache folder in use, or
  None when it is off. Idempotent."""
  import jax

  global _OFF_CHOSEN
  current = jax.config.jax_compilation_cache_dir
  if current:
    return pathlib.Path(current)
  if where is None and _OFF_CHOSEN:
    return None
  explicit = where is not None
  where = os.environ.get(ENV) if where is None else where
  if where is not None and str(where).strip().lower() in OFF:
    _OFF_CHOSEN = _OFF_CHOSEN or explicit
    return None
  path = pathlib.Path(where).expanduser() if where else default_dir()
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError:
    return None  # read-only home (a container): run without the cache rather than fail
  jax.config.update("jax_compilation_cache_dir", str(path))
  return path


def add_argument(parser) -> None:
  """The `--compile_cache DIR|off` option of a command-line tool."""
  parser.add_argument("--compile_cache", default=None, metavar="DIR|off",
                      help=f"persistent XLA compilation cache (default: ${ENV} or {default_dir()}); "
                           "'off' compiles every run afresh")
