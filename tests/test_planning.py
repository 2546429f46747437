"""One program from plan to pod (ufm_jax.planning.planner): `train.py --compile_only` and the planner
(`benchmarks/train_step.py`) compile the same step for the same config and devices, the recipes
default to the sharding the planner sizes, a plan's overrides reproduce it, and train.py's
command line says what it takes."""

import json
import os
import pathlib
import subprocess
import sys
import types

import jax
import pytest

from ufm_jax import testing
from ufm_jax.planning import planner, topologies
from ufm_jax.training import config_lib

REPO = pathlib.Path(__file__).resolve().parents[1]
TINY = REPO / "ufm_jax" / "testing" / "train_support.py"
RECIPES = ("ufm560", "ufm980", "ufm560_refine", "ufm980_refine")


def _last_json(out):
  return json.loads(out.stdout.strip().splitlines()[-1])


def _train_py(*args, env=None, timeout=600):
  return subprocess.run([sys.executable, str(REPO / "train.py"), *args], capture_output=True,
                        text=True, timeout=timeout, cwd=REPO, env=env)


def _planner(*args, env=None, timeout=600):
  return subprocess.run([sys.executable, str(REPO / "benchmarks" / "train_step.py"), *args],
                        capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env)


def _agree(a, b):
  for key in ("chips", "device_kind", "mesh", "grad_accum", "global_batch", "image_shape",
              "param_bytes", "state_bytes_per_device", "hbm_capacity_bytes", "fits"):
    assert a[key] == b[key], key
  assert a["hbm_bytes_per_chip"] == pytest.approx(b["hbm_bytes_per_chip"], rel=0.01)
  assert a["collective_bytes"].keys() == b["collective_bytes"].keys()
  for kind, n in a["collective_bytes"].items():
    assert n == pytest.approx(b["collective_bytes"][kind], rel=0.01), kind
  assert a["flops_per_step"] == pytest.approx(b["flops_per_step"], rel=0.01)


@pytest.mark.slow
def test_compile_only_and_the_planner_agree_on_8_devices():
  """The same config and overrides through both programs on 8 fake CPU devices: the config's
  default mesh (FSDP over all 8), grad_accum 2, the same HBM and collectives."""
  env = testing.fake_devices_env(8)
  a = _train_py(f"--config={TINY}", "--compile_only", "--config.grad_accum=2",
                "--config.input.batch_size=16", env=env)
  assert a.returncode == 0, a.stderr[-3000:]
  b = _planner("--config", str(TINY), "--aot", "--devices", "8", "--grad_accum", "2",
               "--batch", "16", "--host_ms_per_row", "7.5", env=env)
  assert b.returncode == 0, b.stderr[-3000:]
  ra, rb = _last_json(a), _last_json(b)
  _agree(ra, rb)
  assert ra["mesh"] == {"data": 1, "fsdp": 8} and ra["mesh_config"] == "data:1,fsdp:-1"
  assert ra["grad_accum"] == 2 and ra["global_batch"] == 16 and ra["image_shape"] == [14, 14]
  # The train state is sharded: a device holds an eighth of the kernels (and the few biases
  # that do not split over 8).
  assert ra["param_bytes_per_device"] < ra["param_bytes"] / 4
  # 8 CPU devices share the host's RAM (sysconf's count of its pages): an eighth each.
  ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
  assert ra["hbm_capacity_bytes"] == ram // 8 and ra["fits"] is True
  assert ra["collective_link_bytes"].keys() == ra["collective_bytes"].keys()
  assert ra["collective_link_bytes_total"] == sum(ra["collective_link_bytes"].values()) > 0
  # train.py timed the config's own input (its data_fn) for the host feed; the planner was told.
  assert ra["host_feed"]["source"] == "measured" and ra["host_feed"]["host_ms_per_row"] > 0
  assert ra["host_feed"]["load_avg_1m"] >= 0 and ra["host_feed"]["rows"] >= 96
  assert rb["host_feed"]["source"] == "--host_ms_per_row"
  assert rb["host_feed"]["host_ms_per_row"] == 7.5
  for key in ("chips", "device_kind", "hbm_bytes_per_chip", "flops_per_step",
              "collective_bytes", "compile_s"):
    assert key in ra, key


def test_recipes_default_to_the_planned_sharding():
  """Every recipe (and what train.py saves as its config) shards the train state over every chip,
  the sharding docs/scale.md's figures were compiled with; the plan starts at the largest of the
  recipe's own training shapes (the pipeline's rule)."""
  for name in RECIPES:
    config = config_lib.load_config(str(REPO / "configs" / f"{name}.py"))
    assert config.mesh == "data:1,fsdp:-1", name
    assert planner.largest_shape(config) in planner.training_shapes(config)
  c560 = config_lib.load_config(str(REPO / "configs" / "ufm560.py"))
  assert planner.largest_shape(c560) == (420, 560)      # 560_many_non_square_ar: no 560x560
  c980 = config_lib.load_config(str(REPO / "configs" / "ufm980.py"))
  assert planner.largest_shape(c980) == (644, 980)
  assert planner.pairs_per_epoch(c560) == 2 * sum(d.quota for d in c560.input.datasets.values())


def test_capacity_of_the_devices_at_hand():
  """CPU devices share the host's RAM; a GPU's is its allocator's limit where it states one,
  else its chip's HBM; a device that states neither has none known (its plan's "fits" is None)."""
  ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
  assert planner.host_ram_bytes() <= ram
  cpus = [types.SimpleNamespace(platform="cpu", process_index=0) for _ in range(4)]
  cpus.append(types.SimpleNamespace(platform="cpu", process_index=1))   # another host's
  assert planner.device_capacity(cpus) == planner.host_ram_bytes() // 4
  assert planner.capacity_source(cpus) == "host RAM over 4 CPU devices"

  def gpu(stats):
    return types.SimpleNamespace(platform="gpu", process_index=0, memory_stats=lambda: stats)
  h100 = topologies.CHIPS["h100"]
  assert planner.device_capacity([gpu({"bytes_limit": 79 * 2 ** 30})], h100) == 79 * 2 ** 30
  assert planner.device_capacity([gpu(None)], h100) == h100.hbm_bytes
  assert planner.device_capacity([gpu({})], None) is None
  assert planner.capacity_source([gpu({"bytes_limit": 1})]) == "the allocator's bytes_limit"


@pytest.mark.slow
def test_compile_only_exit_codes():
  """train.py --compile_only exits 0 when the step fits, 3 when it does not (here a device of
  --capacity_gib smaller than the tiny step's memory), 1 on an error (a batch of 3 rows in 2
  microbatches)."""
  common = [f"--config={TINY}", "--compile_only", "--config.input.batch_size=2"]
  env = {**os.environ, "JAX_PLATFORMS": "cpu"}
  fits = _train_py(*common, env=env)
  assert fits.returncode == 0, fits.stderr[-3000:]
  r = _last_json(fits)
  assert r["fits"] is True and r["hbm_capacity_bytes"] == planner.host_ram_bytes()
  assert "step_s_estimate" not in r and "days_estimate" not in r   # no step time on a CPU
  assert "no step time" in fits.stdout
  small = _train_py(*common, "--capacity_gib=0.00001", env=env)
  assert small.returncode == 3, small.stderr[-3000:]
  r = _last_json(small)
  assert r["fits"] is False and r["hbm_capacity_bytes"] == int(0.00001 * 2 ** 30)
  assert r["hbm_bytes_per_chip"] > r["hbm_capacity_bytes"]
  assert ": does not fit" in small.stdout
  bad = _train_py(f"--config={TINY}", "--compile_only", "--config.input.batch_size=3",
                  "--config.grad_accum=2", env=env)
  assert bad.returncode == 1 and "does not split" in bad.stderr, bad.stderr[-3000:]


def test_a_step_over_the_chips_hbm_does_not_fit():
  config = config_lib.load_config(str(TINY))
  tgt = planner.target()
  small = planner.Target("tiny chip", tgt.devices[:1], 1, tgt.device_kind, 1024, None, 1,
                          tgt.platform)
  r = planner.plan(config, small, batch=2, flops=False, log=lambda *a, **k: None)
  assert r["fits"] is False and r["hbm_bytes_per_chip"] > 1024


def test_launch_lines_carry_the_overrides():
  result = {"mesh_config": "data:1,fsdp:-1", "global_batch": 96, "grad_accum": 6, "hosts": 2}
  lines = planner.launch_lines(result, "configs/ufm560.py")
  flags = "--config.mesh=data:1,fsdp:-1 --config.input.batch_size=96 --config.grad_accum=6"
  assert lines[0] == f"python train.py --config=configs/ufm560.py --workdir=DIR {flags}"
  assert lines[1].startswith("sbatch --nodes=2 launch/slurm/train.sbatch configs/ufm560.py DIR")
  assert lines[1].endswith(flags)
  assert "MESH=data:1,fsdp:-1 GLOBAL_BATCH=96 GRAD_ACCUM=6" in lines[2]


def test_host_feed():
  """Rows per second per host from the step time, times the host's ms per row, as cores."""
  config = config_lib.load_config(str(REPO / "configs" / "ufm560.py"))
  tgt = planner.target("v5e-64", compile=False)
  shapes = planner.training_shapes(config)
  per_row = {s: 1e12 for s in shapes}
  est = planner.estimate(config, tgt, per_row, shapes[0], 128, 0.5, 10.0)
  step_s = 1e12 * 128 / (64 * 197e12 * 0.5)
  assert est["step_s_estimate"] == pytest.approx(step_s)
  assert est["hosts"] == 16
  assert est["rows_per_s_per_host"] == pytest.approx(128 / step_s / 16)
  assert est["host_cores_per_host"] == pytest.approx(128 / step_s / 16 * 0.010)
  assert est["host_vcpus"] == 112        # a 4-chip v5e VM
  assert est["hosts_feed_chips"] == (est["host_cores_per_host"] <= 112)
  slow = planner.estimate(config, tgt, per_row, shapes[0], 128, 0.5, 1000.0)
  assert slow["hosts_feed_chips"] is False   # a second per row cannot keep up


def _small_980(names=("hd1k", "flyingchairs")):
  """configs/ufm980.py on two of its datasets at two small shapes (the trees stay small)."""
  config = config_lib.load_config(str(REPO / "configs" / "ufm980.py"))
  config.input.datasets = {n: config.input.datasets[n].to_dict() for n in names}
  config.input.shapes = ((42, 56), (28, 56))
  config.input.longest_side = 56
  return config


def test_host_feed_times_the_recipes_own_pipeline(tmp_path, monkeypatch):
  """The plan's host figure comes from trainer.build_input (train.py's input) run on the
  recipe's own input block (datasets, quotas, shapes, augmentation) over stand-in trees in the
  official layouts, and the load average is recorded beside it."""
  from ufm_jax.testing import host_feed
  from ufm_jax.training import trainer
  config = _small_980()
  seen = []
  real = trainer.build_input

  def spy(cfg, process_batch, seed, teacher=None):
    seen.append(cfg)
    return real(cfg, process_batch, seed, teacher)
  monkeypatch.setattr(trainer, "build_input", spy)
  feed = host_feed.measure(config, rows=8, cache_dir=str(tmp_path))
  assert len(seen) == 1
  block = seen[0].input
  assert dict(block.augment) == dict(config.input.augment)
  assert tuple(map(tuple, block.shapes)) == ((42, 56), (28, 56))
  assert {n: d.quota for n, d in block.datasets.items()} == {"hd1k": 5000, "flyingchairs": 25000}
  for name in ("hd1k", "flyingchairs"):   # read from the trees, at the largest shape
    assert block.datasets[name].root.startswith(str(tmp_path / f"{name}_42x56"))
  assert block.num_workers == 0 and block.read_threads == 0
  assert feed["source"] == "measured" and feed["datasets"] == ["flyingchairs", "hd1k"]
  assert feed["rows"] >= 8 and feed["host_ms_per_row"] > 0 and feed["wall_ms_per_row"] > 0
  assert set(map(tuple, feed["image_shapes"])) <= {(42, 56), (28, 56)}
  assert feed["load_avg_1m"] >= 0
  assert config.input.num_workers != 0     # the caller's config is left as it was


def test_host_ms_per_row_overrides_the_measurement(monkeypatch):
  from ufm_jax.testing import host_feed

  def never(*a, **k):
    raise AssertionError("measured although --host_ms_per_row was given")
  monkeypatch.setattr(host_feed, "measure", never)
  feed = host_feed.for_plan(_small_980(), 12.5, log=lambda *a, **k: None)
  assert feed == {"host_ms_per_row": 12.5, "source": "--host_ms_per_row", "load_avg_1m": None}
  with pytest.raises(ValueError, match="host_ms_per_row"):
    host_feed.for_plan(_small_980(), 0.0)


def test_a_mixture_with_nothing_to_read_is_not_measured(tmp_path):
  """A dataset without an official layout (so no stand-in) that is absent here: no figure, and
  the reason, instead of a made-up one."""
  from ufm_jax.testing import host_feed
  config = _small_980()
  config.input.datasets = {"pairs_folder": {"quota": 10, "root": str(tmp_path / "absent"),
                                            "options": {}}}
  lines = []
  feed = host_feed.for_plan(config, log=lambda *a, **k: lines.append(a[0]))
  assert feed["host_ms_per_row"] is None and feed["source"].startswith("not measured")
  assert str(tmp_path / "absent") in feed["source"] and "--host_ms_per_row" in lines[-1]


def test_the_plan_carries_the_host_feed():
  """A plan with a target that has a step time turns the figure into busy cores and says where
  it comes from; the JSON holds the figure and its load average."""
  config = config_lib.load_config(str(REPO / "configs" / "ufm560.py"))
  tgt = planner.target("v5e-8", compile=False)
  shapes = planner.training_shapes(config)
  # A plan without compiler figures (as XLA's refusal leaves it) beside the estimates.
  result = {"grad_accum": 1, "refused": "-", "compile_s": 0.0, "image_shape": [420, 560],
            "global_batch": 8}
  feed = {"host_ms_per_row": 20.0, "source": "measured", "rows": 96, "load_avg_1m": 3.5}
  result.update(planner.estimate(config, tgt, {s: 1e12 for s in shapes}, shapes[0], 8, 0.5,
                                 feed["host_ms_per_row"]))
  result["host_feed"] = feed
  lines = []
  planner.report(result, log=lambda *a, **k: lines.append(a[0]))
  line = next(x for x in lines if x.strip().startswith("host feed"))
  assert "20.0 ms/row (measured here on 96 rows" in line and "load average 3.5" in line
  cores = 8 / (1e12 * 8 / (8 * 197e12 * 0.5)) / result["hosts"] * 0.020   # rows/s per host x 20 ms
  assert result["host_cores_per_host"] == pytest.approx(cores)
  back = json.loads(planner.to_json(result))
  assert back["host_ms_per_row"] == 20.0 and back["host_feed"]["load_avg_1m"] == 3.5


def test_calibrated_mfu_is_the_papers_run():
  """The paper's 560 run, "4 days on 8 H100 GPUs": 48 epochs of the recipe's 645,000 pairs (both
  directions) at 96 rows per step; the MFU it implies by our FLOP count plans that run in 4 days
  on h100-8, and every estimate carries it beside the assumed MFU."""
  run = planner.paper_run()
  assert run["rows"] == 48 * 2 * 645_000 and run["steps"] == 645_000
  peak = 8 * 989e12
  assert run["mfu"] == pytest.approx(645_000 * 96 * run["mean_flops_per_row"] / (4 * 86400 * peak))
  assert planner.mfu_value("calibrated") == run["mfu"] and planner.mfu_value("0.4") == 0.4
  with pytest.raises(ValueError, match="calibrated"):
    planner.mfu_value("fast")
  config = config_lib.load_config(str(REPO / "configs" / "ufm560.py"))
  shapes = planner.training_shapes(config)
  per_row = {s: run["mean_flops_per_row"] for s in shapes}
  tgt = planner.target("h100-8", compile=False)
  at_paper = planner.estimate(config, tgt, per_row, shapes[0], 96, run["mfu"], None,
                              calibrated=run["mfu"])
  assert at_paper["recipe_steps"] == 645_000
  assert at_paper["days_estimate"] == pytest.approx(4.0)
  at_goal = planner.estimate(config, tgt, per_row, shapes[0], 96, 0.4, None, calibrated=run["mfu"])
  assert at_goal["days_estimate"] == pytest.approx(4.0 * run["mfu"] / 0.4)
  assert at_goal["days_at_calibrated_mfu"] == pytest.approx(4.0)
  assert at_goal["mfu_calibrated"] == run["mfu"] and at_goal["mfu_assumed"] == 0.4


def test_train_py_help_lists_its_flags():
  out = _train_py("--help", timeout=120)
  assert out.returncode == 0, out.stderr
  for flag in ("--config", "--workdir", "--compile_only", "--topology", "--capacity_gib",
               "--config.KEY=VALUE"):
    assert any(line.strip().startswith(flag) for line in out.stdout.splitlines()), flag
  assert "exit 0 if the step fits a device's memory, 3 if it does not, 1 on an error" in (
      " ".join(out.stdout.split()))


def test_train_py_names_a_missing_config_file():
  out = _train_py("--config=configs/nope.py", "--workdir=/tmp/unused", timeout=120)
  assert out.returncode == 2
  assert out.stderr.strip() == "error: --config: no such file configs/nope.py"
  assert out.stdout == ""


@pytest.mark.tpu
@pytest.mark.slow
def test_compile_only_and_the_planner_agree_on_a_tpu_slice():
  """The tiny model's step compiled for a v5e-4 through both programs (libtpu): the same HBM and
  collectives; a batch whose step exceeds the chip's HBM makes train.py exit 3."""
  if not topologies.has_libtpu():
    pytest.skip("libtpu is not installed: pip install 'ufm_jax[tpu]' (in its own virtualenv)")
  spec = str(REPO / "configs" / "synthetic.py") + ":eval=false,model=tiny,batch=16"
  common = ["--config.mesh=data:1,fsdp:-1", "--config.grad_accum=2"]
  a = _train_py(f"--config={spec}", "--compile_only", "--topology=v5e-4", *common, timeout=1200)
  assert a.returncode == 0, a.stderr[-3000:]
  b = _planner("--config", spec, "--topology", "v5e-4", "--mesh", "data:1,fsdp:-1",
               "--grad_accum", "2", timeout=1200)
  assert b.returncode == 0, b.stderr[-3000:]
  ra, rb = _last_json(a), _last_json(b)
  _agree(ra, rb)
  assert ra["chips"] == 4 and ra["device_kind"] == "TPU v5 lite" and ra["fits"]
  assert ra["mesh"] == {"data": 1, "fsdp": 4} and ra["grad_accum"] == 2
  big = _train_py(f"--config={spec},size=560,batch=4096", "--compile_only", "--topology=v5e-4",
                  *common, timeout=1200)
  assert big.returncode == 3, big.stderr[-3000:]
  assert _last_json(big)["fits"] is False


def test_target_of_the_devices_at_hand():
  tgt = planner.target()
  assert tgt.chips == len(jax.devices()) and tgt.hosts == jax.process_count()
