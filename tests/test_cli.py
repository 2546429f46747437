"""`python -m ufm_jax infer|convert`: files written, errors for missing inputs, end to end."""

import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from ufm_jax.runtime import model_io
from ufm_jax.tools import cli
from ufm_jax.data.io import read_flo, read_image, write_image

REPO = pathlib.Path(__file__).resolve().parents[1]


def _run(*args, timeout=600):
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  return subprocess.run([sys.executable, "-m", "ufm_jax", *map(str, args)], capture_output=True,
                        text=True, timeout=timeout, env=env, cwd=REPO)


@pytest.fixture(scope="module")
def io(reference_dir):
  return dict(np.load(reference_dir / "base" / "io.npz"))


@pytest.fixture()
def pair_files(io, tmp_path):
  src, tgt = tmp_path / "src.png", tmp_path / "tgt.png"
  write_image(src, io["hl1_src_uint8"])
  write_image(tgt, io["hl1_tgt_uint8"])
  return src, tgt


class _Replay:
  """Stand-in model replaying the official hl1 forward outputs (shape-checked)."""

  inference_resolution = [(168, 224)]

  def __init__(self, io):
    self.flow = io["hl1_fwd_flow"].transpose(0, 2, 3, 1)
    self.covis = io["hl1_fwd_covisibility_mask"][:, 0]

  def apply(self, variables, source, target):
    b = source.shape[0]
    zero = 0.0 * source.sum()
    return {"flow": np.repeat(self.flow, b, 0) + zero, "covisibility": np.repeat(self.covis, b, 0) + zero}


def test_run_infer_writes_all_files(io, pair_files, tmp_path):
  out = tmp_path / "out"
  written = cli.run_infer(_Replay(io), {}, *pair_files, out, bidirectional=True)
  names = sorted(p.name for p in written)
  for d in ("forward", "backward"):
    for suffix in (".flo", "_flow.npy", "_covisibility.npy", "_covisibility.png", "_panel.png"):
      assert d + suffix in names
  flo = read_flo(out / "forward.flo")
  np.testing.assert_allclose(flo, io["hl1_flow"][0].transpose(1, 2, 0), atol=1e-3)
  np.testing.assert_array_equal(np.load(out / "forward_flow.npy"), flo)
  assert read_flo(out / "backward.flo").shape == io["hl1_tgt_uint8"].shape[:2] + (2,)
  panel = read_image(out / "forward_panel.png")
  assert panel.shape == (200, 4 * 300, 3)
  np.testing.assert_array_equal(panel[:, :300], io["hl1_src_uint8"])
  assert not list(out.glob("*.tmp*"))


def test_missing_inputs_give_clear_errors(pair_files, tmp_path):
  r = _run("infer", tmp_path / "nope.png", pair_files[1], "--checkpoint", tmp_path, "--out", tmp_path / "o")
  assert r.returncode == 2 and "image not found" in r.stderr and "nope.png" in r.stderr
  r = _run("infer", *pair_files, "--checkpoint", tmp_path / "missing", "--out", tmp_path / "o")
  assert r.returncode == 2 and "checkpoint directory not found" in r.stderr
  r = _run("infer", *pair_files, "--checkpoint", tmp_path, "--snapshot", "--out", tmp_path / "o")
  assert r.returncode == 2 and "model.safetensors" in r.stderr
  r = _run("infer", *pair_files)
  assert r.returncode != 0 and "--checkpoint" in r.stderr


@pytest.mark.slow
def test_infer_cli_on_fixture_snapshot(io, reference_dir, pair_files, tmp_path):
  r = _run("infer", *pair_files, "--checkpoint", reference_dir / "base", "--snapshot",
           "--out", tmp_path / "o")
  assert r.returncode == 0, r.stderr
  flo = read_flo(tmp_path / "o" / "forward.flo")
  np.testing.assert_allclose(flo, io["hl1_flow"][0].transpose(1, 2, 0), atol=1e-3)
  covis = np.load(tmp_path / "o" / "forward_covisibility.npy")
  np.testing.assert_allclose(covis, io["hl1_covisibility"][0], atol=5e-5)


@pytest.mark.slow
def test_convert_then_infer_from_converted_checkpoint(io, reference_dir, pair_files, tmp_path, capsys):
  """`convert` writes our checkpoint (ufm_jax.runtime.model_io); `infer --checkpoint` then reads it."""
  ckpt = tmp_path / "ckpt"
  assert cli.main(["convert", str(reference_dir / "base"), str(ckpt)]) == 0
  assert cli.main(["infer", *map(str, pair_files), "--checkpoint", str(ckpt), "--out",
                   str(tmp_path / "o"), "--bidirectional"]) == 0
  printed = capsys.readouterr().out
  assert "backward_panel.png" in printed
  flo = read_flo(tmp_path / "o" / "forward.flo")
  np.testing.assert_allclose(flo, io["hl1_flow"][0].transpose(1, 2, 0), atol=1e-3)


def test_load_train_workdir(tmp_path):
  """A train.py workdir (config.json + orbax steps under checkpoints/) loads its latest step."""
  import json

  import jax

  from ufm_jax.runtime import checkpoint

  from ufm_jax.models import ufm

  from ufm_jax.models import variants
  model = variants.build_model("tiny")
  rng = np.random.default_rng(0)  # shapes by eval_shape (no compile); values arbitrary
  params = jax.tree.map(lambda s: rng.normal(size=s.shape).astype(np.float32), ufm.param_shapes(model))
  manager = checkpoint.make_manager(tmp_path, save_interval_steps=1, keep=2, async_save=False)
  for step in (1, 2):
    state = {"params": jax.tree.map(lambda p: p + step, params), "step": step}
    checkpoint.save(manager, step, state, force=True)
  manager.wait_until_finished()
  (tmp_path / "config.json").write_text(json.dumps({"model_name": "tiny", "model": {}}))
  assert model_io.what_is(tmp_path) == model_io.WORKDIR
  loaded_model, loaded = model_io.load_model(tmp_path)
  assert loaded_model.config == model.config and set(loaded) == {"params"}
  for a, b in zip(jax.tree.leaves(loaded["params"]), jax.tree.leaves(params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b) + 2, rtol=0, atol=1e-6)  # latest step


def test_convert_help_matches_the_readme():
  r = _run("convert", "--help", timeout=120)
  assert r.returncode == 0, r.stderr
  usage = " ".join(r.stdout.split("\n\n")[0].split())
  # docs/inference.md's form: `python -m ufm_jax convert UFM-Base/ ckpt/`.
  assert usage.startswith("usage: python -m ufm_jax convert") and usage.endswith("snapshot_dir out_dir")
  guide = (REPO / "docs" / "inference.md").read_text()
  assert "python -m ufm_jax convert UFM-Base/ ckpt/" in guide


def test_top_level_help_gives_the_whole_first_sentence(capsys):
  with pytest.raises(SystemExit):
    cli.main(["--help"])
  text = " ".join(capsys.readouterr().out.split())
  assert "(also installed as `ufm-jax`)." in text


def test_infer_help_says_checkpoint_takes_a_workdir():
  r = _run("infer", "--help", timeout=120)
  assert r.returncode == 0, r.stderr
  text = " ".join(r.stdout.split())
  help_of_checkpoint = text.split("--checkpoint CHECKPOINT", 2)[2].split(" --", 1)[0]
  assert "train.py workdir" in help_of_checkpoint and "converted checkpoint" in help_of_checkpoint


def test_evaluate_help_states_its_description_once_and_documents_every_flag():
  r = subprocess.run([sys.executable, str(REPO / "evaluate.py"), "--help"], capture_output=True,
                     text=True, timeout=120, cwd=REPO)
  assert r.returncode == 0, r.stderr
  assert r.stdout.count("Evaluates UFM on the paper's benchmarks") == 1, r.stdout
  lines = r.stdout.split("options:", 1)[1].splitlines()
  undocumented = []
  for k, line in enumerate(lines):
    if not line.startswith("  -"):
      continue
    # argparse puts the help after two spaces, or on the next, deeper-indented line.
    same_line = "  " in line.strip()
    next_line = k + 1 < len(lines) and lines[k + 1].startswith(" " * 8) \
        and not lines[k + 1].lstrip().startswith("-")
    if not (same_line or next_line):
      undocumented.append(line.strip())
  assert not undocumented, undocumented


def test_mistyped_config_override_prints_one_hint_and_exits_2(tmp_path):
  r = subprocess.run([sys.executable, str(REPO / "train.py"), "--config=configs/synthetic.py",
                      f"--workdir={tmp_path / 'w'}", "--config.totl_steps=5"],
                     capture_output=True, text=True, timeout=300, cwd=REPO)
  assert r.returncode == 2
  lines = (r.stdout + r.stderr).splitlines()
  assert len(lines) == 1 and 'Did you mean "total_steps"' in lines[0], lines
  assert not (tmp_path / "w").exists()
