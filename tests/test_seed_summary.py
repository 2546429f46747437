"""benchmarks/seed_summary.py: the mean, range and ratios the docs' 3-seed figures are printed by."""

import json

import pytest

from ufm_jax import testing


def _results(folder, step=2000, **metrics):
  folder.mkdir()
  (folder / "results.json").write_text(json.dumps({"step": step, "metrics": metrics}))
  return str(folder)


def test_mean_range_and_ratios(tmp_path, capsys):
  tool = testing.load_script("benchmarks/seed_summary.py")
  a = _results(tmp_path / "a", **{"s/epe": 3.0, "s/ause": 0.4, "s/ause_random": 1.6})
  b = _results(tmp_path / "b", **{"s/epe": 5.0, "s/ause": 0.9, "s/ause_random": 1.5})
  c = _results(tmp_path / "c", **{"s/epe": 4.0, "s/ause": 0.5, "s/ause_random": 2.0,
                                  "s/nll": float("nan")})
  ref = _results(tmp_path / "ref", **{"s/epe": 3.2})
  assert tool.main([a, b, c, "--versus", ref, "--ratio", "s/ause:s/ause_random"]) == 0
  out = capsys.readouterr().out.splitlines()
  epe = next(line for line in out if line.startswith("s/epe "))
  # mean 4, range [3, 5]; 4 / 3.2 = 1.25
  assert "4.0000 [3.0000, 5.0000]" in epe and "= 1.250x" in epe
  # per run: 0.25, 0.6, 0.25 -> mean 0.3667
  assert out[-1] == "s/ause / s/ause_random: 0.367 [0.250, 0.600] | 0.250 0.600 0.250"
  assert not any(line.startswith("s/nll") for line in out)   # no finite value in any run


def test_a_missing_metric_or_file_is_named(tmp_path, capsys):
  tool = testing.load_script("benchmarks/seed_summary.py")
  a = _results(tmp_path / "a", **{"s/epe": 3.0})
  assert tool.main([a, "--ratio", "s/epe:s/ause"]) == 2
  assert "no metric 's/ause' in every run" in capsys.readouterr().err
  (tmp_path / "empty").mkdir()
  with pytest.raises(SystemExit, match="cannot read .*empty/results.json"):
    tool.main([str(tmp_path / "empty")])
