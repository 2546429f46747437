"""Shared test fixtures: where the official reference snapshots live."""

import os
import pathlib

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
# CI clones main with shared/ beside it; UFM_FIXTURES points elsewhere when needed.
FIXTURES = pathlib.Path(os.environ.get("UFM_FIXTURES", REPO.parent / "shared" / "fixtures"))
REFERENCE = FIXTURES / "ufm_reference"


@pytest.fixture(scope="session")
def reference_dir():
  """Folder holding the official-code snapshots (`base/`, `refine/`)."""
  if not REFERENCE.is_dir():
    pytest.fail(f"reference fixtures not found at {REFERENCE}; set UFM_FIXTURES to the folder "
                "that holds ufm_reference/")
  return REFERENCE
