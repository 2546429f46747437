"""UFM base model vs the official PyTorch run (fixtures/ufm_reference/base), stage by stage."""

import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from ufm_jax.official import snapshot

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", params=[False, True], ids=["unrolled", "scan"])
def base(reference_dir, request):
  """The official snapshot, run per layer and as the scan model (stacked params); both must
  match the official stages, the scan one through its per-block scan outputs."""
  d = reference_dir / "base"
  model, variables = snapshot.load_official(d)
  params = variables["params"]
  if request.param:
    from ufm_jax.models import scan
    model = model.clone(config=model.config.replace(scan_blocks=True))
    params = scan.stack_blocks(params, model.config)
    assert "blocks" in params["encoder"] and "self_attention_blocks" in params["info_sharing"]
  io = dict(np.load(d / "io.npz"))
  inter = dict(np.load(d / "intermediates.npz"))
  fwd = jax.jit(lambda p, a, b: model.apply({"params": p}, a, b, mutable=["intermediates"]))
  out, state = fwd(params, io["img1_uint8"], io["img2_uint8"])
  return dict(model=model, params=params, io=io, inter=inter, out=out,
              sown=state["intermediates"], dir=d, fwd=fwd)


def _nchw(x):
  return np.asarray(x).transpose(0, 3, 1, 2)


def _close(name, got, want, atol):
  got = np.asarray(got)
  assert got.shape == want.shape, f"{name}: shape {got.shape} != {want.shape}"
  err = float(np.abs(got.astype(np.float64) - want).max())
  assert err <= atol, f"{name}: max |diff| {err:.3g} > {atol:.3g}"


def test_normalisation_matches_official(base):
  from ufm_jax.models import ufm
  io = base["io"]
  got = _nchw(ufm.normalize(io["img1_uint8"]))
  np.testing.assert_array_equal(got, io["img1_norm"])


def _official_batch(x):
  """Our encoder batch interleaves the views (s0, t0, s1, t1, ...: each pair's rows stay on one
  device when sharded); the official one is [view1; view2]."""
  x = np.asarray(x)
  return np.concatenate([x[0::2], x[1::2]])


def test_encoder_stages(base):
  e, ref = base["sown"]["encoder"], base["inter"]
  _close("patch_embed", _official_batch(e["patch_embed_tokens"][0]), ref["enc_patch_embed_tokens"],
         1e-4)
  _close("pos_embed_interp", e["pos_embed_interp"][0], ref["enc_pos_embed_interp"], 1e-6)
  _close("tokens_in", _official_batch(e["tokens_in"][0]), ref["enc_tokens_in"], 1e-4)
  _close("block0", _official_batch(e["block0_out"][0]), ref["enc_block0_out"], 1e-4)
  _close("block1", _official_batch(e["block1_out"][0]), ref["enc_block1_out"], 1e-4)


def test_encoder_outputs_with_final_norm(base):
  e, ref = base["sown"]["encoder"], base["inter"]
  for i in range(2):  # encoder indices [0, 1]; both views encoded as one (interleaved) batch
    o = np.asarray(e[f"out{i}"][0])
    _close(f"enc_out{i}_view1", _nchw(o[0::2]), ref[f"enc_out{i}_view1"], 1e-4)
    _close(f"enc_out{i}_view2", _nchw(o[1::2]), ref[f"enc_out{i}_view2"], 1e-4)


def test_info_sharing_stages(base):
  s, ref = base["sown"]["info_sharing"], base["inter"]
  _close("proj_embed", s["proj_embed_out"][0], ref["is_proj_embed_out"], 1e-4)
  _close("tokens_in", s["tokens_in"][0], ref["is_tokens_in"], 1e-4)
  for i in range(4):
    _close(f"block{i}", s[f"block{i}_out"][0], ref[f"is_block{i}_out"], 1e-4)


def test_info_sharing_outputs(base):
  s, ref = base["sown"]["info_sharing"], base["inter"]
  fin1, fin2 = s["final"][0]
  _close("final_view1", _nchw(fin1), ref["is_final_view1"], 1e-4)
  _close("final_view2", _nchw(fin2), ref["is_final_view2"], 1e-4)
  for i in range(2):
    for v in range(2):
      _close(f"inter{i}_view{v + 1}", _nchw(s[f"inter{i}"][0][v]), ref[f"is_inter{i}_view{v + 1}"],
             1e-4)


@pytest.mark.parametrize("head,name", [("head1", "head1"), ("uncertainty_head", "uncertainty_head")])
def test_dpt_stages(base, head, name):
  # DPT activations grow to O(100) with the fixture's He-init: 1e-4 relative to the largest value.
  s, ref = base["sown"][f"{head}_0_0"], base["inter"]
  keys = [f"layer{k}" for k in range(4)] + [f"refinenet{k}_out" for k in (4, 3, 2, 1)]
  for k in keys:
    want = ref[f"{name}_dpt_{k}"]
    _close(k, _nchw(s[k][0]), want, 1e-4 * max(1.0, float(np.abs(want).max())))
  want = ref[f"{name}_proc_conv1_out"]
  _close("proc_conv1", _nchw(base["sown"][f"{head}_0_1"]["conv1_out"][0]), want,
         1e-4 * float(np.abs(want).max()))


def test_flow_head_channels(base):
  ref = base["inter"]
  _close("decoded_channels", _nchw(base["sown"]["flow_decoded_channels"][0]),
         ref["head1_decoded_channels"], 1e-4)


def test_forward_outputs(base):
  out, io = base["out"], base["io"]
  assert out["flow"].dtype == np.float32
  _close("flow", _nchw(out["flow"]), io["flow"], 1e-3)
  _close("covisibility_logits", np.asarray(out["covisibility_logits"])[:, None],
         io["covisibility_logits"], 2e-4)
  _close("covisibility", np.asarray(out["covisibility"])[:, None], io["covisibility_mask"], 5e-5)


def test_symmetrized_equals_plain(base):
  # (a,b),(b,a),(c,d),(d,c): each image encoded once, features interleaved (official path)
  model, params, io = base["model"], base["params"], base["io"]
  a, b, c, d = io["img1_uint8"][0], io["img2_uint8"][0], io["img1_uint8"][1], io["img2_uint8"][1]
  sym = jax.jit(lambda p, s, t: model.apply({"params": p}, s, t, symmetrized=True))(
      params, np.stack([a, b, c, d]), np.stack([b, a, d, c]))
  plain_fwd = base["out"]  # pairs (a,b), (c,d)
  plain_bwd = base["fwd"](params, np.stack([b, d]), np.stack([a, c]))[0]  # pairs (b,a), (d,c)
  # The heads run on 4 rows here and 2 there: XLA:CPU's convolutions (XNNPACK since jax 0.10) round
  # differently per batch size, so "equal" is float32 rounding relative to the output's scale.
  for k in plain_fwd:
    for got, want in ((np.asarray(sym[k])[0::2], np.asarray(plain_fwd[k])),
                      (np.asarray(sym[k])[1::2], np.asarray(plain_bwd[k]))):
      np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * max(1.0, np.abs(want).max()))


def test_float_input_normalisation(base):
  # float 0..255 input takes the arithmetic path (XLA may use reciprocals: ulp-level only).
  from ufm_jax.models import ufm
  io = base["io"]
  got = _nchw(jax.jit(ufm.normalize)(io["img1_uint8"].astype(np.float32)))
  np.testing.assert_allclose(got, io["img1_norm"], rtol=0, atol=2e-6)


@pytest.mark.parametrize("scan_blocks", [False, True], ids=["unrolled", "scan"])
def test_float64_matches_official_float64_run(reference_dir, scan_blocks):
  """The whole pass in float64 (x64 must be enabled before jax starts: a subprocess)."""
  script = textwrap.dedent(f"""
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from ufm_jax.models import scan
    from ufm_jax.official import snapshot
    d = {str(reference_dir / "base")!r}
    model, variables = snapshot.load_official(d)
    model = model.clone(config=model.config.replace(dtype="float64", scan_blocks={scan_blocks}))
    params = scan.to_layout(variables["params"], model.config)
    params = jax.tree.map(lambda p: np.asarray(p, np.float64), params)
    io = np.load(d + "/io_f64.npz")
    out = jax.jit(model.apply)({{"params": params}}, io["img1_uint8"], io["img2_uint8"])
    flow = np.asarray(out["flow"]).transpose(0, 3, 1, 2)
    assert flow.dtype == np.float64, flow.dtype
    logits = np.asarray(out["covisibility_logits"])[:, None]
    print(np.abs(flow - io["flow"]).max() / np.abs(io["flow"]).max(),
          np.abs(logits - io["covisibility_logits"]).max() / np.abs(io["covisibility_logits"]).max())
  """)
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
             JAX_PLATFORMS="cpu")
  res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                       timeout=300)
  assert res.returncode == 0, res.stderr[-3000:]
  rel_flow, rel_logits = map(float, res.stdout.split()[-2:])
  # float64 end to end: agreement to ~1e-9 relative (float32 would be ~1e-6).
  assert rel_flow < 1e-9 and rel_logits < 1e-9, (rel_flow, rel_logits)
