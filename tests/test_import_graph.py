"""The import graph of `ufm_jax` has no cycles, function-level imports included, library code
never imports the command line (#34), and the model package knows neither the data nor the
official format (#41): parsed with `ast`, nothing is imported."""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "ufm_jax"
# Entry points may import the CLI; nothing else may.
CLI_IMPORTERS = {"ufm_jax.__main__"}


def _modules() -> dict[str, pathlib.Path]:
  out = {}
  for path in PACKAGE.rglob("*.py"):
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
      parts = parts[:-1]
    out[".".join(parts)] = path
  return out


def _resolve(name: str, modules) -> str | None:
  """The longest prefix of the dotted `name` that is a module of the package."""
  parts = name.split(".")
  while parts:
    if ".".join(parts) in modules:
      return ".".join(parts)
    parts.pop()
  return None


def _edges(module: str, path: pathlib.Path, modules) -> set[str]:
  """Package modules `module` imports anywhere in its file, plus the packages that importing
  them runs (`import a.b.c` executes a/__init__ and a/b/__init__ too), except its own."""
  is_package = path.name == "__init__.py"
  targets = set()
  for node in ast.walk(ast.parse(path.read_text(), str(path))):
    if isinstance(node, ast.Import):
      names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom):
      if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[:len(base) - node.level + 1]
        prefix = ".".join(base + ([node.module] if node.module else []))
      else:
        prefix = node.module
      # `from pkg import mod` imports the submodule pkg.mod when there is one.
      names = [prefix] + [f"{prefix}.{a.name}" for a in node.names]
    else:
      continue
    for name in names:
      if not name or not name.startswith("ufm_jax"):
        continue
      target = _resolve(name, modules)
      while target:
        targets.add(target)
        target = target.rpartition(".")[0] if "." in target else None
  # A module's own packages are already running when it runs: no edge back to them.
  parts = module.split(".")
  return targets - {".".join(parts[:i]) for i in range(1, len(parts) + 1)}


def _graph():
  modules = _modules()
  return {m: _edges(m, p, modules) for m, p in modules.items()}


def _cycle(graph) -> list[str] | None:
  """One cycle of `graph` as [a, b, ..., a], or None (iterative depth-first search)."""
  state = {}
  for root in sorted(graph):
    if root in state:
      continue
    stack = [(root, iter(sorted(graph[root])))]
    path = [root]
    state[root] = "open"
    while stack:
      node, children = stack[-1]
      child = next(children, None)
      if child is None:
        state[node] = "done"
        stack.pop()
        path.pop()
      elif state.get(child) == "open":
        return path[path.index(child):] + [child]
      elif child not in state:
        state[child] = "open"
        stack.append((child, iter(sorted(graph.get(child, ())))))
        path.append(child)
  return None


def test_the_checker_finds_a_cycle_and_resolves_imports():
  assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
  assert _cycle({"a": {"b"}, "b": set()}) is None
  graph = _graph()
  assert "ufm_jax.official.dinov2_weights" in graph["ufm_jax.training.model_init"]  # a function-level import
  assert "ufm_jax.official" in graph["ufm_jax.training.model_init"]  # the package the import runs
  assert "ufm_jax.tools.cli" in graph["ufm_jax.__main__"]


def test_no_import_cycles():
  cycle = _cycle(_graph())
  assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("module", ["ufm_jax.tools.cli"])
def test_library_code_never_imports_the_cli(module):
  importers = sorted(m for m, targets in _graph().items() if module in targets)
  assert set(importers) <= CLI_IMPORTERS, importers


def test_the_model_package_imports_only_itself():
  """ufm_jax.models is the network alone: reading files (ufm_jax.data) and the official names
  (ufm_jax.official) sit above it, in the loaders."""
  graph = _graph()
  bad = {m: sorted(t for t in targets if not t.startswith("ufm_jax.models") and t != "ufm_jax")
         for m, targets in graph.items() if m.startswith("ufm_jax.models")}
  assert not {m: t for m, t in bad.items() if t}, bad


# The floors of the house, bottom up (docs/architecture.md): a package imports only packages on its
# own floor or below. `testing` (helpers of the tests and benchmarks) sits on top.
FLOORS = [{"models", "geometry"}, {"data"}, {"official"}, {"runtime"}, {"training"},
          {"evaluators"}, {"planning"}, {"tools"}, {"testing"}]


def _package(module: str) -> str | None:
  parts = module.split(".")
  return parts[1] if len(parts) > 1 and (PACKAGE / parts[1]).is_dir() else None


def test_every_module_lives_in_a_package():
  """ufm_jax's top level holds the public API (__init__) and the entry point (__main__) only."""
  assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py", "__main__.py"]
  assert {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()} == set().union(*FLOORS)


def test_no_import_runs_back_up_a_floor():
  floor = {pkg: i for i, names in enumerate(FLOORS) for pkg in names}
  up = sorted(f"{m} -> {t}" for m, targets in _graph().items() for t in targets
              if _package(m) and _package(t) and floor[_package(t)] > floor[_package(m)])
  assert not up, up
