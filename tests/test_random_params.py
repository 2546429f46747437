"""trainer.random_params: the compiler options follow the model's size; both give the same init."""

import functools

import jax
import numpy as np
import pytest

from ufm_jax.training import optim, trainer
from ufm_jax.models import variants


def test_small_models_skip_backend_optimisations_and_full_size_keeps_them():
  def count(name):
    init = functools.partial(trainer.init_params, variants.build_model(name), (28, 28))
    return optim.count_params(jax.eval_shape(init, jax.random.PRNGKey(0)))["total"]
  assert trainer.init_compiler_options(count("tiny")) == trainer._INIT_COMPILER_OPTIONS
  assert trainer.init_compiler_options(count("ufm_base")) == {}


@pytest.mark.slow
def test_random_params_equal_with_and_without_backend_optimisations():
  model = variants.build_model("tiny")
  key = jax.random.PRNGKey(3)
  got = trainer.random_params(model, seed=3)
  lowered = jax.jit(functools.partial(trainer.init_params, model, (28, 28))).lower(key)
  optimised = lowered.compile()(key)
  assert jax.tree.structure(got) == jax.tree.structure(optimised)
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(optimised)):
    assert a.shape == b.shape and a.dtype == b.dtype
    # The generators' bits are equal; float transforms may round differently in the last place.
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
