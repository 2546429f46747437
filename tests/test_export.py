"""`python -m ufm_jax export`: StableHLO artifacts reloaded in a fresh process without the model
code, ONNX parity through onnxruntime, the sidecar, and the errors that name what is wrong."""

import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ufm_jax
from ufm_jax import testing
from ufm_jax.tools import cli, export
from ufm_jax.models import ufm
from ufm_jax.official import config as official_config
from ufm_jax.official import snapshot

REPO = pathlib.Path(__file__).resolve().parents[1]

# Runs in a fresh interpreter: jax.export alone, then ufm_jax.load_exported; neither may pull in
# the model code.
FRESH = textwrap.dedent("""
    import sys
    import numpy as np
    from jax import export
    art, inputs, out = sys.argv[1:4]
    d = np.load(inputs)
    exp = export.deserialize(bytearray(open(art, "rb").read()))
    raw = exp.call(d["source"], d["target"])
    import ufm_jax
    m = ufm_jax.load_exported(art)
    full = m(d["source"], d["target"])
    one = m(d["source"][:1], d["target"][:1])   # fixed batch: padded; dynamic: batch 1
    loaded = sorted(k for k in sys.modules if k.startswith("ufm_jax"))
    assert "ufm_jax.models" not in sys.modules, loaded
    res = {"raw_" + k: np.asarray(v) for k, v in raw.items()}
    res.update({"full_" + k: v for k, v in full.items()})
    res.update({"one_" + k: v for k, v in one.items()})
    np.savez(out, **res)
""")


def _fresh_call(artifact, source, target, tmp_path):
  inputs, out = tmp_path / "inputs.npz", tmp_path / "outputs.npz"
  np.savez(inputs, source=source, target=target)
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  r = subprocess.run([sys.executable, "-c", FRESH, str(artifact), str(inputs), str(out)],
                     capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
  assert r.returncode == 0, r.stderr[-3000:]
  return dict(np.load(out))


def _apply(model, variables, src, tgt):
  """Jitted model.apply with the params closed over, as the export bakes them in: XLA folds
  constant weights differently from weights passed as arguments (2.8e-5 px apart on the base
  fixture's flow, the size of the official-parity error), so that is the like-for-like reference."""
  out = jax.jit(lambda a, b: model.apply(variables, a, b))(src, tgt)
  return {k: np.asarray(v) for k, v in out.items()}


def _max_err(a, b):
  return float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max())


@pytest.fixture(scope="module", params=["base", "refine"])
def fixture_model(request, reference_dir):
  d = reference_dir / request.param
  model, variables = snapshot.load_official(d)
  io = np.load(d / "io.npz")
  src, tgt = io["img1_uint8"], io["img2_uint8"]
  ref = _apply(model, variables, src, tgt)
  return dict(kind=request.param, dir=d, model=model, variables=variables, src=src, tgt=tgt,
              ref={k: np.asarray(v) for k, v in ref.items()})


@pytest.mark.slow
def test_stablehlo_roundtrip_in_fresh_process(fixture_model, tmp_path):
  """Base: dynamic batch. Refine: fixed batch 2 with an extra output (batch 1 is padded)."""
  fm = fixture_model
  h, w = fm["src"].shape[1:3]
  art = tmp_path / f"{fm['kind']}.stablehlo"
  refine = fm["kind"] == "refine"
  outputs = ["flow", "covisibility"] + (["flow_before_refinement"] if refine else [])
  assert cli.main(["export", "--checkpoint", str(fm["dir"]), "--snapshot", "--size", f"{h}x{w}",
                   "--out", str(art), "--batch", "2" if refine else "dynamic",
                   "--outputs", ",".join(outputs)]) == 0
  got = _fresh_call(art, fm["src"], fm["tgt"], tmp_path)
  ref_one = ({k: v[:1] for k, v in fm["ref"].items()} if refine else   # padded to batch 2
             _apply(fm["model"], fm["variables"], fm["src"][:1], fm["tgt"][:1]))
  for k in outputs:
    for how in ("raw", "full"):
      err = _max_err(got[f"{how}_{k}"], fm["ref"][k])
      assert got[f"{how}_{k}"].shape == fm["ref"][k].shape and err <= 1e-5, (how, k, err)
    # Like for like: the CPU attention sizes its query chunks by the batch, so a batch of one
    # rounds differently from row 0 of a batch of two (1.5e-5 px on the base fixture).
    assert _max_err(got[f"one_{k}"], ref_one[k]) <= 1e-5, k
  assert sorted(k[4:] for k in got if k.startswith("raw_")) == sorted(outputs)

  meta = json.loads(export.sidecar_path(art).read_text())
  assert meta["format"] == "stablehlo" and meta["input_size"] == [h, w]
  assert meta["batch"] == (2 if refine else "dynamic") and meta["dtype"] == "float32"
  assert set(meta["platforms"]) == {"cpu", "cuda"}
  assert meta["ufm_jax_version"] == ufm_jax.__version__
  assert meta["outputs"]["flow"]["shape"][1:] == [h, w, 2]
  assert meta["model"]["class"] == official_config.CLASS_NAMES[type(fm["model"])]
  cfg = json.loads(json.dumps(dataclasses.asdict(fm["model"].config)))
  assert meta["model"]["config"] == cfg
  assert not list(tmp_path.glob(".*tmp*"))


@pytest.mark.slow
def test_bfloat16_export_runs_the_bf16_model(reference_dir, tmp_path):
  d = reference_dir / "base"
  model, variables = snapshot.load_official(d)
  io = np.load(d / "io.npz")
  src, tgt = io["img1_uint8"][:1], io["img2_uint8"][:1]
  art = tmp_path / "bf16.stablehlo"
  export.export(model, variables, src.shape[1:3], art, dtype="bfloat16")
  got = export.load_exported(art)(src, tgt)
  bf16 = model.clone(config=model.config.replace(dtype="bfloat16"))
  want = _apply(bf16, variables, src, tgt)
  assert _max_err(got["flow"], want["flow"]) <= 1e-5
  f32 = _apply(model, variables, src, tgt)
  assert _max_err(got["flow"], f32["flow"]) > 0  # it did compute in bf16
  assert json.loads(export.sidecar_path(art).read_text())["dtype"] == "bfloat16"


@pytest.mark.slow
def test_export_errors_name_the_problem(reference_dir, tmp_path, capsys):
  d = str(reference_dir / "base")
  assert cli.main(["export", "--checkpoint", d, "--size", "100x154", "--out",
                   str(tmp_path / "a")]) == 2
  assert "multiples of the patch size 14" in capsys.readouterr().err
  assert cli.main(["export", "--checkpoint", d, "--size", "98x154", "--out", str(tmp_path / "a"),
                   "--outputs", "flow,residual"]) == 2
  err = capsys.readouterr().err
  assert "['residual']" in err and "covisibility_logits" in err
  with pytest.raises(SystemExit):
    cli.main(["export", "--checkpoint", d, "--size", "98x154", "--out", "x", "--batch", "0"])
  assert not (tmp_path / "a").exists()

  model, variables = snapshot.load_official(d)
  art = tmp_path / "m.stablehlo"
  export.export(model, variables, (98, 154), art, batch=1)
  run = export.load_exported(art)
  with pytest.raises(ValueError, match="exported for 98x154 images; source is 112x154"):
    run(np.zeros((1, 112, 154, 3), np.uint8), np.zeros((1, 112, 154, 3), np.uint8))
  (tmp_path / "junk.stablehlo").write_bytes(b"not an artifact")
  with pytest.raises(ValueError, match="not a jax.export artifact"):
    export.load_exported(tmp_path / "junk.stablehlo")


# ----------------------------------------------------------------------------------------------
# ONNX (the optional [onnx] extra; part of the test extra, so CI always runs these)


def _need_onnx():
  testing.require_extra("onnx", ("jax2onnx", "onnxruntime"))


def _onnx_parity(fm, tmp_path, batch):
  _need_onnx()
  h, w = fm["src"].shape[1:3]
  out = tmp_path / f"{fm['kind']}.onnx"
  assert cli.main(["export", "--checkpoint", str(fm["dir"]), "--size", f"{h}x{w}", "--out",
                   str(out), "--format", "onnx", "--batch", str(batch)]) == 0
  import onnxruntime as ort
  sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
  ins = {i.name: (i.shape, i.type) for i in sess.get_inputs()}
  assert ins == {n: ([batch, h, w, 3], "tensor(uint8)") for n in ("source", "target")}
  assert [o.name for o in sess.get_outputs()] == ["flow", "covisibility"]
  flow, covis = sess.run(["flow", "covisibility"], {"source": fm["src"], "target": fm["tgt"]})
  assert flow.shape == (len(fm["src"]), h, w, 2) and flow.dtype == np.float32
  assert _max_err(flow, fm["ref"]["flow"]) <= 1e-3
  assert _max_err(covis, fm["ref"]["covisibility"]) <= 1e-4
  got = ufm_jax.load_exported(out)(fm["src"][0], fm["tgt"][0])  # one HWC pair, padded to the batch
  assert _max_err(got["flow"], flow[0]) <= 1e-5
  assert json.loads(export.sidecar_path(out).read_text())["format"] == "onnx"


@pytest.mark.slow
def test_onnx_matches_apply_base(reference_dir, tmp_path):
  model, variables = snapshot.load_official(reference_dir / "base")
  io = np.load(reference_dir / "base" / "io.npz")
  src, tgt = io["img1_uint8"], io["img2_uint8"]
  fm = dict(kind="base", dir=reference_dir / "base", src=src, tgt=tgt,
            ref=_apply(model, variables, src, tgt))
  _onnx_parity(fm, tmp_path, 2)


@pytest.mark.slow
def test_onnx_matches_apply_refine(reference_dir, tmp_path):
  """The refinement's windowed gather and the U-Net's max-pool convert too (fixed batch 2)."""
  model, variables = snapshot.load_official(reference_dir / "refine")
  io = np.load(reference_dir / "refine" / "io.npz")
  src, tgt = io["img1_uint8"], io["img2_uint8"]
  fm = dict(kind="refine", dir=reference_dir / "refine", src=src, tgt=tgt,
            ref=_apply(model, variables, src, tgt))
  _onnx_parity(fm, tmp_path, 2)


def test_onnx_graph_computes_the_model_once(reference_dir, tmp_path, monkeypatch):
  """The function handed to jax2onnx runs the forward once for all its outputs: a copy of the
  model per output made the converter's quadratic transpose pass take 106 s instead of 11 on the
  base structure with three outputs (it merges the copies only after that pass)."""
  model, variables = snapshot.load_official(reference_dir / "base")
  model = ufm.model_from_config(ufm.with_flow_covariance(model.config))
  variables = testing.perturbed_params(model, 0)
  seen = {}
  monkeypatch.setattr(export, "write_onnx",
                      lambda fn, specs, *a: seen.update(fn=fn, specs=specs, names=a[1]))
  export.export_onnx(model, variables, (28, 42), tmp_path / "m.onnx", batch=1)
  assert seen["names"] == ("flow", "covisibility", "flow_covariance")

  def convs(fn, specs):
    jaxpr = jax.make_jaxpr(fn)(*specs).jaxpr
    return sum(e.primitive.name == "conv_general_dilated" for e, _ in export._equations(jaxpr))

  once = convs(lambda s, t: model.apply(ufm.variables(variables), s, t), seen["specs"])
  assert once > 0 and convs(seen["fn"], seen["specs"]) == once


def test_onnx_dynamic_batch_is_refused_with_the_alternative(reference_dir, tmp_path, capsys):
  assert cli.main(["export", "--checkpoint", str(reference_dir / "base"), "--size", "98x154",
                   "--out", str(tmp_path / "m.onnx"), "--format", "onnx", "--batch", "dynamic"]) == 2
  assert "fixed --batch N" in capsys.readouterr().err and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_onnx_failure_names_primitive_and_model_part(tmp_path):
  _need_onnx()

  class Head(nn.Module):
    @nn.compact
    def __call__(self, x):  # full SVD of a 3x3: a primitive jax2onnx cannot convert
      return jnp.linalg.svd(nn.Dense(3)(x).reshape(3, 3))[0]

  class Net(nn.Module):
    @nn.compact
    def __call__(self, x):
      return Head(name="head")(nn.Dense(3, name="stem")(x))

  net = Net()
  variables = net.init(jax.random.key(0), jnp.ones((3, 3)))
  out = tmp_path / "svd.onnx"
  with pytest.raises(export.ExportError, match=r"primitive 'svd' in model part Net/head"):
    export.write_onnx(lambda x: (net.apply(variables, x),),
                      [jax.ShapeDtypeStruct((3, 3), jnp.float32)], ["x"], ["y"], out)
  assert list(tmp_path.iterdir()) == []  # nothing half-written
