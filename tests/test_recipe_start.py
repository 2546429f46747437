"""Where the 980 and refine recipes start: `model_init=snapshot:infinity1096/UFM-Base` (a Hub ID or a
folder), as the official scripts' `resume_model` (megatraining_980.sh:41,
megatraining_refinement_560.sh:46, megatraining_refinement_980.sh:47). The official resume loads
the snapshot's weights and buffers (its flow_mean / flow_std) into the model its YAML builds
(base_shape, scale_strategy stay the YAML's): `model_init_flow_adaptor="buffers"`.

The snapshot is a random one in the structure of the released UFM-Base (UniFlowMatchConfidence,
`testing.random_snapshot`), narrow enough for CPU; each recipe config is run as train.py runs it
(adopt_flow_adaptor before the config is written, build the model, load_init_variables), with the
recipe's model swapped for the same structure at that width."""

import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest

import ufm_jax
from ufm_jax import testing
from ufm_jax.training import config_lib, model_init, trainer
from ufm_jax.models import dinov2, dpt, scan, ufm

REPO = pathlib.Path(__file__).resolve().parents[1]
MEAN, STD = (0.5, -0.25), (12.0, 9.0)
RECIPES = {"ufm980": "ufm_jax.testing:official_small_model",
           "ufm560_refine": "ufm_jax.testing:official_small_refine_recipe_model",
           "ufm980_refine": "ufm_jax.testing:official_small_refine_recipe_model"}
REFINER = ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias")


def _base_config():
  """UFM-Base's structure at test width: the encoder depth of the small refine recipe (its
  refiner taps block 0, the fusion block 1), a flow normalisation unlike the recipes'."""
  return testing.official_small_config(
      encoder=dinov2.dinov2_config("small", depth=2, indices=(1,)),
      flow_adaptor=dpt.FlowAdaptorConfig(MEAN, STD, (420, 560), "scale_both"))


@pytest.fixture(scope="module")
def snapshot(tmp_path_factory):
  return testing.random_snapshot(tmp_path_factory.mktemp("ufm_base") / "snap", _base_config())


def _recipe(name, spec):
  config = config_lib.load_config(str(REPO / "configs" / f"{name}.py"))
  config.model_fn = RECIPES[name]
  if name == "ufm980":
    config.model.encoder = {"depth": 2, "indices": (1,)}
  config.model.dtype = "float32"
  config.model_init = spec
  return config


def _zeros(model):
  return jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), ufm.variable_shapes(model))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(RECIPES))
def test_recipes_start_from_a_ufm_base_snapshot(name, snapshot):
  config = _recipe(name, f"snapshot:{snapshot}")
  assert config.model_init_flow_adaptor == "buffers"
  recipe_shape = tuple(config.model.flow_adaptor.base_shape)
  changes = model_init.adopt_flow_adaptor(config)
  assert len(changes) == 2 and all("as the official resume_model loads them" in c
                                   for c in changes)
  model = trainer.build_model(config)
  fa = model.config.flow_adaptor
  assert (fa.flow_mean, fa.flow_std) == (MEAN, STD)
  assert (fa.base_shape, fa.scale_strategy) == (recipe_shape, "scale_both") != ((420, 560),)
  out, rep = model_init.load_init_variables(config.model_init, _zeros(model), model.config,
                                            config.model, flow_adaptor="buffers")
  _, want = ufm_jax.load_official(snapshot)
  want = scan.to_layout(ufm.variables(want)["params"], model.config)   # the recipes scan blocks
  flat, ref = model_init.flatten(out["params"]), model_init.flatten(want)
  refine = name.endswith("refine")
  for k, v in ref.items():
    if refine and k.startswith("uncertainty_head"):
      assert k in rep.unused   # the recipe's refinement model has no uncertainty head
      continue
    np.testing.assert_array_equal(flat[k], v, err_msg=k)
  left = {k.split("/")[0] for k in rep.left_at_init}
  assert left == (set(REFINER) | {"batch_stats"} if refine else set())
  # The old rule refuses the same start, naming the buffers the official code takes over.
  config = _recipe(name, f"snapshot:{snapshot}")
  with pytest.raises(ValueError, match=r"flow_adaptor.flow_std: source \(12.0, 9.0\), config "
                                       r"\(25.0, 25.0\)"):
    model_init.load_init_variables(config.model_init, _zeros(model), trainer.build_model(
        config).config, config.model, flow_adaptor="check")


COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.mark.slow
def test_a_hub_id_starts_the_refine_recipe_offline(snapshot, tmp_path):
  """`snapshot:infinity1096/UFM-Base` read from huggingface_hub's standard cache (offline), as is
  and at a revision (`@COMMIT`); the report names the commit, and an unknown revision is refused
  with its name."""
  testing.hub_cache(tmp_path / "hub", "infinity1096/UFM-Base", snapshot, COMMIT)
  script = f"""
import jax, numpy as np
from ufm_jax.training import config_lib, model_init, trainer
from ufm_jax.models import ufm
config = config_lib.load_config({str(REPO / "configs" / "ufm560_refine.py")!r})
config.model_fn = {RECIPES["ufm560_refine"]!r}
config.model.dtype = "float32"
config.model_init = "snapshot:infinity1096/UFM-Base"
assert len(model_init.adopt_flow_adaptor(config)) == 2
model = trainer.build_model(config)
fa = model.config.flow_adaptor
assert (fa.flow_mean, fa.flow_std) == ({MEAN!r}, {STD!r}), fa
zeros = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), ufm.variable_shapes(model))
out, rep = model_init.load_init_variables(config.model_init, zeros, model.config, config.model,
                                          flow_adaptor="buffers")
commit = {COMMIT!r}
assert rep.loaded and rep.source == f"snapshot:infinity1096/UFM-Base (commit {{commit}})", rep.source
# A revision: the commit itself, and one the cache does not hold (refused, naming it)
out2, rep = model_init.load_init_variables(f"{{config.model_init}}@{{commit}}", zeros,
                                           model.config, config.model, flow_adaptor="buffers")
assert rep.source == f"snapshot:infinity1096/UFM-Base@{{commit}}", rep.source
assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out2)))
try:
  model_init.load_init_variables(config.model_init + "@v9.9", zeros, model.config, config.model,
                                 flow_adaptor="buffers")
  raise SystemExit("an unknown revision was not refused")
except FileNotFoundError as e:
  assert "revision v9.9" in str(e), e
print("ok")
"""
  r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600,
                     env=dict(os.environ, JAX_PLATFORMS="cpu", HF_HUB_CACHE=str(tmp_path / "hub"),
                              HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO)))
  assert r.returncode == 0 and "ok" in r.stdout, r.stderr[-3000:]
