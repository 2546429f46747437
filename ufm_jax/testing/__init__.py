"""Helpers shared by the tests and benchmarks (tests never import each other): model structures
the public fixtures do not cover, random parameters for them, official-style snapshot folders,
random weights in official namings, the skip-or-fail rule of optional extras. Submodules:
`wide_trees` (tiny trees in the real on-disk formats of the wide-baseline and benchmark datasets),
`bench_trees` (the optical-flow benchmarks' layouts and the official benchmark branch's),
`official_trees` (the official processed training layouts), `train_support` (a stand-in model,
data and config for the training-machinery tests), `param_counts` (closed-form parameter counts
of the official modules); `training_fixtures()` locates the official training-code fixtures."""

from __future__ import annotations

import json
import pathlib

import numpy as np

from ufm_jax.models import dinov2, dpt, info_sharing, refine, ufm


def load_script(relpath: str):
  """The repository's script at `relpath` (train.py, evaluate.py, data/*/prepare.py, a benchmark)
  loaded as a module by its path: scripts are not part of the installed package, and `pytest`
  run from a fresh clone does not put the repository root on sys.path."""
  import importlib.util
  path = pathlib.Path(__file__).resolve().parents[2] / relpath
  spec = importlib.util.spec_from_file_location(f"_script_{path.stem}", path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def skip_or_fail(reason: str, ci_note: str) -> None:
  """Skips the calling test with `reason`; under CI=true fails instead (`ci_note` says why CI
  has what is missing), so CI never passes by skipping."""
  import os

  import pytest
  if os.environ.get("CI", "").lower() == "true":
    pytest.fail(f"{reason} ({ci_note})")
  pytest.skip(reason)


def fake_devices_env(devices: int, **extra) -> dict:
  """Environment for a subprocess with `devices` fake CPU devices (the repository on its
  PYTHONPATH): multi-device tests run their step in a child process, since the device count is
  fixed when jax starts. XLA:CPU runs each fake device's program on a shared thread pool and ends
  the process when a collective waits more than 40 s for its peers; on CI's 2 cores, with
  another test worker beside it, a step of 8 fake devices can wait that long without anything
  being wrong, so the limit is raised to 15 minutes (a real deadlock still ends the test)."""
  import os
  repo = str(pathlib.Path(__file__).resolve().parents[2])
  env = dict(os.environ)
  env["PYTHONPATH"] = os.pathsep.join(p for p in (repo, env.get("PYTHONPATH", "")) if p)
  env["JAX_PLATFORMS"] = "cpu"
  env["XLA_FLAGS"] = (f"--xla_force_host_platform_device_count={devices}"
                      " --xla_cpu_collective_call_terminate_timeout_seconds=900"
                      " --xla_cpu_collective_timeout_seconds=900")
  env.update(extra)
  return env


def require_extra(extra: str, modules) -> None:
  """Skips the calling test when an optional extra's modules are missing, naming the pip command;
  fails instead under CI=true (CI installs the test extra, which includes every extra tested)."""
  import importlib.util
  missing = [m for m in modules if importlib.util.find_spec(m) is None]
  if missing:
    skip_or_fail(f"the [{extra}] extra is not installed ({', '.join(missing)} missing): "
                 f"pip install -e '.[{extra}]'", "CI installs the test extra, which includes it")


def training_fixtures_root() -> pathlib.Path:
  """Where the official training-code fixtures are looked for (`UFM_TRAINING_FIXTURES`, default
  `../shared/fixtures/ufm_training` beside the repository), without checking it exists: for
  discovering the cases a folder lists when pytest collects (missing: no cases)."""
  import os
  repo = pathlib.Path(__file__).resolve().parents[2]
  default = repo.parent / "shared" / "fixtures" / "ufm_training"
  return pathlib.Path(os.environ.get("UFM_TRAINING_FIXTURES", default))


def training_fixtures(subdir: str | None = None) -> pathlib.Path:
  """The folder of the official training-code fixtures (`UFM_TRAINING_FIXTURES`, default
  `../shared/fixtures/ufm_training` beside the repository), or `subdir` of it.

  Missing: skips the calling test with a reason naming UFM_TRAINING_FIXTURES; under CI=true
  fails instead, so CI can never pass the training parity tests by skipping them.
  """
  folder = training_fixtures_root() / subdir if subdir else training_fixtures_root()
  if not folder.is_dir():
    skip_or_fail(f"official training fixtures not found at {folder}: set UFM_TRAINING_FIXTURES "
                 "to the folder that holds losses/, schedules/, labels/, processed/",
                 "CI=true: parity tests may not be skipped")
  return folder


def reference_cases(folder: str, env: str) -> tuple[pathlib.Path, list[str]]:
  """(root, case names) of a folder of official reference snapshots: `env` when set (a folder of
  case folders), else `<UFM_FIXTURES or ../shared/fixtures beside the repository>/<folder>`; a case
  is any sub-folder with a config.json, so every case a folder holds is checked. No cases (or no
  folder): an empty list, for the test to skip or fail on (`skip_or_fail`)."""
  import os
  repo = pathlib.Path(__file__).resolve().parents[2]
  fixtures = pathlib.Path(os.environ.get("UFM_FIXTURES", repo.parent / "shared" / "fixtures"))
  root = pathlib.Path(os.environ.get(env) or fixtures / folder)
  return root, sorted(p.parent.name for p in root.glob("*/config.json"))


def reference_case(root: pathlib.Path, name: str | None, env: str) -> pathlib.Path:
  """`root / name`, or for None (a folder without cases) skip naming where they were looked
  for and the variables that move it (fails under CI=true: parity tests may not be skipped)."""
  if name is None:
    skip_or_fail(f"no official reference snapshots under {root}: set {env} to a folder of case "
                 f"folders, or UFM_FIXTURES to the folder that holds {root.name}/",
                 "CI=true: parity tests may not be skipped")
  return root / name


def nhwc(a):
  """[B, C, H, W] (the official outputs) -> [B, H, W, C]."""
  return np.transpose(a, (0, 2, 3, 1))


def assert_max_abs(name: str, got, want, atol: float) -> None:
  """Same shape and max |got - want| <= atol, the message naming both."""
  got = np.asarray(got, np.float64)
  assert got.shape == want.shape, f"{name}: shape {got.shape} != {want.shape}"
  err = float(np.abs(got - want).max())
  assert err <= atol, f"{name}: max |diff| {err:.3g} > {atol:.3g}"


def official_case(case_dir) -> tuple:
  """(model, variables, io, forward outputs as numpy) of an official reference snapshot folder
  (config.json + model.safetensors + io.npz): the snapshot loaded and run on io.npz's pair."""
  import jax

  import ufm_jax
  model, variables = ufm_jax.load_official(case_dir)
  io = dict(np.load(pathlib.Path(case_dir) / "io.npz"))
  out = jax.jit(model.apply)(variables, io["img1_uint8"], io["img2_uint8"])
  return model, variables, io, {k: np.asarray(v) for k, v in out.items()}


def assert_forward_parity(io: dict, out: dict) -> None:
  """The forward outputs an official io.npz has, at the fixtures' tolerances: flow 1e-3 px (5e-3
  after refinement), covisibility logits 2e-4 and mask 5e-5; a refinement model's regressed flow
  1e-3, residual 5e-3 and feature maps 2e-4."""
  refined = "flow_before_refinement" in io
  assert_max_abs("flow", out["flow"], nhwc(io["flow"]), 5e-3 if refined else 1e-3)
  if "covisibility_logits" in io:
    assert_max_abs("covisibility_logits", out["covisibility_logits"],
                   io["covisibility_logits"][:, 0], 2e-4)
    assert_max_abs("covisibility", out["covisibility"], io["covisibility_mask"][:, 0], 5e-5)
  else:   # the official model has no covisibility output: none made up
    assert "covisibility" not in out, "no official covisibility, yet ours predicts one"
  if refined:
    assert_max_abs("flow_before_refinement", out["flow_before_refinement"],
                   nhwc(io["flow_before_refinement"]), 1e-3)
    assert_max_abs("residual", out["residual"], nhwc(io["residual"]), 5e-3)
    for k in ("feature_map_0", "feature_map_1"):
      assert_max_abs(k, out[k], nhwc(io[k]), 2e-4)


# predict_correspondences_batched's flow, as the v2 tests hold it (tests/test_official_releases.py,
# HL_FLOW_ATOL there says why): 1e-3 px, 6e-3 px after refinement.
HL_FLOW_ATOL = {"base": 1e-3, "refine": 6e-3}


def assert_predict_parity(model, variables, io: dict, pair: str) -> dict:
  """ufm_jax.predict on io.npz's high-level pair `pair` (hl0, hl1, ...) against the official
  predict_correspondences_batched: flow within HL_FLOW_ATOL, covisibility 5e-5 (a case without
  one, e.g. UniFlowMatch with the adaptor map {flow}: none predicted). Skips when the case has no
  such pair; returns the prediction."""
  import pytest

  import ufm_jax
  if f"{pair}_src_uint8" not in io:
    pytest.skip(f"this case has no {pair}")
  got = ufm_jax.predict(model, variables, io[f"{pair}_src_uint8"], io[f"{pair}_tgt_uint8"])
  atol = HL_FLOW_ATOL["refine" if "flow_before_refinement" in io else "base"]
  assert_max_abs(f"{pair}_flow", got["flow"], nhwc(io[f"{pair}_flow"])[0], atol)
  if f"{pair}_covisibility" in io:
    assert_max_abs(f"{pair}_covisibility", got["covisibility"], io[f"{pair}_covisibility"][0],
                   5e-5)
  else:
    assert "covisibility" not in got, f"{pair}: no official covisibility, yet ours predicts one"
  return got


def assert_covariance_close(name: str, got, want, rtol: float, slack=None) -> None:
  """Flow covariance triplets [..., 3] (var_x, var_y, cov_xy) compared as issue #42 states it:
  each variance within `rtol` of itself, cov_xy within `rtol` of sqrt(var_x var_y) (so a
  correlation near 0 is not held to a relative bound); `slack` [...] widens the bound per pixel.
  The message names the worst pixel."""
  got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
  assert got.shape == want.shape, f"{name}: shape {got.shape} != {want.shape}"
  bound = np.broadcast_to(rtol + (0 if slack is None else slack), want.shape[:-1])
  errors = {"var_x": np.abs(got[..., 0] / want[..., 0] - 1),
            "var_y": np.abs(got[..., 1] / want[..., 1] - 1),
            "cov_xy": np.abs(got[..., 2] - want[..., 2]) / np.sqrt(want[..., 0] * want[..., 1])}
  for what, err in errors.items():
    worst = np.unravel_index(np.argmax(err - bound), err.shape)
    assert (err <= bound).all(), (f"{name} {what}: error {err[worst]:.3g} > {bound[worst]:.3g} "
                                  f"(relative{' to sqrt(var_x var_y)' if what == 'cov_xy' else ''})"
                                  f" at {worst}")


def assert_exact_official_round_trip(snapshot_dir, model, variables, tmp_path) -> None:
  """snapshot -> our checkpoint (convert) -> official snapshot (save_official with the snapshot
  as source): config.json and model.safetensors byte for byte (the header as the source file has
  it, alias order included)."""
  import ufm_jax
  from ufm_jax.runtime import model_io
  d, tmp = pathlib.Path(snapshot_dir), pathlib.Path(tmp_path)
  model_io.save(tmp / "ckpt", model, variables)
  back_model, back_variables = ufm_jax.load(tmp / "ckpt")
  assert back_model.config == model.config
  ufm_jax.save_official(back_model, back_variables, tmp / "out", source=str(d))
  assert (tmp / "out" / "config.json").read_bytes() == (d / "config.json").read_bytes()
  assert (tmp / "out" / "model.safetensors").read_bytes() == \
      (d / "model.safetensors").read_bytes()


def snapshot_with_config(src, dst, edit, sort_keys: bool = True) -> pathlib.Path:
  """A snapshot folder `dst` with `src`'s weights (linked) and its config.json changed by
  `edit(config_dict)`, written with sorted keys as save_pretrained writes it, or in the order
  `edit` left them (`sort_keys=False`)."""
  import os
  src, dst = pathlib.Path(src), pathlib.Path(dst)
  dst.mkdir()
  cj = json.loads((src / "config.json").read_text())
  edit(cj)
  (dst / "config.json").write_text(json.dumps(cj, indent=2, sort_keys=sort_keys))
  os.symlink(src / "model.safetensors", dst / "model.safetensors")
  return dst


def write_snapshot(folder, config: dict, state: dict, metadata=None) -> pathlib.Path:
  """A Hugging Face snapshot folder (config.json + model.safetensors) from a torch-named state."""
  from safetensors.numpy import save_file
  d = pathlib.Path(folder)
  d.mkdir(parents=True, exist_ok=True)
  (d / "config.json").write_text(json.dumps(config))
  save_file({k: np.ascontiguousarray(v) for k, v in state.items()}, str(d / "model.safetensors"),
            metadata=metadata)
  return d


def random_snapshot(folder, config: ufm.UFMConfig, seed: int = 0) -> pathlib.Path:
  """An official snapshot folder (`save_official`: config.json + model.safetensors) of the model
  `config` describes with random parameters (`perturbed_params`)."""
  from ufm_jax.official import snapshot
  model = ufm.model_from_config(config)
  snapshot.save_official(model, perturbed_params(model, seed), folder)
  return pathlib.Path(folder)


def hub_cache(root, repo_id: str, snapshot, commit: str) -> pathlib.Path:
  """A Hugging Face cache in the standard layout (models--owner--name/{blobs, refs, snapshots})
  under `root` holding `snapshot`'s config.json and model.safetensors at `commit`, with `main`
  pointing there; read with HF_HUB_CACHE=root (and HF_HUB_OFFLINE=1)."""
  import hashlib
  import os
  repo = pathlib.Path(root) / ("models--" + repo_id.replace("/", "--"))
  (repo / "refs").mkdir(parents=True)
  (repo / "refs" / "main").write_text(commit)
  snap = repo / "snapshots" / commit
  snap.mkdir(parents=True)
  (repo / "blobs").mkdir()
  for name in ("config.json", "model.safetensors"):
    data = (pathlib.Path(snapshot) / name).read_bytes()
    blob = repo / "blobs" / hashlib.sha256(data).hexdigest()
    blob.write_bytes(data)
    os.symlink(os.path.relpath(blob, snap), snap / name)
  return pathlib.Path(root)


def perturbed_params(model, seed: int):
  """Random values for every parameter of the model's tree (shapes via jax.eval_shape; compiling
  flax's initialisers for a many-module tree is slow on CPU and not what the tests check)."""
  return ufm.random_param_values(model, seed,
                                 small_names=("cls_token", "pos_embed", "register_tokens"))


def _small_dpt(enc_dim: int, dim: int, output_dim: int, layer_dims=(8, 16, 32, 48), feature_dim=16):
  return dpt.DPTConfig((enc_dim, dim, dim, dim), layer_dims, feature_dim, output_dim=output_dim)


def _refine(base: ufm.UFMConfig, **kw) -> refine.UFMRefineConfig:
  fields = {f: getattr(base, f) for f in ufm.UFMConfig.__dataclass_fields__}
  return refine.UFMRefineConfig(**fields, **kw)


# Structures with which the loader and the export are tested beyond the two public fixtures.
STRUCTURES = {
    # ViT-S with registers (antialiased pos-embed), 1 block; LayerScale + qk-norm in the fusion
    # transformer; processor hidden dims; x-only flow scaling.
    "registers_layerscale_qknorm": ufm.UFMConfig(
        encoder=dinov2.dinov2_config("small", depth=1, indices=(0,), num_register_tokens=4,
                                     interpolate_antialias=True, interpolate_offset=0.0),
        info_sharing=info_sharing.InfoSharingConfig(
            input_embed_dim=384, dim=64, depth=3, num_heads=2, qk_norm=True, init_values=0.5,
            indices=(0, 1)),
        flow_head=dpt.DPTConfig((384, 64, 64, 64), (8, 16, 32, 48), 16, output_dim=2,
                                hidden_dims=(12, 6)),
        covisibility_head=dpt.DPTConfig((384, 64, 64, 64), (16, 16, 16, 16), 24, output_dim=1),
        flow_adaptor=dpt.FlowAdaptorConfig((0.5, 0.25), (3.0, 4.0), (70, 98), "scale_width"),
        inference_resolution=(70, 98)),
    # ViT-S cut to 2 blocks, taps by "last n", identity input projection (dim == 384),
    # coordinate-style flow output, no gradient stop before the covisibility head.
    "identity_proj_coords": ufm.UFMConfig(
        encoder=dinov2.dinov2_config("small", depth=2, indices=2),
        info_sharing=info_sharing.InfoSharingConfig(
            input_embed_dim=384, dim=384, depth=2, num_heads=6, indices=(0, 1)),
        flow_head=dpt.DPTConfig((384, 384, 384, 384), (8, 8, 8, 8), 8, output_dim=2),
        covisibility_head=dpt.DPTConfig((384, 384, 384, 384), (8, 8, 8, 8), 8, output_dim=1),
        flow_adaptor=dpt.FlowAdaptorConfig((0.0, 0.0), (1.0, 1.0), (42, 70), "none",
                                           output_normalized_coordinate=True),
        detach_uncertainty_head=False, inference_resolution=(42, 70)),
    # ViT-g (SwiGLU FFN, 1536 wide) cut to its first block.
    "giant_swiglu": ufm.UFMConfig(
        encoder=dinov2.dinov2_config("giant", depth=1, indices=(0,)),
        info_sharing=info_sharing.InfoSharingConfig(
            input_embed_dim=1536, dim=64, depth=2, num_heads=2, indices=(0, 1)),
        flow_head=_small_dpt(1536, 64, 2), covisibility_head=_small_dpt(1536, 64, 1),
        flow_adaptor=dpt.FlowAdaptorConfig((0.0, 0.0), (8.0, 8.0), (42, 70), "scale_height"),
        inference_resolution=(42, 70)),
    # The UFM 980 configuration: ViT-L (cut to one block), 980 px inference resolution over the
    # 560 base shape of the flow normalisation, fusion taps as the release's (5, 8 of 12).
    "ufm980": ufm.UFMConfig(
        encoder=dinov2.dinov2_config("large", depth=1, indices=(0,)),
        info_sharing=info_sharing.InfoSharingConfig(
            input_embed_dim=1024, dim=32, depth=12, num_heads=2, indices=(5, 8)),
        flow_head=_small_dpt(1024, 32, 2), covisibility_head=_small_dpt(1024, 32, 1),
        flow_adaptor=dpt.FlowAdaptorConfig((0.1, -0.2), (20.0, 15.0), (420, 560), "scale_both"),
        inference_resolution=(742, 980)),
    # UFM-Refine with a non-integral head ratio, a 5 x 5 window and another temperature.
    "refine_window5": _refine(
        ufm.UFMConfig(
            encoder=dinov2.dinov2_config("small", depth=1, indices=(0,)),
            info_sharing=info_sharing.InfoSharingConfig(
                input_embed_dim=384, dim=32, depth=2, num_heads=2, indices=(0, 1)),
            flow_head=_small_dpt(384, 32, 2), covisibility_head=_small_dpt(384, 32, 1),
            flow_adaptor=dpt.FlowAdaptorConfig((0.0, 0.0), (4.0, 4.0), (42, 70), "scale_both"),
            inference_resolution=(42, 70)),
        unet_features=(8, 16), refine_feature_dim=8, refine_mlp_ratio=1.5, refinement_range=5,
        temperature=2.0),
}


def official_small_config(**overrides) -> ufm.UFMConfig:
  """The smallest structure the official classes build (ViT-S/14 cut to one block, narrow fusion
  and heads), for training a few steps and exporting the result."""
  cfg = ufm.UFMConfig(
      encoder=dinov2.dinov2_config("small", depth=1, indices=(0,)),
      info_sharing=info_sharing.InfoSharingConfig(
          input_embed_dim=384, dim=32, depth=2, num_heads=2, indices=(0, 1)),
      flow_head=_small_dpt(384, 32, 2, (8, 8, 16, 16), 8),
      covisibility_head=_small_dpt(384, 32, 1, (8, 8, 16, 16), 8),
      flow_adaptor=dpt.FlowAdaptorConfig((0.0, 0.0), (8.0, 8.0), (56, 56), "scale_both"),
      inference_resolution=(56, 56))
  return cfg.replace(**overrides)


def official_small_model(model_kw=None):
  """`model_fn` of a train.py workdir config (called with the config's `model` block)."""
  kw = model_kw.to_dict() if hasattr(model_kw, "to_dict") else dict(model_kw or {})
  return ufm.model_from_config(official_small_config(**kw))


def official_small_refine_recipe_config(**overrides) -> refine.UFMRefineConfig:
  """`variants.ufm_refine_recipe`'s options (BatchNorm U-Net, "modulate", no uncertainty head, an
  extra early encoder tap) on the smallest structure the official classes build: what a test
  trains and exports to an official snapshot (a `tiny_refine_recipe` encoder is no DINOv2 size)."""
  base = official_small_config(encoder=dinov2.dinov2_config("small", depth=2, indices=(0, 1)),
                               covisibility_head=None)
  cfg = _refine(base, unet_features=(8, 16), refine_feature_dim=8, refine_mlp_ratio=2.0,
                use_unet_batchnorm=True, feature_combine_method="modulate")
  return cfg.replace(**overrides)


def official_small_refine_recipe_model(model_kw=None):
  """`model_fn` of a train.py config for `official_small_refine_recipe_config`."""
  kw = model_kw.to_dict() if hasattr(model_kw, "to_dict") else dict(model_kw or {})
  return ufm.model_from_config(official_small_refine_recipe_config(**kw))


def hf_dinov2(depth=2, dim=8, grid=3, seed=0):
  """Random weights in the transformers Dinov2Model naming."""
  rng = np.random.default_rng(seed)
  r = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
  sd = {"embeddings.cls_token": r(1, 1, dim), "embeddings.mask_token": r(1, dim),
        "embeddings.position_embeddings": r(1, 1 + grid * grid, dim),
        "embeddings.patch_embeddings.projection.weight": r(dim, 3, 14, 14),
        "embeddings.patch_embeddings.projection.bias": r(dim),
        "layernorm.weight": r(dim), "layernorm.bias": r(dim)}
  for i in range(depth):
    p = f"encoder.layer.{i}."
    for n in ("query", "key", "value"):
      sd[p + f"attention.attention.{n}.weight"] = r(dim, dim)
      sd[p + f"attention.attention.{n}.bias"] = r(dim)
    sd[p + "attention.output.dense.weight"] = r(dim, dim)
    sd[p + "attention.output.dense.bias"] = r(dim)
    for n in ("norm1", "norm2"):
      sd[p + f"{n}.weight"], sd[p + f"{n}.bias"] = r(dim), r(dim)
    sd[p + "layer_scale1.lambda1"], sd[p + "layer_scale2.lambda1"] = r(dim), r(dim)
    sd[p + "mlp.fc1.weight"], sd[p + "mlp.fc1.bias"] = r(4 * dim, dim), r(4 * dim)
    sd[p + "mlp.fc2.weight"], sd[p + "mlp.fc2.bias"] = r(dim, 4 * dim), r(dim)
  return sd


def wide_scanned_config(grad_accum: int = 1):
  """configs/synthetic.py with a model whose scanned blocks are as wide as a small production
  model's (512 wide, MLP 2048: 4 encoder blocks, 6 fusion blocks in three scans of 2), small DPT
  heads, bf16, remat and FSDP over every device: for compiling a train step for a TPU slice
  (tests/test_sharding_collectives.py). Its 64-way shards are large enough for XLA:TPU to reduce
  them as it reduces UFM-Base's (the tiny model's 64-wide blocks are all-reduced whatever is
  asked)."""
  from ufm_jax.training import config_lib
  c = config_lib.load_config(str(pathlib.Path(__file__).resolve().parents[2] / "configs" /
                                 "synthetic.py") + ":eval=false")
  c.unlock()
  c.model_name = "tiny"
  c.model = config_lib.model_options(dtype="bfloat16", remat=True, scan_blocks=True)
  c.model.encoder = dinov2.DinoV2Config(embed_dim=512, depth=4, num_heads=8, pos_grid=4,
                                        indices=(3,))
  c.model.info_sharing = info_sharing.InfoSharingConfig(input_embed_dim=512, dim=512, depth=6,
                                                        num_heads=8, indices=(1, 3))
  c.model.flow_head = _small_dpt(512, 512, 2)
  c.model.covisibility_head = _small_dpt(512, 512, 1)
  c.mesh = "data:1,fsdp:-1"
  c.grad_accum = grad_accum
  return c
