"""Sharding rules and mesh parsing (pure logic; the multi-device runs are in test_train_mesh.py)."""

import json

import jax
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

from ufm_jax.training import sharding


def test_fsdp_picks_largest_divisible_dim():
  assert sharding._fsdp_spec((1024, 4096), 8) == P(None, "fsdp")
  assert sharding._fsdp_spec((4096, 1000), 8) == P("fsdp", None)
  assert sharding._fsdp_spec((1001, 6), 8) == P()          # nothing divisible: replicate
  assert sharding._fsdp_spec((3, 3, 64, 16), 4) == P(None, None, "fsdp", None)
  assert sharding._fsdp_spec((1, 1370, 1024), 4) == P(None, None, "fsdp")  # 1370 % 4 != 0
  assert sharding._fsdp_spec((1024,), 1) == P()


def test_parse_mesh_and_errors():
  assert sharding.parse_mesh("data:-1,fsdp:2") == [("data", -1), ("fsdp", 2)]
  assert sharding.parse_mesh([("data", 2), ("fsdp", 1)]) == [("data", 2), ("fsdp", 1)]
  with pytest.raises(ValueError, match="axis:size"):
    sharding.parse_mesh("data=2")
  with pytest.raises(ValueError, match="must name the axes"):
    sharding.make_mesh("data:-1")
  with pytest.raises(ValueError, match="at most one axis"):
    sharding.make_mesh("data:-1,fsdp:-1")
  mesh = sharding.make_mesh("data:-1,fsdp:1")
  assert dict(mesh.shape) == {"data": jax.device_count(), "fsdp": 1}


def test_rules_first_match_and_explicit_specs():
  mesh = sharding.make_mesh("data:-1,fsdp:1")
  tree = {"encoder": {"pos_embed": np.zeros((1, 5, 4))}, "head": {"kernel": np.zeros((4, 2))},
          "step": np.zeros(())}
  rules = [(r"pos_embed$", "replicate"), (r"^head/", (None, "fsdp")), (r".*", "fsdp")]
  sh = sharding.tree_shardings(tree, mesh, rules)
  assert sh["encoder"]["pos_embed"].spec == P()
  assert sh["head"]["kernel"].spec == P(None, "fsdp")
  assert sh["step"].spec == P()
  with pytest.raises(ValueError, match="has 1 entries but param head/kernel"):
    sharding.tree_shardings(tree, mesh, [(r"^head/", ("fsdp",))])


def test_local_batch_size_checks_divisibility():
  mesh = sharding.make_mesh("data:-1,fsdp:1")
  assert sharding.local_batch_size(4 * jax.device_count(), mesh) == 4 * jax.device_count()
  if jax.device_count() > 1:
    with pytest.raises(ValueError, match="divisible by the data\\*fsdp"):
      sharding.local_batch_size(jax.device_count() + 1, mesh)


class _Counter:
  """A checkpointable iterator of numbered batches (state = next index)."""

  def __init__(self, n=10):
    self.i, self.n = 0, n

  def __next__(self):
    if self.i >= self.n:
      raise StopIteration
    self.i += 1
    return {"x": np.full((2, 3), self.i - 1, np.float32)}

  def get_state(self):
    return {"i": self.i}

  def set_state(self, state):
    self.i = state["i"]


def test_device_prefetch_state_is_the_last_returned_batch():
  mesh = sharding.make_mesh("data:-1,fsdp:1")
  inner = _Counter()
  it = sharding.DevicePrefetch(inner, mesh, depth=3)
  got = [int(np.asarray(next(it)["x"])[0, 0]) for _ in range(4)]
  assert got == [0, 1, 2, 3] and inner.i == 6  # three batches read ahead
  state = it.get_state()
  assert json.loads(state) == {"i": 4}
  fresh = sharding.DevicePrefetch(_Counter(), mesh, depth=3)
  fresh.set_state(state)
  assert [int(np.asarray(b["x"])[0, 0]) for b in fresh] == [4, 5, 6, 7, 8, 9]


def test_fsdp_never_shards_the_layer_axis_of_a_scanned_stack():
  mesh = jax.sharding.AbstractMesh((1, 8), ("data", "fsdp"))
  rules = [(".*", "fsdp")]
  shape = (24, 16, 8)   # 24 layers: the largest dimension, and divisible by 8
  assert sharding.spec_for("encoder/blocks_3/mlp/fc1/kernel", shape, rules, mesh) == P("fsdp", None, None)
  for path in ("encoder/blocks/mlp/fc1/kernel", "info_sharing/self_attention_blocks/attn/qkv/bias",
               "opt_state/0/mu/encoder/blocks/mlp/fc1/kernel"):
    assert sharding.spec_for(path, shape, rules, mesh) == P(None, "fsdp", None), path


def test_layer_gather_refuses_a_rule_sharding_the_layer_axis():
  assert sharding.layer_gather(jax.sharding.AbstractMesh((1, 1), ("data", "fsdp")), []) is None
  mesh = jax.sharding.AbstractMesh((1, 4), ("data", "fsdp"))
  hook = sharding.layer_gather(mesh, [(r"blocks/", ("fsdp", None))])
  with pytest.raises(ValueError, match="encoder/blocks/w .*layer axis"):
    hook("encoder/blocks", {"w": np.zeros((4, 4))})
