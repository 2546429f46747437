"""Training the refinement recipe's structure (`tiny_refine_recipe`: BatchNorm U-Net, no
uncertainty head): BatchNorm running statistics as train state (outside the optimizer, replicated,
checkpointed, restored on resume, used for evaluation, carried by model_init and the exports),
and every consumer of predictions coping with a model that predicts no covisibility."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

import ufm_jax
from ufm_jax.runtime import checkpoint, model_io, outputs
from ufm_jax.tools import cli, export
from ufm_jax.training import config_lib, model_init, optim
from ufm_jax import testing
from ufm_jax.training import sharding, trainer
from ufm_jax.evaluators import dense, pose
from ufm_jax.models import refine, ufm, variants

REPO = pathlib.Path(__file__).resolve().parents[1]
REFINER = ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias")
SMOKE = f"{REPO}/configs/ufm560_refine.py:model=tiny_refine_recipe,data=synthetic"


def _flat(tree):
  return {"/".join(k): np.asarray(v) for k, v in traverse_util.flatten_dict(tree).items()}


def _counts(stats):
  """{BatchNorm module: num_batches_tracked}."""
  return {k.rsplit("/", 1)[0]: int(v) for k, v in _flat(stats).items()
          if k.endswith("num_batches_tracked")}


# ------------------------------------------------------------------------------ train state


def test_batch_stats_are_state_outside_the_optimizer():
  model = variants.build_model("tiny_refine_recipe")
  v = jax.eval_shape(lambda r: trainer.init_variables(model, (28, 28), r), jax.random.PRNGKey(0))
  assert set(v) == {"params", "batch_stats"}
  assert {k.split("/")[-1] for k in _flat(v["batch_stats"])} == {
      "running_mean", "running_var", "num_batches_tracked"}
  # torch BatchNorm2d's initial state: scale 1, bias 0, running mean 0, running variance 1, no
  # batch seen (the U-Net's BatchNorm, initialised alone).
  bn = refine.BatchNorm().init(jax.random.PRNGKey(0), jnp.ones((1, 4, 4, 3)))
  np.testing.assert_array_equal(bn["params"]["scale"], 1.0)
  np.testing.assert_array_equal(bn["params"]["bias"], 0.0)
  for k, x in _flat(bn["batch_stats"]).items():
    want = {"running_mean": 0.0, "running_var": 1.0, "num_batches_tracked": 0}[k.split("/")[-1]]
    np.testing.assert_array_equal(x, want, err_msg=k)
  # The official groups cover every parameter (no "default" rate needed); the statistics are in
  # no group and get no optimizer state.
  ocfg = config_lib.load_config(SMOKE).optim
  tx, labels, _ = optim.make_optimizer(ocfg, v["params"], 10)
  assert jax.tree_util.tree_structure(labels) == jax.tree_util.tree_structure(v["params"])
  state = jax.eval_shape(lambda x: optim.TrainState.create(x["params"], tx, x["batch_stats"]), v)
  assert isinstance(state, optim.TrainStateWithStats)
  n_opt = sum(x.size for x in jax.tree.leaves(state.opt_state) if x.ndim)
  n_refiner = sum(x.size for k, x in traverse_util.flatten_dict(v["params"]).items()
                  if k[0] in REFINER)
  assert n_opt == 2 * n_refiner
  # A model without BatchNorm keeps the train state (and checkpoint) layout it always had.
  plain = optim.TrainState.create({"w": jnp.zeros(3)}, optim.optax.adam(1e-3))
  assert type(plain) is optim.TrainState and plain.batch_stats is None
  fields = [p[0].name for p, _ in jax.tree_util.tree_flatten_with_path(plain)[0]]
  assert list(dict.fromkeys(fields)) == ["step", "params", "opt_state", "skipped"]
  assert plain.variables() == {"params": plain.params}


def test_batch_stats_are_replicated_whatever_the_rules():
  mesh = jax.sharding.AbstractMesh((1, 8), ("data", "fsdp"))
  tree = {"params": {"w": np.zeros((64, 8))}, "batch_stats": {"u": {"running_mean": np.zeros(64)}}}
  sh = sharding.tree_shardings(tree, mesh, [(".*", "fsdp")])
  assert sh["params"]["w"].spec == jax.sharding.PartitionSpec("fsdp", None)
  assert sh["batch_stats"]["u"]["running_mean"].spec == jax.sharding.PartitionSpec()


@pytest.mark.slow
def test_train_step_updates_stats_and_eval_reads_them():
  """One step of the recipe's train step (tiny model, the smoke config's loss and optimizer):
  the running statistics move by one update per view; evaluation normalises with them (it equals
  apply(train=False), not the batch-statistics forward); a non-finite step keeps them."""
  config = config_lib.load_config(SMOKE + ",steps=4")
  mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
  ts = trainer.setup(config, mesh, (56, 56), 4, dataset_names=("synthetic",))
  state = ts.init_state(0)
  batch = ts.random_batch(mesh, 2, (56, 56), seed=1)
  batch["image1"] = jnp.roll(batch["image0"], 3, axis=2)
  batch["flow"] = jnp.zeros_like(batch["flow"]).at[..., 0].set(3.0)
  before = jax.device_get(state.batch_stats)
  new, metrics = ts.train_step(state, batch)
  assert bool(metrics["update_ok"])
  after = jax.device_get(new.batch_stats)
  assert set(_counts(after).values()) == {2}    # one U-Net call per view
  assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(before),
                                                        jax.tree.leaves(after)))

  model = ts.model
  variables = jax.device_get(new.variables())
  evaluated = jax.device_get(ts.predict(new.variables(), batch))
  assert set(evaluated) == {"flow"}                 # no uncertainty head
  eval_fwd, train_fwd = jax.jit(lambda v, a, b: (
      model.apply(v, a, b), model.apply(v, a, b, train=True, mutable=["batch_stats"])[0]))(
          variables, batch["image0"], batch["image1"])
  np.testing.assert_allclose(evaluated["flow"], np.asarray(eval_fwd["flow"]), atol=1e-4)
  assert not np.allclose(np.asarray(eval_fwd["feature_map_0"]),
                         np.asarray(train_fwd["feature_map_0"]), atol=1e-3)

  # A NaN weight in the U-Net: non-finite loss, the update is skipped, the statistics stay.
  bad = jax.tree_util.tree_map_with_path(
      lambda p, x: x * jnp.nan if optim.path_str(p) == "unet_feature/downs_0/conv_0/kernel" else x,
      new.params)
  kept = jax.device_get(new.batch_stats)
  skipped, m = ts.train_step(new.replace(params=bad), batch)
  assert not bool(m["update_ok"]) and int(skipped.skipped) == 1
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(skipped.batch_stats), kept)


# ------------------------------------------------------------------------------ train.py


def _train(workdir, config, *extra, devices=2):
  env = dict(os.environ, PYTHONPATH=str(REPO), JAX_PLATFORMS="cpu",
             XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
  return subprocess.run([sys.executable, str(REPO / "train.py"), f"--config={config}",
                         f"--workdir={workdir}", *extra],
                        env=env, capture_output=True, text=True, timeout=900, cwd=REPO)


@pytest.mark.slow
def test_recipe_trains_resumes_predicts_and_exports(tmp_path, capsys):
  """configs/ufm560_refine.py's smoke path on `tiny_refine_recipe`, sharded over 2 devices: the
  checkpoints hold the running statistics (2 updates a step, the base frozen), a resumed run
  continues from them, the workdir predicts with them (flow only) and exports flow only."""
  wd = tmp_path / "wd"
  common = ["--config.ckpt_steps=2", "--config.keep_ckpt=5", "--config.mesh=data:1,fsdp:2",
            "--config.sharding_min_size=0"]
  r = _train(wd, SMOKE + ",steps=4", *common)
  assert r.returncode == 0, r.stderr[-3000:]
  s2, _ = checkpoint.read_state_numpy(wd, 2)
  s4, _ = checkpoint.read_state_numpy(wd, 4)
  assert set(_counts(s2["batch_stats"]).values()) == {4}
  assert set(_counts(s4["batch_stats"]).values()) == {8}
  means = {k: v for k, v in _flat(s4["batch_stats"]).items() if k.endswith("running_mean")}
  assert means and all(np.any(v != 0) for v in means.values())
  assert any(not np.array_equal(v, _flat(s2["batch_stats"])[k]) for k, v in means.items())
  p2, p4 = _flat(s2["params"]), _flat(s4["params"])
  for k in p2:
    if k.split("/")[0] not in REFINER:
      np.testing.assert_array_equal(p2[k], p4[k], err_msg=k)   # the frozen base

  # Resume: the statistics continue from step 4's (a fresh start would count 4 at step 6).
  r = _train(wd, SMOKE + ",steps=6", *common)
  assert r.returncode == 0, r.stderr[-3000:]
  assert "resumed from step 4" in r.stdout
  s6, _ = checkpoint.read_state_numpy(wd, 6)
  assert set(_counts(s6["batch_stats"]).values()) == {12}

  # The workdir as a model: its variables carry the statistics; prediction is flow only.
  model, variables = model_io.load_model(wd)
  assert set(variables) == {"params", "batch_stats"}
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(variables["batch_stats"]),
               s6["batch_stats"])
  rng = np.random.default_rng(0)
  src = rng.integers(0, 256, (56, 56, 3), np.uint8)
  pred = ufm_jax.predict(model, variables, src, np.roll(src, 2, axis=1), resolutions=[(56, 56)])
  assert set(pred) == {"flow"} and pred["flow"].shape == (56, 56, 2)
  want = model.apply(variables, src[None], np.roll(src, 2, axis=1)[None])["flow"][0]
  np.testing.assert_allclose(pred["flow"], np.asarray(want), atol=1e-3)

  out = tmp_path / "recipe.stablehlo"
  assert cli.main(["export", "--checkpoint", str(wd), "--size", "56x56", "--out", str(out)]) == 0
  capsys.readouterr()
  side = json.loads(export.sidecar_path(out).read_text())
  assert list(side["outputs"]) == ["flow"]
  got = export.load_exported(out)(src[None], np.roll(src, 2, axis=1)[None])
  np.testing.assert_allclose(np.asarray(got["flow"][0]), np.asarray(want), atol=1e-3)


@pytest.mark.slow
def test_trained_recipe_workdir_round_trips_through_the_official_format(tmp_path, capsys):
  """train.py on the recipe structure at the smallest size the official classes build (the
  smoke config with its model_fn), then `to-official` of the workdir: load_official gives back
  the same parameters and running statistics, hence the same outputs."""
  cfg = tmp_path / "recipe_small.py"
  cfg.write_text(
      "from ufm_jax.training import config_lib\n\n\ndef get_config(arg=None):\n"
      f"  c = config_lib.load_config({SMOKE + ',steps=2'!r})\n"
      "  c.model_fn = 'ufm_jax.testing:official_small_refine_recipe_model'\n"
      "  return c\n")
  wd = tmp_path / "wd"
  r = _train(wd, cfg, devices=1)
  assert r.returncode == 0, r.stderr[-3000:]
  state, step = checkpoint.read_state_numpy(wd)
  assert step == 2 and set(_counts(state["batch_stats"]).values()) == {4}

  assert cli.main(["to-official", str(wd), str(tmp_path / "snap")]) == 0
  capsys.readouterr()
  back_model, back = ufm_jax.load_official(tmp_path / "snap")
  model, variables = model_io.load_workdir(wd)
  assert set(back) == {"params", "batch_stats"}
  assert back_model.config.use_unet_batchnorm and back_model.config.covisibility_head is None
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(back["batch_stats"]),
               state["batch_stats"])
  from ufm_jax.models import scan
  unstacked = scan.unstack_blocks(variables["params"], model.config)
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(back["params"]),
               jax.device_get(unstacked))
  x = np.random.default_rng(1).integers(0, 256, (1, 56, 56, 3), np.uint8)
  y = np.roll(x, 3, axis=2)
  want = model.apply(variables, x, y)["flow"]
  got = back_model.apply(back, x, y)["flow"]
  np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-4)


# ------------------------------------------------------------------------------ model_init


def _zeros(tree):
  return jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), tree)


def _template(model):
  return _zeros({k: v for k, v in ufm.variable_shapes(model).items()})


@pytest.mark.slow
def test_snapshot_init_refuses_another_flow_normalisation(reference_dir):
  """The fixture snapshot's normalisation is (1.5, -2) / (12, 9) px at 120 x 160: a model config
  with the recipe's (std 25 at 224 x 224) is refused before training, naming both values and the
  override; with the snapshot's values it loads."""
  snap = f"snapshot:{reference_dir / 'base'}"
  block = config_lib.load_config(SMOKE).model
  cfg = variants.fixture_small(flow_adaptor={"flow_mean": (0.0, 0.0), "flow_std": (25.0, 25.0),
                                             "base_shape": (224, 224)})
  model = ufm.model_from_config(cfg)
  with pytest.raises(ValueError) as e:
    model_init.load_init_variables(snap, _template(model), cfg, block)
  msg = str(e.value)
  assert "flow_adaptor.flow_std: source (12.0, 9.0), config (25.0, 25.0)" in msg
  assert "--config.model.flow_adaptor.flow_std='(12.0, 9.0)'" in msg
  assert "flow_adaptor.flow_mean: source (1.5, -2.0), config (0.0, 0.0)" in msg
  assert "flow_adaptor.base_shape: source (120, 160), config (224, 224)" in msg
  assert "scale_strategy" not in msg   # equal (scale_both)
  # Not in the training config's model block: where to set it instead of a flag.
  other = variants.fixture_small(info_sharing={"num_heads": 2})
  with pytest.raises(ValueError, match=r"info_sharing.num_heads: source 4, config 2  ->  set "
                                       r"config.model.info_sharing.num_heads = 4"):
    model_init.load_init_variables(snap, _template(ufm.model_from_config(other)), other, block)
  ok = variants.fixture_small()
  out, rep = model_init.load_init_variables(snap, _template(ufm.model_from_config(ok)), ok, block)
  assert rep.left_at_init == [] and rep.unused == [] and set(out) == {"params"}


def test_base_snapshot_into_a_recipe_model_leaves_the_unet_statistics_fresh(reference_dir):
  """A base model's weights into the refinement recipe's structure: no uncertainty head and an
  extra encoder tap are no conflict; the base loads, the refiner and its statistics start fresh,
  the uncertainty head is unused."""
  base = variants.fixture_small(covisibility_head=None)
  cfg = testing._refine(base, unet_features=(8, 16), refine_feature_dim=8,
                        refine_mlp_ratio=2.0, use_unet_batchnorm=True,
                        feature_combine_method="modulate")
  model = ufm.model_from_config(cfg)
  template = _template(model)
  template["batch_stats"] = jax.tree_util.tree_map_with_path(
      lambda p, x: x + 1 if p[-1].key == "running_var" else x, template["batch_stats"])
  out, rep = model_init.load_init_variables(f"snapshot:{reference_dir / 'base'}", template, cfg)
  _, official = ufm_jax.load_official(reference_dir / "base")
  flat, ref = _flat(out["params"]), _flat(official["params"])
  for k in ref:
    if not k.startswith("uncertainty_head"):
      np.testing.assert_array_equal(flat[k], ref[k], err_msg=k)
  assert rep.unused and all(k.startswith("uncertainty_head") for k in rep.unused)
  assert {k.split("/")[0] for k in rep.left_at_init} == set(REFINER) | {"batch_stats"}
  jax.tree.map(np.testing.assert_array_equal, out["batch_stats"], template["batch_stats"])


def _save_workdir(path, model_name, variables, model_block=None):
  tx = optim.optax.adam(1e-3)
  state = optim.TrainState.create(variables["params"], tx, variables.get("batch_stats"))
  mngr = checkpoint.make_manager(path, 1, 1, async_save=False)
  checkpoint.save(mngr, 7, state, None, force=True)
  mngr.wait_until_finished()
  mngr.close()
  (path / "config.json").write_text(json.dumps({"model_name": model_name,
                                                "model": model_block or {}}))


@pytest.mark.slow
def test_ckpt_init_carries_batch_stats_and_checks_the_workdir_config(tmp_path):
  model = variants.build_model("tiny_refine_recipe")
  trained = jax.tree.map(lambda x: x + 41, _template(model))
  _save_workdir(tmp_path / "bn", "tiny_refine_recipe", trained)
  spec = f"ckpt:{tmp_path / 'bn'}"
  out, rep = model_init.load_init_variables(spec, _template(model), model.config)
  assert rep.source.endswith("@7") and rep.left_at_init == [] and rep.unused == []
  assert any(k.startswith("batch_stats/") for k in rep.loaded)
  jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), b), out, trained)

  # Into the same structure without BatchNorm: the statistics are reported unused.
  plain = variants.build_model("tiny_refine_recipe", use_unet_batchnorm=False)
  out, rep = model_init.load_init_variables(spec, _template(plain), None)
  assert set(out) == {"params"}
  stats = sorted(f"batch_stats/{k}" for k in _flat(trained["batch_stats"]))
  assert sorted(k for k in rep.unused if k.startswith("batch_stats/")) == stats

  # A workdir trained with another flow normalisation than the config's: refused.
  tiny = variants.build_model("tiny")
  _save_workdir(tmp_path / "std4", "tiny", _template(tiny),
                {"flow_adaptor": {"flow_std": [4.0, 4.0]}})
  with pytest.raises(ValueError, match=r"flow_adaptor.flow_std: source \(4.0, 4.0\), config "
                                       r"\(8.0, 8.0\)"):
    model_init.load_init_variables(f"ckpt:{tmp_path / 'std4'}", _template(tiny), tiny.config,
                                   {"flow_adaptor": {"flow_std": (8.0, 8.0)}})


# ------------------------------------------------------------------------------ no covisibility


def test_consumers_of_predictions_without_covisibility(tmp_path):
  rng = np.random.default_rng(0)
  h, w = 8, 10
  sample = {"image0": rng.integers(0, 256, (h, w, 3), np.uint8),
            "image1": rng.integers(0, 256, (h, w, 3), np.uint8),
            "flow": np.zeros((h, w, 2), np.float32), "flow_valid": np.ones((h, w), bool),
            "covisibility": np.ones((h, w), bool), "covis_valid": np.ones((h, w), bool)}
  pred = {"flow": np.ones((h, w, 2), np.float32)}
  acc = dense.DenseMetrics(baselines=True)
  acc(sample, pred)
  res = acc.result()
  assert "covis_acc" not in res and res["epe"] == pytest.approx(np.sqrt(2), rel=1e-6)
  acc(sample, dict(pred, covisibility=np.ones((h, w), np.float32)))
  assert acc.result()["covis_acc"] == 1.0

  with pytest.raises(pose.NoCovisibilityError, match="predicts none"):
    meta = {"K0": np.eye(3), "K1": np.eye(3), "cam2world0": np.eye(4), "cam2world1": np.eye(4)}
    pose.PoseMetrics()(dict(sample, meta=meta), pred)

  files = outputs.paths(tmp_path, "p", ("npy", "covis", "panel"))
  written = outputs.write(files, sample["image0"], sample["image1"], pred)
  assert sorted(p.name for p in written) == ["p.flo", "p_flow.npy", "p_panel.png"]
  assert sorted(p.name for p in tmp_path.iterdir()) == ["p.flo", "p_flow.npy", "p_panel.png"]

  from ufm_jax.tools import matching
  with pytest.raises(ValueError, match="predicts none"):
    matching.matches_from_dense(pred["flow"], None)

  assert export.resolve_outputs(None, {"flow": 0}) == ("flow",)
  assert export.resolve_outputs(None, {"flow": 0, "covisibility": 0}) == export.DEFAULT_OUTPUTS
  assert export.resolve_outputs(["flow", "residual"], {}) == ("flow", "residual")
