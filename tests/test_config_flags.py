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
