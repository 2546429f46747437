"""Scripts and tests reach the code through the installed package: no sys.path edits, no test that
imports another test module, no benchmark that imports from tests/."""

import pathlib
import re
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
_SKIP = {".venv", "build", "dist", ".git"}
# Any other virtualenv in the checkout (e.g. the libtpu one docs/scale.md suggests, .venv-tpu).
_VENVS = {p.parent.name for p in REPO.glob("*/pyvenv.cfg")}


def _python_files():
  return sorted(p for p in REPO.rglob("*.py")
                if not (_SKIP | _VENVS) & set(p.relative_to(REPO).parts))


def test_no_sys_path_edits():
  edits = [f"{p.relative_to(REPO)}:{i}" for p in _python_files()
           for i, line in enumerate(p.read_text().splitlines(), 1)
           if re.search(r"\bsys\.path\.(insert|append|extend)\(|\bsys\.path\s*[+]?=", line)]
  assert not edits, f"sys.path edits (import the installed package instead): {edits}"


def test_tests_and_benchmarks_import_no_test_module():
  test_modules = {p.stem for p in (REPO / "tests").glob("test_*.py")}
  bad = []
  for p in _python_files():
    rel = p.relative_to(REPO)
    if rel.parts[0] not in ("tests", "benchmarks"):
      continue
    for i, line in enumerate(p.read_text().splitlines(), 1):
      m = re.match(r"\s*(?:from\s+([\w.]+)\s+import|import\s+([\w.]+))", line)
      name = m and (m.group(1) or m.group(2))
      if name and (name.split(".")[0] == "tests" or name in test_modules or name == "conftest"):
        bad.append(f"{rel}:{i}: {line.strip()}")
  assert not bad, f"shared test helpers live in ufm_jax/testing/: {bad}"


DATA_TOOLS = sorted(str(p.relative_to(REPO)) for p in (REPO / "data").rglob("*.py"))


@pytest.mark.parametrize("tool", DATA_TOOLS)
def test_data_tool_runs_from_any_directory(tool, tmp_path):
  r = subprocess.run([sys.executable, str(REPO / tool), "--help"], cwd=tmp_path,
                     capture_output=True, text=True, timeout=120)
  assert r.returncode == 0, r.stderr[-2000:]
  assert "usage:" in r.stdout


@pytest.mark.parametrize("name", sorted(p.stem for p in (REPO / "configs").glob("*.py")))
def test_config_docstring_is_a_command_not_a_lab_notebook(name):
  """A config's docstring gives the command that runs it; measured figures live in docs/."""
  import ast
  doc = ast.get_docstring(ast.parse((REPO / "configs" / f"{name}.py").read_text())) or ""
  assert f"python train.py --config=configs/{name}.py" in doc
  assert not re.search(r"\bmeasured\b|\d+(\.\d+)? ?-> ?\d+(\.\d+)? ?px", doc, re.IGNORECASE), doc
  for path in re.findall(r"\bdocs/[\w./-]+\.md", doc):
    assert (REPO / path).is_file(), path


def test_default_outputs_are_ignored_by_git():
  """evaluate.py's default --out (results/) and the README's workdirs/ never show up as changes."""
  ignored = {line.strip() for line in (REPO / ".gitignore").read_text().splitlines()}
  assert {"/results/", "/workdirs/"} <= ignored


def test_model_code_passes_no_bare_bool_positionally():
  """`Block(..., True, False)` reads as nothing; flags go by keyword (dict.get/getattr defaults aside)."""
  import ast
  bad = []
  for p in sorted((REPO / "ufm_jax" / "models").glob("*.py")):
    for node in ast.walk(ast.parse(p.read_text())):
      if not isinstance(node, ast.Call):
        continue
      fn = node.func
      if (isinstance(fn, ast.Attribute) and fn.attr == "get") or \
          (isinstance(fn, ast.Name) and fn.id == "getattr"):
        continue
      if any(isinstance(a, ast.Constant) and isinstance(a.value, bool) for a in node.args):
        bad.append(f"{p.relative_to(REPO)}:{node.lineno}: {ast.unparse(node)[:80]}")
  assert not bad, bad


def _text_files():
  out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                       capture_output=True, text=True, check=True).stdout.split()
  return [REPO / f for f in out if f.endswith((".py", ".md")) and (REPO / f).is_file()]


# Documents named before they land, with the branch that writes them; the test fails once one
# exists, so that its entry goes.
PENDING_DOCS: dict[str, str] = {}


def test_doc_references_resolve():
  """Every `docs/<x>.md` and `data/<name>/README.md` a file names, every bare `<x>.md` and every
  relative Markdown link exists in the repository, every README section a file points to (the
  README's name, then the heading or bullet label in single quotes) is there, and no file sends the
  reader to a document outside the repository (a fresh clone has nothing beside it)."""
  files = _text_files()
  md_names = {p.name for p in files if p.suffix == ".md"}
  readme = (REPO / "README.md").read_text()
  bad = []
  for p in files:
    text, rel = p.read_text(), p.relative_to(REPO)
    for m in re.finditer(r"(?<![\w/.~-])(docs/[\w./-]+\.md|data/[\w-]+/README\.md)", text):
      if not (REPO / m.group(1)).is_file():
        bad.append(f"{rel}: {m.group(1)}")
    for m in re.finditer(r"(?<![\w/.-])([\w-]+\.md)\b", text):
      if m.group(1) not in md_names:
        bad.append(f"{rel}: {m.group(1)}")
    for m in re.finditer(r"(?<![\w/.-])(\.\./[\w./-]+\.md)", text):
      target = (p.parent / m.group(1)).resolve()
      if REPO not in target.parents or not target.is_file():
        bad.append(f"{rel}: {m.group(1)}")
    for m in re.finditer(r"README(?:\.md)?[,:]? '([^']+)'", text):   # a README section
      label = re.escape(m.group(1))   # a heading, or a bullet's leading label
      if not re.search(rf"^(#+ {label}\s*$|- {label}:)", readme, re.MULTILINE):
        bad.append(f"{rel}: README section {m.group(1)!r}")
    if p.suffix == ".md":
      for m in re.finditer(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", text):
        if not m.group(1).startswith(("http:", "https:", "mailto:")) and \
            not (p.parent / m.group(1)).exists():
          bad.append(f"{rel}: link {m.group(1)}")
  landed = [d for d in PENDING_DOCS if (REPO / d).is_file()]
  assert not landed, f"{landed} exist now: remove them from PENDING_DOCS"
  bad = [b for b in bad if b.split(": ", 1)[1] not in PENDING_DOCS]
  assert not bad, f"references to files that do not exist: {bad}"


def test_datasets_doc_names_every_reader():
  """docs/datasets.md tables every registered reader and both layouts' readers of every training
  set (ufm_jax.data.mixture.LAYOUTS)."""
  from ufm_jax import data
  from ufm_jax.data import mixture, registry
  doc = (REPO / "docs" / "datasets.md").read_text()
  # The package's readers (tests register their own stand-ins in the same process).
  factories = registry._REGISTRY  # pylint: disable=protected-access
  readers = {n for n in data.available() if factories[n].__module__.startswith("ufm_jax.")}
  readers |= {l.source for ls in mixture.LAYOUTS.values() for l in ls}
  missing = sorted(r for r in readers if f"`{r}`" not in doc)
  assert not missing, f"docs/datasets.md does not name the readers {missing}"
  folders = [l.folders[0] for ls in mixture.LAYOUTS.values() for l in ls if l.kind == "official"]
  missing = [f for f in folders if f"`{f.split('/')[0]}" not in doc]
  assert not missing, f"docs/datasets.md does not name the official folders {missing}"
