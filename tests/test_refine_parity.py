"""UFM-Refine parity against the official PyTorch fixture (../shared/fixtures/ufm_reference/refine)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from safetensors.numpy import load_file

from ufm_jax.official import keymap
from ufm_jax.models import refine

REFINER_PREFIXES = ("unet_feature.", "classification_head.", "conv1.", "conv2.",
                    "classification_bias")


def nhwc(a):
  return np.transpose(a, (0, 2, 3, 1))


@pytest.fixture(scope="module")
def fx(reference_dir):
  d = reference_dir / "refine"
  tensors = load_file(str(d / "model.safetensors"))
  # The refiner's tensors through the loader's key map (the whole model is loaded further down).
  params = {}
  for key, value in tensors.items():
    if key.startswith(REFINER_PREFIXES):
      path = keymap.torch_key_to_path(key, value.ndim)
      node = params
      for part in path[:-1]:
        node = node.setdefault(part, {})
      node[path[-1]] = keymap.torch_to_flax_array(key, value)
  return dict(dir=d, tensors=tensors, params=params,
              io=dict(np.load(d / "io.npz")), it=dict(np.load(d / "intermediates.npz")))


@pytest.fixture(scope="module")
def refiner(fx):
  import json
  cfg = json.loads((fx["dir"] / "config.json").read_text())
  head = cfg["classification_head_kwargs"]
  return refine.Refiner(unet_features=refine.unet_widths(fx["tensors"]),
                        feature_dim=head["output_dim"], patch_size=head["patch_size"],
                        mlp_ratio=head["mlp_ratio"], use_unet_feature=cfg["use_unet_feature"],
                        feature_combine_method=cfg["feature_combine_method"],
                        refinement_range=cfg["refinement_range"], temperature=cfg["temperature"])


def test_unet_widths_from_weights(fx):
  assert refine.unet_widths(fx["tensors"]) == (8, 16, 32, 64)


def test_unet_matches_fixture(fx, refiner):
  io, it = fx["io"], fx["it"]
  imgs = np.concatenate([nhwc(io["img1_norm"]), nhwc(io["img2_norm"])])
  out = jax.jit(lambda p, x: refiner.apply({"params": p}, x, method=lambda m, x: m.unet_feature(x)))(
      fx["params"], imgs)
  ref = np.concatenate([nhwc(it["unet_out_view1"]), nhwc(it["unet_out_view2"])])
  np.testing.assert_allclose(np.asarray(out), ref, atol=2e-4)


def test_classification_head_matches_fixture(fx, refiner):
  it = fx["it"]
  tokens = nhwc(it["cls_head_in"])
  mlp = refiner.apply({"params": fx["params"]}, tokens,
                      method=lambda m, x: m.classification_head(x, return_mlp=True))
  np.testing.assert_allclose(np.asarray(mlp), it["cls_mlp_out_nhwc"], atol=1e-4)
  out = refiner.apply({"params": fx["params"]}, tokens, method=lambda m, x: m.classification_head(x))
  np.testing.assert_allclose(np.asarray(out), nhwc(it["cls_head_out"]), atol=1e-4)


def test_feature_maps_match_fixture(fx, refiner):
  io, it = fx["io"], fx["it"]
  tokens = nhwc(it["cls_head_in"])
  imgs = np.concatenate([nhwc(io["img1_norm"]), nhwc(io["img2_norm"])])
  feats = np.asarray(jax.jit(lambda p, t, x: refiner.apply(
      {"params": p}, t, x, method=lambda m, t, x: m.features(t, x)))(fx["params"], tokens, imgs))
  np.testing.assert_allclose(feats[:2], nhwc(io["feature_map_0"]), atol=2e-4)
  np.testing.assert_allclose(feats[2:], nhwc(io["feature_map_1"]), atol=2e-4)


@pytest.mark.parametrize("chunk", [None, 16])
def test_local_refinement_matches_fixture(fx, chunk):
  """The official features and regressed flow in; residual, log_softmax, refined flow out."""
  io = fx["io"]
  flow0 = nhwc(io["flow_before_refinement"])
  fn = jax.jit(lambda *a: refine.local_refinement(*a, temperature=4.0, radius=3, chunk=chunk))
  res, log_p = fn(jnp.asarray(nhwc(io["feature_map_0"])), jnp.asarray(nhwc(io["feature_map_1"])),
                  jnp.asarray(flow0), jnp.asarray(fx["params"]["classification_bias"]))
  np.testing.assert_allclose(np.asarray(res), nhwc(io["residual"]), atol=5e-3)
  np.testing.assert_allclose(np.asarray(log_p), io["log_softmax"], atol=1e-2)
  np.testing.assert_allclose(flow0 + np.asarray(res), nhwc(io["flow"]), atol=5e-3)
  # The official `regression_flow_output` holds the refined flow too.
  np.testing.assert_allclose(flow0 + np.asarray(res), nhwc(io["regression_flow_output"]), atol=5e-3)


# ----------------------------------------------------------------------------------------------
# The whole UFM-Refine model, loaded from the snapshot through load_official


@pytest.fixture(scope="module", params=[False, True], ids=["unrolled", "scan"])
def full(fx, request):
  from ufm_jax.official.snapshot import load_official
  from ufm_jax.models import scan
  model, variables = load_official(fx["dir"])
  params = variables["params"]
  if request.param:   # the same snapshot as a scan model (stacked encoder / fusion blocks)
    model = model.clone(config=model.config.replace(scan_blocks=True))
    params = scan.stack_blocks(params, model.config)
    assert "blocks" in params["encoder"] and "self_attention_blocks" in params["info_sharing"]
  io = fx["io"]
  out = jax.jit(model.apply)({"params": params}, io["img1_uint8"], io["img2_uint8"])
  return model, params, {k: np.asarray(v) for k, v in out.items()}


def test_load_official_recognises_refine(full):
  model, params, _ = full
  assert type(model).__name__ == "UFMRefine"
  assert model.config.unet_features == (8, 16, 32, 64)
  assert model.config.refinement_range == 7 and model.config.temperature == 4.0
  assert model.config.refine_mlp_ratio == 2.0 and model.config.refine_feature_dim == 16
  for k in ("unet_feature", "classification_head", "conv1", "conv2", "classification_bias",
            "encoder", "info_sharing"):
    assert k in params


def test_forward_matches_fixture(fx, full):
  io = fx["io"]
  _, _, out = full
  assert set(out) >= {"flow", "covisibility", "covisibility_logits", "flow_before_refinement",
                      "residual", "log_softmax", "feature_map_0", "feature_map_1"}
  np.testing.assert_allclose(out["flow_before_refinement"], nhwc(io["flow_before_refinement"]),
                             atol=1e-3)
  np.testing.assert_allclose(out["flow"], nhwc(io["flow"]), atol=5e-3)
  np.testing.assert_allclose(out["residual"], nhwc(io["residual"]), atol=5e-3)
  np.testing.assert_allclose(out["log_softmax"], io["log_softmax"], atol=1e-2)
  np.testing.assert_allclose(out["feature_map_0"], nhwc(io["feature_map_0"]), atol=2e-4)
  np.testing.assert_allclose(out["feature_map_1"], nhwc(io["feature_map_1"]), atol=2e-4)
  np.testing.assert_allclose(out["covisibility_logits"], io["covisibility_logits"][:, 0], atol=2e-4)
  np.testing.assert_allclose(out["covisibility"], io["covisibility_mask"][:, 0], atol=5e-5)


def test_symmetrized_forward_agrees(fx, full):
  """(a,b),(b,a) batches: encoding each image (and U-Net) once equals the plain pass.
  (Row chunking of the refinement is checked on the fixture in test_local_refinement_matches_fixture.)"""
  model, params, _ = full
  a, b = fx["io"]["img1_uint8"][0, :42, :70], fx["io"]["img2_uint8"][0, :42, :70]
  src, tgt = np.stack([a, b]), np.stack([b, a])
  fwd = jax.jit(lambda p, s, t: (model.apply({"params": p}, s, t),
                                 model.apply({"params": p}, s, t, symmetrized=True)))
  plain, sym = fwd(params, src, tgt)
  for k in ("flow", "flow_before_refinement", "feature_map_0", "feature_map_1", "covisibility"):
    np.testing.assert_allclose(np.asarray(sym[k]), np.asarray(plain[k]), atol=1e-4, err_msg=k)


@pytest.mark.parametrize("pair", ["hl0", "hl1", "hl2"])
def test_predict_high_level_pairs(fx, full, pair):
  from ufm_jax import predict
  model, params, _ = full
  io = fx["io"]
  out = predict(model, params, io[f"{pair}_src_uint8"], io[f"{pair}_tgt_uint8"])
  np.testing.assert_allclose(out["flow"], nhwc(io[f"{pair}_flow"])[0], atol=5e-3)
  np.testing.assert_allclose(out["covisibility"], io[f"{pair}_covisibility"][0], atol=5e-5)


def test_convert_save_load_and_infer_cli(fx, full, tmp_path):
  """The converted checkpoint reloads as UFMRefine with equal params, and the infer CLI on it
  reproduces the official high-level output of pair hl1 (target smaller than the source)."""
  import cv2
  from ufm_jax.tools import cli
  from ufm_jax.runtime.model_io import load_converted, save
  model, params, _ = full
  save(tmp_path / "ckpt", model, params)
  model2, variables2 = load_converted(tmp_path / "ckpt")
  assert type(model2) is type(model) and model2.config == model.config
  for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(variables2["params"])):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  io = fx["io"]
  cv2.imwrite(str(tmp_path / "src.png"), io["hl1_src_uint8"][..., ::-1])
  cv2.imwrite(str(tmp_path / "tgt.png"), io["hl1_tgt_uint8"][..., ::-1])
  assert cli.main(["infer", str(tmp_path / "src.png"), str(tmp_path / "tgt.png"),
                   "--checkpoint", str(tmp_path / "ckpt"), "--out", str(tmp_path / "out")]) == 0
  flow = np.load(tmp_path / "out" / "forward_flow.npy")
  np.testing.assert_allclose(flow, nhwc(io["hl1_flow"])[0], atol=5e-3)


def test_loader_rejects_wrong_refiner_weights(fx, tmp_path):
  import json
  import shutil
  from safetensors.numpy import save_file
  from ufm_jax.official.snapshot import load_official
  d = tmp_path / "snap"
  d.mkdir()
  shutil.copy(fx["dir"] / "config.json", d / "config.json")
  tensors = dict(fx["tensors"])
  del tensors["conv2.bias"]
  tensors["conv1.weight"] = tensors["conv1.weight"][:, :16]
  save_file(tensors, str(d / "model.safetensors"))
  with pytest.raises(ValueError) as e:
    load_official(d)
  msg = str(e.value)
  assert "conv2.bias" in msg and "conv1.weight" in msg
  cj = json.loads((fx["dir"] / "config.json").read_text())
  del cj["temperature"]
  (d / "config.json").write_text(json.dumps(cj))
  save_file(dict(fx["tensors"]), str(d / "model.safetensors"))
  with pytest.raises(ValueError, match="temperature"):
    load_official(d)


def test_float64_matches_official_float64_run(fx):
  """The whole UFM-Refine pass in float64 against io_f64.npz (x64 must be on before jax starts,
  hence a subprocess). Refined flow and residual agree far below the 1e-4 px bar."""
  import os
  import pathlib
  import subprocess
  import sys
  import textwrap
  repo = pathlib.Path(__file__).resolve().parents[1]
  script = textwrap.dedent(f"""
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from ufm_jax.official.snapshot import load_official
    d = {str(fx["dir"])!r}
    model, variables = load_official(d)
    params = variables["params"]
    model = model.clone(config=model.config.replace(dtype="float64"))
    params = jax.tree.map(lambda p: np.asarray(p, np.float64), params)
    io = np.load(d + "/io_f64.npz")
    out = jax.jit(model.apply)({{"params": params}}, io["img1_uint8"], io["img2_uint8"])
    assert out["flow"].dtype == np.float64, out["flow"].dtype
    errs = [np.abs(np.asarray(out[k]).transpose(0, 3, 1, 2) - io[k]).max()
            for k in ("flow", "residual", "flow_before_refinement")]
    print(*errs)
  """)
  env = dict(os.environ, PYTHONPATH=str(repo) + os.pathsep + os.environ.get("PYTHONPATH", ""),
             JAX_PLATFORMS="cpu")
  res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                       timeout=600)
  assert res.returncode == 0, res.stderr[-3000:]
  flow, residual, before = map(float, res.stdout.split()[-3:])
  assert flow < 1e-4 and residual < 1e-4 and before < 1e-6, (flow, residual, before)
