"""The tools' persistent compilation cache (ufm_jax.runtime.compile_cache): a second `infer` process on
the same shapes loads the forward from disk; `--compile_cache off` and a host's own cache dir."""

import json
import os
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ufm_jax.data.io import write_image

REPO = pathlib.Path(__file__).resolve().parents[1]

# Runs the CLI in-process and reports JAX's own cache events (hits are executables loaded from
# the persistent cache instead of compiled).
DRIVER = textwrap.dedent("""
    import json, sys
    import jax
    events = []
    jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
    from ufm_jax.tools import cli
    rc = cli.main(sys.argv[1:])
    print(json.dumps({"rc": rc, "cache_dir": jax.config.jax_compilation_cache_dir,
                      "hits": events.count("/jax/compilation_cache/cache_hits"),
                      "misses": events.count("/jax/compilation_cache/cache_misses")}))
""")


def _infer(args, env_extra):
  env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
  env.update(env_extra, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
             PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  r = subprocess.run([sys.executable, "-c", DRIVER, "infer", *map(str, args)], capture_output=True,
                     text=True, timeout=600, env=env, cwd=REPO)
  assert r.returncode == 0, r.stderr[-3000:]
  return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_second_infer_loads_the_forward_from_the_cache(reference_dir, tmp_path):
  io = np.load(reference_dir / "base" / "io.npz")
  src, tgt = tmp_path / "a.png", tmp_path / "b.png"
  write_image(src, io["hl1_src_uint8"])
  write_image(tgt, io["hl1_tgt_uint8"])
  args = [src, tgt, "--checkpoint", reference_dir / "base", "--snapshot"]
  cache = tmp_path / "cache"
  env = {"UFM_JAX_COMPILE_CACHE": str(cache), "XDG_CACHE_HOME": str(tmp_path / "xdg")}

  cold = _infer(args + ["--out", tmp_path / "o1"], env)
  assert cold["rc"] == 0 and cold["cache_dir"] == str(cache)
  assert cold["misses"] >= 1 and any(cache.iterdir())
  warm = _infer(args + ["--out", tmp_path / "o2"], env)
  assert warm["rc"] == 0 and warm["hits"] >= 1 and warm["misses"] == 0, warm
  assert (tmp_path / "o1" / "forward.flo").read_bytes() == (tmp_path / "o2" / "forward.flo").read_bytes()

  off = _infer(args + ["--out", tmp_path / "o3", "--compile_cache", "off"], env)
  assert off["cache_dir"] is None and off["hits"] == 0
  assert not (tmp_path / "xdg").exists()   # neither the default folder


def test_a_configured_cache_is_left_alone(tmp_path):
  """The host program's JAX_COMPILATION_CACHE_DIR wins over --compile_cache and the default."""
  code = ("from ufm_jax.runtime import compile_cache; print(compile_cache.enable(%r))"
          % str(tmp_path / "other"))
  env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "mine"))
  r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                     timeout=120)
  assert r.returncode == 0, r.stderr
  assert r.stdout.strip() == str(tmp_path / "mine") and not (tmp_path / "other").exists()
