"""The bf16 CPU path: every contraction as bf16 x bf16 -> f32 dots on CPU, nothing else changed.

XLA:CPU runs bf16 dots with float32 accumulation on its bf16 units; a bf16 convolution it compiles
as a float32 one. So on CPU the model's bf16 convolutions are dots (layers.conv_as_dots), chosen
when lowering for CPU only: other platforms keep XLA's convolution, and float32 keeps it
everywhere (the parity tests hold float32 to the official fixtures).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.models import layers
from ufm_jax.official import snapshot

NHWC = ("NHWC", "HWIO", "NHWC")

# (input [b, h, w, c], kernel [kh, kw, c, o], strides, padding): the model's kinds (3x3 same,
# 3x3 stride 2, the patch embedding, 1x1) and odd ones (uneven padding, a non-square kernel).
CASES = [
    ((2, 9, 11, 5), (3, 3, 5, 7), (1, 1), ((1, 1), (1, 1))),
    ((1, 10, 13, 4), (3, 3, 4, 6), (2, 2), ((1, 1), (1, 1))),
    ((2, 28, 42, 3), (14, 14, 3, 8), (14, 14), ((0, 0), (0, 0))),
    ((1, 7, 9, 6), (1, 1, 6, 4), (1, 1), ((0, 0), (0, 0))),
    ((1, 9, 10, 3), (2, 3, 3, 4), (1, 2), ((0, 1), (2, 0))),
]


@pytest.mark.parametrize("xs,ks,strides,padding", CASES)
@pytest.mark.parametrize("tile", [None, 1, 40, 10**9])
def test_conv_as_dots_is_the_convolution(xs, ks, strides, padding, tile):
  rng = np.random.default_rng(0)
  x, k = rng.standard_normal(xs).astype(np.float32), rng.standard_normal(ks).astype(np.float32)
  ref = jax.lax.conv_general_dilated(x, k, strides, padding, dimension_numbers=NHWC,
                                     precision="highest")
  kw = {} if tile is None else dict(tile=tile)
  got = jax.jit(lambda x, k: layers.conv_as_dots(x, k, strides, padding, **kw))(x, k)
  assert got.dtype == jnp.float32
  np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-5, atol=1e-4)


def _lowered(fn, *args, platform):
  return jax.jit(fn).trace(*args).lower(lowering_platforms=(platform,)).as_text()


def _conv(x, k):
  return layers.conv_general_dilated(x, k, (1, 1), ((1, 1), (1, 1)), dimension_numbers=NHWC)


def test_bf16_convolution_is_dots_on_cpu_only():
  rng = np.random.default_rng(1)
  x = jnp.asarray(rng.standard_normal((1, 6, 7, 160)), jnp.bfloat16)
  k = jnp.asarray(rng.standard_normal((3, 3, 160, 160)) * 0.05, jnp.bfloat16)
  out = jax.jit(_conv)(x, k)
  assert out.dtype == jnp.bfloat16
  # Each dot accumulates in float32 and the result is rounded once: the float32 convolution of
  # the same bf16 values, rounded to bf16, up to one bf16 rounding (2^-8 relative).
  ref = jax.lax.conv_general_dilated(x.astype(jnp.float32), k.astype(jnp.float32), (1, 1),
                                     ((1, 1), (1, 1)), dimension_numbers=NHWC,
                                     precision="highest")
  np.testing.assert_allclose(np.asarray(out, np.float32), np.asarray(ref),
                             rtol=2**-8, atol=2**-8 * float(jnp.abs(ref).max()))
  cpu = _lowered(_conv, x, k, platform="cpu")
  assert "stablehlo.convolution" not in cpu
  assert "(tensor<42x1440xbf16>, tensor<1440x160xbf16>) -> tensor<42x160xf32>" in cpu
  for platform in ("cuda", "tpu"):
    other = _lowered(_conv, x, k, platform=platform)
    assert "stablehlo.convolution" in other and "stablehlo.dot_general" not in other, platform
  # float32 is XLA's convolution on every platform, and so is a narrow bf16 one on CPU
  x32, k32 = x.astype(jnp.float32), k.astype(jnp.float32)
  assert "stablehlo.convolution" in _lowered(_conv, x32, k32, platform="cpu")
  narrow = (x[..., :64], k[:, :, :64, :64])
  assert "stablehlo.convolution" in _lowered(_conv, *narrow, platform="cpu")


def _kernels(text):
  """(c_in, c_out) of every stablehlo.convolution of a lowered module (HWIO kernels)."""
  import re
  return [tuple(int(v) for v in m.groups()) for m in re.finditer(
      r"stablehlo\.convolution.*tensor<\d+x\d+x\d+x\d+x\w+>, tensor<\d+x\d+x(\d+)x(\d+)x", text)]


@pytest.mark.slow
def test_ufm_base_bf16_lowering_on_cpu():
  """UFM-Refine's structure in bf16 (dtype and head_dtype), lowered for CPU (abstract params,
  nothing runs): the convolutions left to XLA are the narrow ones, and every dot but the
  position-table resize (float32 HIGHEST on purpose) takes bf16 operands; lowered for a GPU
  the same model keeps all its convolutions."""
  from ufm_jax.models import ufm, variants
  model = variants.build_model("ufm_refine", dtype="bfloat16", head_dtype="bfloat16")
  params = ufm.param_shapes(model)
  img = jax.ShapeDtypeStruct((1, 56, 84, 3), jnp.uint8)
  fwd = lambda p, a, b: model.apply({"params": p}, a, b)  # noqa: E731
  cpu = _lowered(fwd, params, img, img, platform="cpu")
  narrow = _kernels(cpu)
  assert narrow and all(c * o <= layers.CPU_CONV_MIN_WIDTH * (c + o) for c, o in narrow), narrow
  dots = [line.rsplit(":", 1)[-1] for line in cpu.splitlines() if "stablehlo.dot_general" in line]
  # the two einsums of interpolate_pos_embed, and the local refinement's (float32, as official)
  wide = [d for d in dots if d.count("xbf16>") < 2 and "x7x7x" not in d]
  assert len(dots) > 100 and len(wide) <= 6, wide
  assert len(_kernels(_lowered(fwd, params, img, img, platform="cuda"))) > 2 * len(narrow)


@pytest.mark.slow
def test_refine_bf16_close_to_the_fixture(reference_dir):
  """UFM-Refine with dtype and head_dtype bf16 (the official code under CPU autocast), held to
  the bf16 bound of test_model.test_bfloat16_compute against the official float32 outputs:
  mean flow error under 5% of the mean flow, and before the refinement at most 1 px anywhere.
  The refined flow has no max bound: its 7 x 7 window softmax can move a pixel's pick by a
  tap (several px) where two taps score within bf16 rounding of each other (already so with
  dtype bf16 and float32 heads)."""
  model, variables = snapshot.load_official(reference_dir / "refine")
  params = variables["params"]
  io = dict(np.load(reference_dir / "refine" / "io.npz"))
  m16 = model.clone(config=model.config.replace(dtype="bfloat16", head_dtype="bfloat16"))
  out = jax.jit(lambda p: m16.apply({"params": p}, io["img1_uint8"], io["img2_uint8"]))(params)
  for key in ("flow", "flow_before_refinement", "covisibility", "feature_map_0"):
    assert out[key].dtype == jnp.float32, key
  nchw = lambda k: np.asarray(out[k]).transpose(0, 3, 1, 2)  # noqa: E731
  for key, max_px in (("flow", None), ("flow_before_refinement", 1.0)):
    err = np.abs(nchw(key) - io[key])
    assert err.mean() < 0.05 * np.abs(io[key]).mean(), (key, err.mean())
    assert max_px is None or err.max() < max_px, (key, err.max())
  covis = np.abs(np.asarray(out["covisibility"]) - io["covisibility_mask"][:, 0])
  assert covis.mean() < 0.05, covis.mean()
