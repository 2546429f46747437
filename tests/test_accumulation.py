"""Gradient accumulation (config.grad_accum): which rows each microbatch takes, that the
accumulated step is the update of the mean of the microbatch losses (the official DDP runs'
loss over that many replicas), BatchNorm's running statistics, the refusals, and that on a mesh
the split moves no rows between devices."""

import json
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.planning import hlo_stats
from ufm_jax.training import accumulation, config_lib, sharding, trainer

REPO = pathlib.Path(__file__).resolve().parents[1]
SYNTH = f"{REPO}/configs/synthetic.py:model=tiny,steps=4,loss=paper"
REFINE = f"{REPO}/configs/ufm560_refine.py:model=tiny_refine_recipe,data=synthetic,steps=4"


def test_microbatches_take_every_kth_pair():
  rows = np.arange(12)
  batch = {"flow": jnp.asarray(rows, jnp.float32)[:, None] * jnp.ones((12, 3)),
           "dataset_id": jnp.asarray(rows)}
  out = accumulation.microbatches(batch, 3)
  assert out["flow"].shape == (3, 4, 3)
  # pairs (0,1) (2,3) (4,5) (6,7) (8,9) (10,11): microbatch j takes pairs j and j + 3
  np.testing.assert_array_equal(out["dataset_id"], [[0, 1, 6, 7], [2, 3, 8, 9], [4, 5, 10, 11]])
  np.testing.assert_array_equal(out["flow"][:, :, 0], out["dataset_id"])
  single = accumulation.microbatches({"x": jnp.arange(6)}, 3, pair_rows=1)
  np.testing.assert_array_equal(single["x"], [[0, 3], [1, 4], [2, 5]])


def test_refuses_batches_that_do_not_split():
  # 6 rows per device: 2 microbatches would split a pair
  with pytest.raises(ValueError, match=r"grad_accum=2: the batch of 24 rows \(6 per device over "
                                       r"4 batch shards\).*multiple of 16"):
    accumulation.check_divisible(24, 2, 4)
  accumulation.check_divisible(24, 3, 4)
  accumulation.check_divisible(48, 3, 4)
  accumulation.check_divisible(7, 1, 4)    # no accumulation: nothing to check here
  with pytest.raises(ValueError, match="leading"):
    accumulation.microbatches({"a": jnp.zeros((4, 2)), "b": jnp.zeros((6,))}, 2)
  config = config_lib.load_config(SYNTH)
  config.grad_accum = 0
  mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
  with pytest.raises(ValueError, match="grad_accum=0"):
    trainer.setup(config, mesh, (56, 56), 4)


def _setup(spec, grad_accum=1, groups=1):
  config = config_lib.load_config(spec)
  config.grad_accum = grad_accum
  config.loss.groups = groups
  mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
  return mesh, trainer.setup(config, mesh, (56, 56), 4, dataset_names=("synthetic",))


@pytest.mark.slow
def test_accumulated_step_is_the_update_of_the_mean_microbatch_loss():
  """grad_accum=2 on a batch == one step whose loss is the mean of two per-group losses
  (loss.groups=2, consecutive row blocks) on the same rows reordered so that block j holds
  microbatch j: the same update, the same loss."""
  mesh, acc = _setup(SYNTH, grad_accum=2)
  _, ref = _setup(SYNTH, groups=2)
  _, pooled = _setup(SYNTH)
  state = acc.init_state(0)
  batch = acc.random_batch(mesh, 8, (56, 56), seed=3)
  batch["image1"] = jnp.roll(batch["image0"], 2, axis=1)
  # so that the mean over the pooled batch differs from the mean of the microbatches' means,
  # microbatch 0 (rows 0, 1, 4, 5): larger flow, and fewer supervised pixels
  batch["flow"] = batch["flow"].at[np.array([0, 1, 4, 5])].multiply(10.0)
  batch["covisibility"] = batch["covisibility"].at[0:2, :50].set(False)
  order = np.array([0, 1, 4, 5, 2, 3, 6, 7])    # pairs 0, 2 | pairs 1, 3
  reordered = {k: v[order] for k, v in batch.items()}

  new, m = acc.train_step(jax.tree.map(jnp.copy, state), batch)
  want, m_ref = ref.train_step(jax.tree.map(jnp.copy, state), reordered)
  _, m_pooled = pooled.train_step(jax.tree.map(jnp.copy, state), batch)
  assert bool(m["update_ok"])
  np.testing.assert_allclose(float(m["loss"]), float(m_ref["loss"]), rtol=1e-5)
  np.testing.assert_allclose(float(m["grad_norm"]), float(m_ref["grad_norm"]), rtol=1e-4)
  # Adam's moments hold the gradient itself (its first step's update is ~lr x sign(g), which
  # says little about g).
  moments = [(a, b) for a, b in zip(jax.tree.leaves(new.opt_state), jax.tree.leaves(want.opt_state))
             if np.ndim(a) and np.issubdtype(np.asarray(a).dtype, np.floating)]
  assert moments and any(np.abs(np.asarray(b)).max() > 0 for _, b in moments)
  for a, b in moments:
    b = np.asarray(b)
    np.testing.assert_allclose(np.asarray(a), b, rtol=1e-4, atol=1e-5 * np.abs(b).max())
  for a, b in zip(jax.tree.leaves(new.params), jax.tree.leaves(want.params)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)
  # ...and it is not the loss pooled over the whole batch
  assert abs(float(m["loss"]) - float(m_pooled["loss"])) > 1e-4 * abs(float(m_pooled["loss"]))


@pytest.mark.slow
def test_batch_norm_statistics_move_once_by_the_microbatch_mean():
  """The refinement recipe's BatchNorm: each microbatch normalises with its own statistics (a
  DDP replica's), and the running statistics take one momentum step towards their mean."""
  mesh, acc = _setup(REFINE, grad_accum=2)
  _, one = _setup(REFINE)
  state = acc.init_state(0)
  batch = acc.random_batch(mesh, 4, (56, 56), seed=1)
  new, m = acc.train_step(jax.tree.map(jnp.copy, state), batch)
  assert bool(m["update_ok"])
  singles = [jax.device_get(one.train_step(jax.tree.map(jnp.copy, state),
                                           {k: v[np.array(rows)] for k, v in batch.items()})[0].batch_stats)
             for rows in ([0, 1], [2, 3])]
  got = jax.device_get(new.batch_stats)
  leaves = zip(jax.tree_util.tree_leaves_with_path(got), *map(jax.tree.leaves, singles))
  for (path, x), a, b in leaves:
    name = jax.tree_util.keystr(path)
    if name.endswith("['num_batches_tracked']"):
      assert int(x) == int(a) == 2, name   # one update per view, not per microbatch
    else:
      np.testing.assert_allclose(x, (a + b) / 2, rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.slow
def test_split_moves_no_rows_between_devices(tmp_path):
  """On 8 fake devices (data:2, fsdp:4) the accumulated step compiles, activation memory is
  that of a microbatch, and no collective carries rows of the batch or of a microbatch."""
  # 20 rows per device: two microbatches of five pairs; no parameter has a dimension of 160,
  # 320 (encoder rows), 80 (pairs, or a microbatch's rows) or 40 (a microbatch's pairs)
  batch = 160
  results = {}
  for k in (1, 2):
    hlo = tmp_path / f"step{k}.hlo.txt"
    cmd = [sys.executable, str(REPO / "benchmarks" / "train_step.py"), "--config", "synthetic",
           "--model", "tiny", "--mesh", "data:2,fsdp:4", "--devices", "8", "--batch", str(batch),
           "--size", "56x56", "--aot", "--grad_accum", str(k), "--hlo_out", str(hlo)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=REPO)
    assert out.returncode == 0, out.stderr[-3000:]
    results[k] = json.loads(out.stdout.strip().splitlines()[-1])
    colls = hlo_stats.collectives(hlo.read_text())
    assert {c.kind for c in colls} <= {"all-gather", "all-reduce", "reduce-scatter"}, (
        k, {c.kind for c in colls})
    row_dims = {batch, 2 * batch, batch // 2, batch // 4}
    for c in colls:
      for dtype, dims in c.shapes:
        assert not (dims and dims[0] in row_dims), f"k={k}: {c.kind} of {dtype}{list(dims)}"
  # activations of a half batch; a gradient sum and a microbatch's reduction in the loop
  assert results[2]["temp_bytes_per_device"] < 0.75 * results[1]["temp_bytes_per_device"], results
  params = results[1]["param_bytes"]
  assert results[2]["collective_bytes_total"] <= 2 * 4 * params, results[2]


@pytest.mark.slow
def test_train_py_accumulates_on_a_mesh_as_on_one_device(tmp_path):
  """train.py end to end with --config.grad_accum=2: the (data=4, fsdp=2) run of 8 fake devices
  trains the params of the one-device run (microbatch j is the same rows whatever the mesh), and
  a batch that does not split is refused before the pipeline starts."""
  from ufm_jax import testing
  from ufm_jax.runtime import checkpoint
  from ufm_jax.training import model_init

  def train(workdir, mesh, *extra):
    cmd = [sys.executable, str(REPO / "train.py"),
           f"--config={REPO}/ufm_jax/testing/train_support.py", f"--workdir={workdir}",
           f"--config.mesh={mesh}", "--config.total_steps=2", "--config.ckpt_steps=2",
           "--config.input.batch_size=16", "--config.grad_accum=2", *extra]
    return subprocess.run(cmd, env=testing.fake_devices_env(8), capture_output=True, text=True,
                          timeout=600, cwd=REPO)

  states = {}
  for name, mesh in (("mesh", "data:4,fsdp:2"), ("single", "data:1,fsdp:1")):
    r = train(tmp_path / name, mesh)
    assert r.returncode == 0, r.stderr[-3000:]
    states[name] = model_init.flatten(checkpoint.read_state_numpy(tmp_path / name, 2)[0]["params"])
  assert states["mesh"].keys() == states["single"].keys()
  for k, v in states["mesh"].items():
    np.testing.assert_allclose(v, states["single"][k], rtol=1e-5, atol=1e-6, err_msg=k)
  r = train(tmp_path / "odd", "data:4,fsdp:2", "--config.grad_accum=4")
  assert r.returncode != 0
  assert "grad_accum=4: the batch of 16 rows (2 per device over 8 batch shards)" in r.stderr
