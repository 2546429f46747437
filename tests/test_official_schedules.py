"""Optimizer groups and learning rates against the official training code (fixtures in
UFM_TRAINING_FIXTURES, `schedules/`): for every run that `schedules.json` lists, the same
parameter groups train (in the official optimizer order) and the same are frozen, every group's
learning rate at every optimizer step is within 1e-7 relative of the official one, and the recipe
config of the run carries the official optimisation settings.
"""

import json
import pathlib
import re

import jax
import ml_collections
import numpy as np
import pytest

from ufm_jax import testing
from ufm_jax.training import config_lib, optim
from ufm_jax.models import ufm, variants

pytestmark = pytest.mark.official_training

REPO = pathlib.Path(__file__).resolve().parents[1]
# Official recipe -> our config file.
CONFIGS = {"ufm_560": "configs/ufm560.py", "ufm_980": "configs/ufm980.py",
           "refine_560": "configs/ufm560_refine.py", "refine_980": "configs/ufm980_refine.py"}


def _discover():
  path = testing.training_fixtures_root() / "schedules" / "schedules.json"
  try:
    runs = json.loads(path.read_text())["recipes"]
  except OSError:
    return [pytest.param(None, id="fixtures-missing")]
  return [pytest.param(r, id=r) for r in runs]


def _run(name):
  folder = testing.training_fixtures("schedules")
  run = json.loads((folder / "schedules.json").read_text())["recipes"][name]
  return run, np.load(folder / "schedules.npz")


def _official_module(top: str) -> str:
  """Our top-level parameter name -> the official module attribute (`head1_0_1` -> `head1`:
  indices of nn.Sequential children are joined with '_' by the key map)."""
  return re.sub(r"(_\d+)+$", "", top)


def _optim_config(run):
  c = config_lib.load_config(str(REPO / CONFIGS[run["recipe"]]))
  return c.optim


@pytest.mark.parametrize("name", _discover())
def test_groups_and_lr_every_step(name):
  run, z = _run(name)
  sched = run["scheduler"]
  assert sched["function"].endswith("get_cosine_with_min_lr_schedule_with_warmup")
  assert sched["interval"] == "step" and sched["num_cycles"] == 0.5
  ocfg = ml_collections.ConfigDict(dict(_optim_config(run)))
  ocfg.lr = dict(run["learning_rate_config"])
  ocfg.warmup_epochs = sched["warmup_epochs"]
  ocfg.min_lr_rate = sched["min_lr_rate"]
  # The refinement recipe's structure (BatchNorm U-Net, no uncertainty head: the LR key of that
  # group is ignored, as the official does); its BatchNorm statistics are no parameters.
  model_name = "tiny_refine_recipe" if "Refinement" in run["model_class"] else "tiny"
  params = ufm.param_shapes(variants.build_model(model_name))
  trained = [g["name"] for g in run["param_groups_in_optimizer_order"]]
  frozen = set(run["frozen_groups_lr0_requires_grad_false"])
  steps_per_epoch = sched["dataloader_len"] // sched["accumulate_grad_batches"]
  assert steps_per_epoch == sched["iteration_per_epoch"]
  total = sched["num_epochs"] * steps_per_epoch
  assert total == sched["num_training_steps"]
  _, labels, schedules = optim.make_optimizer(ocfg, params, total, steps_per_epoch=steps_per_epoch)

  # Membership: every official module lands in its official group, the frozen groups' params
  # are frozen, and exactly the official groups train.
  official = {p.split(".")[0]: g["name"] for g in run["param_groups_in_optimizer_order"]
              for p in g["param_names_of_placeholder_model"]}
  ours = {}
  for path, label in jax.tree_util.tree_flatten_with_path(labels)[0]:
    ours.setdefault(_official_module(optim.path_str(path).split("/")[0]), set()).add(label)
  for module, group in official.items():
    assert ours.get(module) == {group}, (module, ours.get(module), group)
  before = optim.param_labels(params, ocfg.groups)
  for (path, g), label in zip(jax.tree_util.tree_flatten_with_path(before)[0],
                              jax.tree.leaves(labels)):
    assert (label == optim.FROZEN) == (g in frozen), (optim.path_str(path), g, label)
  assert set().union(*ours.values()) - {optim.FROZEN} == set(trained)
  assert sorted(schedules) == sorted(trained)

  # Learning rate of every group at every optimizer step (row k = step k's update).
  table = z[f"{name}_lr"]
  assert table.shape == (run["num_lr_rows"], len(trained))
  for j, g in enumerate(trained):
    ref = table[:, j]
    got = np.asarray(jax.jit(lambda k, s=schedules[g]: s(k))(np.arange(len(ref))), np.float64)
    assert got[0] == ref[0] == 0.0
    rel = np.abs(got[1:] - ref[1:]) / ref[1:]
    assert rel.max() <= 1e-7, (g, int(rel.argmax()) + 1, rel.max())
    host = np.array([schedules[g](k) for k in range(len(ref))])
    np.testing.assert_allclose(host, ref, rtol=1e-12, atol=0)


@pytest.mark.parametrize("name", _discover())
def test_recipe_config_has_the_official_optimisation(name):
  run, _ = _run(name)
  c = config_lib.load_config(str(REPO / CONFIGS[run["recipe"]]))
  o = c.optim
  sched = run["scheduler"]
  assert (o.b1, o.b2) == tuple(run["betas"]) and o.eps == run["optimizer_defaults"]["eps"]
  assert o.weight_decay == run["weight_decay"] and o.no_decay is None
  assert run["gradient_clip"] == {"algorithm": "norm", "value": o.grad_clip_norm}
  assert o.warmup_epochs == sched["warmup_epochs"] and o.min_lr_rate == sched["min_lr_rate"]
  assert o.fractional_warmup and c.num_epochs == sched["num_epochs"]
  lrs = dict(o.lr)
  groups = [g["name"] for g in run["param_groups_in_optimizer_order"]]
  groups += run["frozen_groups_lr0_requires_grad_false"]
  for g in groups:   # learning-rate keys of groups the official model lacks are ignored there
    assert lrs[g] == run["learning_rate_config"][g], (g, lrs[g])
  # Symmetrized batches: the official effective_batch_size counts unique pairs.
  assert run["symmetrize_inputs"] and c.input.symmetrize
  assert c.input.batch_size == 2 * run["effective_batch_size"]
