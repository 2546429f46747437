"""Every config's `model_init` can be set from the command line, as the README's commands do:
ml_collections refuses `--config.model_init=...` on a plain None field, so it must be typed."""

import pathlib

import ml_collections
import pytest

from ufm_jax.training import config_lib

CONFIGS = pathlib.Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", ["ufm560", "ufm980", "ufm560_refine", "ufm980_refine",
                                  "synthetic"])
def test_model_init_is_a_typed_string_field(name):
  config = config_lib.load_config(str(CONFIGS / f"{name}.py"))
  assert config.get_ref("model_init").get_type() is str
  config.model_init = "ckpt:/runs/560"
  assert config.model_init == "ckpt:/runs/560"


REPO = __import__("pathlib").Path(__file__).resolve().parents[1]


def _parse(name, *overrides):
  """The config as train.py's --config flag builds it from the file path, with overrides."""
  from absl import flags
  from ml_collections import config_flags
  argv = ["train.py", f"--config={REPO / 'configs' / name}.py", *overrides]
  fv = flags.FlagValues()
  config_flags.DEFINE_config_file("config", None, flag_values=fv, sys_argv=argv)
  fv(argv)
  return fv.config


@pytest.mark.parametrize("name", ["ufm560", "ufm980", "ufm560_refine", "ufm980_refine",
                                  "synthetic"])
@pytest.mark.parametrize("impl", ["cudnn", "xla"])
def test_model_options_override_from_the_command_line(name, impl):
  from ufm_jax.models import variants
  assert _parse(name).model.attention_impl is None   # auto
  config = _parse(name, f"--config.model.attention_impl={impl}", "--config.model.scan_blocks=False",
                  "--config.model.head_dtype=bfloat16")
  assert config.model.attention_impl == impl
  assert config.model.scan_blocks is False and config.model.head_dtype == "bfloat16"
  # Every key is a field of the variant's config, so it accepts the block (trainer.build_model).
  cfg = variants.get(config.model_name, **config.model.to_dict())
  assert cfg.attention_impl == impl and cfg.scan_blocks is False


@pytest.mark.parametrize("name,scan", [("ufm560", True), ("ufm980", True),
                                       ("ufm560_refine", True), ("synthetic", False)])
def test_training_configs_scan_their_blocks(name, scan):
  assert _parse(name).model.scan_blocks is scan


def _none_leaves(c, prefix=""):
  for k in c.keys():
    v = c[k]
    if isinstance(v, ml_collections.ConfigDict):
      yield from _none_leaves(v, f"{prefix}{k}.")
    elif v is None:
      yield prefix + k


# A source rendered on the fly has no root to set.
_NOT_SETTABLE = {"input.datasets.synthetic.root", "evals.heldout.root"}


@pytest.mark.parametrize("name", ["ufm560", "ufm980", "ufm560_refine", "ufm980_refine",
                                  "synthetic"])
def test_every_none_default_can_be_set_from_the_command_line(name):
  """`--config.total_steps=1000` or `--config.matmul_precision=highest` on a plain None field
  stops train.py at flag parsing; each None default must carry its type."""
  config = _parse(name)
  keys = sorted(set(_none_leaves(config)) - _NOT_SETTABLE)
  assert "matmul_precision" in keys and "optim.no_decay" in keys
  values = {int: "7", float: "0.5", str: "highest"}
  types = {}
  for key in keys:
    parent, _, leaf = key.rpartition(".")
    types[key] = _lookup(config, parent).get_ref(leaf).get_type()
    assert types[key] in values, f"{key}: a None default of type {types[key]}"
  parsed = _parse(name, *(f"--config.{k}={values[types[k]]}" for k in keys))
  for key in keys:
    got = _lookup(parsed, key.rpartition(".")[0])[key.rpartition(".")[2]]
    assert got == types[key](values[types[key]]), key


def _lookup(config, dotted):
  for part in filter(None, dotted.split(".")):
    config = config[part]
  return config


@pytest.mark.parametrize("arg, message", [
    ("stpes=10", "unknown config arg 'stpes'; valid keys: aligned, batch, cov, cov_head, eval, "
                 "loss, lr, max_shift, model, pairs, size, steps, tie"),
    ("cov=maybe", "config arg cov='maybe' is not a bool; valid values: true, false, 1, 0")])
def test_train_py_reports_a_bad_config_arg_in_one_line(arg, message):
  import subprocess
  import sys
  out = subprocess.run([sys.executable, str(REPO / "train.py"),
                        f"--config=configs/synthetic.py:{arg}", "--workdir=/tmp/unused"],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
  assert out.returncode == 2
  assert out.stderr.strip() == f"error: --config=configs/synthetic.py:{arg}: {message}"
  assert out.stdout == ""
