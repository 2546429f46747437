"""Shared test fixtures: where the official reference snapshots live, running the scripts."""

import os
import pathlib
import subprocess
import sys
import tempfile

import pytest

# One persistent XLA compilation cache for the whole run, this process and every train.py /
# evaluate.py / CLI subprocess it starts (they inherit the environment): many tests compile the
# same small models, and compiling dominates the suite's time on a CPU. Set before jax is imported.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      os.path.join(tempfile.gettempdir(), "ufm_jax_tests_xla_cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")

REPO = pathlib.Path(__file__).resolve().parents[1]
# CI clones main with shared/ beside it; UFM_FIXTURES points elsewhere when needed.
FIXTURES = pathlib.Path(os.environ.get("UFM_FIXTURES", REPO.parent / "shared" / "fixtures"))
REFERENCE = FIXTURES / "ufm_reference"


@pytest.fixture(scope="session")
def reference_dir():
  """Folder holding the official-code snapshots (`base/`, `refine/`).

  Absent (a clone outside the project's layout): the parity tests are skipped, naming
  UFM_FIXTURES; under CI=true they fail instead, so CI can never pass by skipping parity.
  """
  if not REFERENCE.is_dir():
    from ufm_jax import testing  # after the cache variables above: it imports jax
    testing.skip_or_fail(f"official reference fixtures not found at {REFERENCE}: set UFM_FIXTURES "
                         "to the folder that holds ufm_reference/ (README.md, 'Set up')",
                         "CI=true: parity tests may not be skipped")
  return REFERENCE


@pytest.fixture
def run_evaluate():
  """`python evaluate.py ARGS` as a user runs it, from the repo root: (exit code, stdout, stderr)."""
  def run(*args):
    out = subprocess.run([sys.executable, str(REPO / "evaluate.py"), *args], capture_output=True,
                         text=True, timeout=900, cwd=REPO)
    return out.returncode, out.stdout, out.stderr
  return run


def pytest_collection_modifyitems(items):
  """The Slurm test first: it spends minutes waiting on its jobs' starts, and run first it
  overlaps the other worker's tests instead of being the suite's last minutes on one worker."""
  items.sort(key=lambda item: item.get_closest_marker("slurm") is None)
