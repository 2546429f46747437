"""Every config's `model_init` can be set from the command line, as the README's commands do:
ml_collections refuses `--config.model_init=...` on a plain None field, so it must be typed."""

import pathlib

import pytest

from ufm_jax import config_lib

CONFIGS = pathlib.Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", ["ufm560", "ufm980", "ufm560_refine", "synthetic"])
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


@pytest.mark.parametrize("name", ["ufm560", "ufm980", "ufm560_refine", "synthetic"])
@pytest.mark.parametrize("impl", ["cudnn", "xla"])
def test_model_options_override_from_the_command_line(name, impl):
  from ufm_jax.models import ufm
  assert _parse(name).model.attention_impl is None   # auto
  config = _parse(name, f"--config.model.attention_impl={impl}", "--config.model.scan_blocks=False",
                  "--config.model.head_dtype=bfloat16")
  assert config.model.attention_impl == impl
  assert config.model.scan_blocks is False and config.model.head_dtype == "bfloat16"
  # Every key is a UFMConfig field, so the variant accepts the block (train.build_model).
  cfg = ufm.UFMConfig().replace(**config.model.to_dict())
  assert cfg.attention_impl == impl and cfg.scan_blocks is False


@pytest.mark.parametrize("name,scan", [("ufm560", True), ("ufm980", True),
                                       ("ufm560_refine", True), ("synthetic", False)])
def test_training_configs_scan_their_blocks(name, scan):
  assert _parse(name).model.scan_blocks is scan
