import pytest

from ufm_jax import data


def test_unknown_dataset_lists_known_names():
  with pytest.raises(KeyError, match="unknown dataset 'nope'"):
    data.get_source("nope", "/tmp")
