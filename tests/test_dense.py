"""layers.dot_general / layers.Dense: low-precision matmuls on CPU accumulate into float32."""

import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.models import layers


def _operands(dtype, seed=0):
  r = np.random.default_rng(seed)
  x = jnp.asarray(r.standard_normal((5, 96, 64)), dtype)
  w = jnp.asarray(r.standard_normal((64, 48)) / 8, dtype)
  return x, w


def test_bf16_dense_lowers_to_a_float32_accumulating_dot_on_cpu():
  x, w = _operands(jnp.bfloat16)
  dense = layers.Dense(48, dtype=jnp.bfloat16)
  params = dense.init(jax.random.PRNGKey(0), x)
  lowered = jax.jit(dense.apply).lower(params, x)
  # Lowered for the cpu alone: only the cpu branch, whose dot takes bf16 and yields f32.
  dots = [l for l in lowered.as_text().splitlines() if "stablehlo.dot_general" in l]
  assert dots and all("xbf16>) -> tensor<5x96x48xf32>" in l for l in dots), dots
  # Compiled for one platform the switch is folded away: one f32-result dot, no conditional.
  compiled = lowered.compile().as_text()
  assert "conditional" not in compiled
  assert " = f32[480,48]{1,0} dot(" in compiled and " = bf16[480,48]{1,0} dot(" not in compiled
  out = dense.apply(params, x)
  assert out.dtype == jnp.bfloat16 and out.shape == (5, 96, 48)


def test_bf16_dot_general_rounds_the_exact_float32_product():
  x, w = _operands(jnp.bfloat16)
  dims = (((2,), (0,)), ((), ()))
  got = jax.jit(lambda a, b: layers.dot_general(a, b, dims))(x, w)
  # bf16 x bf16 products are exact in float32; only the summation order may differ.
  ref = jax.lax.dot_general(x.astype(jnp.float32), w.astype(jnp.float32), dims)
  assert got.dtype == jnp.bfloat16
  np.testing.assert_allclose(np.asarray(got, np.float32), np.asarray(ref.astype(jnp.bfloat16),
                             np.float32), rtol=1e-2, atol=1e-2)


def test_float32_and_explicit_preferred_type_are_plain_dots():
  dims = (((2,), (0,)), ((), ()))
  x, w = _operands(jnp.float32)
  got = jax.jit(lambda a, b: layers.dot_general(a, b, dims))(x, w)
  np.testing.assert_array_equal(got, jax.jit(lambda a, b: jax.lax.dot_general(a, b, dims))(x, w))
  xb, wb = _operands(jnp.bfloat16)
  out = layers.dot_general(xb, wb, dims, preferred_element_type=jnp.bfloat16)
  assert out.dtype == jnp.bfloat16
  hlo = jax.jit(lambda a, b: layers.dot_general(a, b, dims)).lower(x, w).as_text()
  assert "stablehlo.case" not in hlo   # float32: no platform switch at all
