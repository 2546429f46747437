import typing

import pytest

from ufm_jax import data
from ufm_jax.data import registry


def test_unknown_dataset_lists_known_names():
  with pytest.raises(KeyError, match="unknown dataset 'nope'"):
    data.get_source("nope", "/tmp")


# Paper Table 1 above the dashed line plus the static benchmark scenes; the sources that label
# backward pairs themselves (scene flow, Spring's BW files, Kubric's rigid objects, pair folders
# with reverse/, the generator).
# The readers of the official processed layouts (#30): the static DUSt3R-style sets, and the flow
# sets whose files store both directions' labels (TA-WB shards, HD1K's empty backward view).
STATIC = {"blendedmvs", "megadepth", "tartanair_v2", "scannetpp", "habitat", "staticthings",
          "dtu", "eth3d", "tawb", "scannet1500", "blendedmvs_official", "megadepth_official",
          "scannetpp_official", "habitat_official", "staticthings_official"}
WITH_BACKWARD = {"flyingthings", "monkaa", "spring", "kubric4d", "pairs_folder", "synthetic",
                 "flyingthings_official", "monkaa_official", "spring_official", "hd1k_official",
                 "tartanair_assembled", "kubric4d_official", "flyingchairs"}


def test_every_source_class_declares_backward_labels_and_static_scenes():
  names = [n for n in data.available() if not n.startswith("_")]   # "_...": test-only fakes
  classes = {}
  for n in names:
    factory = registry._REGISTRY[n]   # a source class, or a function annotated with the one it builds
    classes[n] = factory if isinstance(factory, type) else typing.get_type_hints(factory)["return"]
  for n, c in classes.items():
    assert isinstance(getattr(c, "has_backward", None), bool), n
    assert isinstance(getattr(c, "static_scene", None), bool), n
    if c.has_backward:
      assert callable(getattr(c, "both", None)) and callable(getattr(c, "backward", None)), n
  assert {n for n, c in classes.items() if c.static_scene} == STATIC
  assert {n for n, c in classes.items() if c.has_backward} == WITH_BACKWARD
