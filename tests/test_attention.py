"""The CPU attention path (layers.cpu_attention) against jax.nn.dot_product_attention."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.models import layers


def _qkv(b, n, m, h, d, dtype=jnp.float32, seed=0):
  r = np.random.default_rng(seed)
  q = r.standard_normal((b, n, h, d)) * 2
  k, v = r.standard_normal((b, m, h, d)) * 2, r.standard_normal((b, m, h, d))
  return tuple(jnp.asarray(x, dtype) for x in (q, k, v))


def _xla(q, k, v):
  return jax.nn.dot_product_attention(q, k, v, scale=q.shape[-1] ** -0.5, implementation="xla")


@pytest.mark.parametrize("b,n,m,h,d,tile", [
    (2, 37, 37, 3, 8, layers.CPU_ATTENTION_TILE),   # one chunk
    (2, 37, 37, 3, 8, 500),                           # 6 chunks of 7 queries, the last overlapping by 5
    (3, 16, 29, 2, 16, 100),                          # cross attention, keys != queries
])
def test_cpu_attention_equals_xla(b, n, m, h, d, tile):
  q, k, v = _qkv(b, n, m, h, d)
  out = jax.jit(lambda q, k, v: layers.cpu_attention(q, k, v, d ** -0.5, tile))(q, k, v)
  assert out.shape == (b, n, h, d)
  np.testing.assert_allclose(out, _xla(q, k, v), atol=2e-6, rtol=2e-6)


def test_cpu_attention_gradients_and_bf16():
  q, k, v = _qkv(2, 21, 21, 2, 8)
  loss = lambda f: lambda q, k, v: jnp.sum(f(q, k, v) * jnp.cos(q))  # noqa: E731
  g_cpu = jax.grad(loss(lambda q, k, v: layers.cpu_attention(q, k, v, 8 ** -0.5, 200)),
                   argnums=(0, 1, 2))(q, k, v)
  g_xla = jax.grad(loss(_xla), argnums=(0, 1, 2))(q, k, v)
  for a, b in zip(g_cpu, g_xla):
    np.testing.assert_allclose(a, b, atol=1e-5, rtol=1e-5)
  qb, kb, vb = (x.astype(jnp.bfloat16) for x in (q, k, v))
  out = layers.cpu_attention(qb, kb, vb, 8 ** -0.5)
  assert out.dtype == jnp.bfloat16
  np.testing.assert_allclose(np.asarray(out, np.float32), _xla(q, k, v), atol=0.05)


def test_auto_attention_takes_the_cpu_path_here():
  """In auto mode the jitted CPU program holds the loop (a while op), forcing "xla" does not;
  both give the same numbers."""
  q, k, v = _qkv(1, 30, 30, 2, 8)
  fwd = lambda impl: jax.jit(lambda q, k, v: layers.dot_product_attention(q, k, v, 8 ** -0.5, impl))  # noqa: E731
  assert " while(" in fwd(None).lower(q, k, v).compile().as_text()
  assert " while(" not in fwd("xla").lower(q, k, v).compile().as_text()
  np.testing.assert_allclose(fwd(None)(q, k, v), fwd("xla")(q, k, v), atol=2e-6, rtol=2e-6)


def _fused_like_jax_cudnn(calls):
  """A stand-in for jax's cuDNN attention on CPU: XLA's numbers, and like the real one
  (jax 0.11.2) it refuses to be differentiated when a sequence length is odd."""
  def fused(q, k, v, scale):
    calls.append(q.shape[1])

    @jax.custom_jvp
    def f(q, k, v):
      return jax.nn.dot_product_attention(q, k, v, scale=scale, implementation="xla")

    @f.defjvp
    def f_jvp(primals, tangents):
      if primals[0].shape[1] % 2 or primals[1].shape[1] % 2:
        raise NotImplementedError(f"Unsupported sequence length Q {primals[0].shape[1]}")
      return jax.jvp(lambda *a: jax.nn.dot_product_attention(*a, scale=scale, implementation="xla"),
                     primals, tangents)
    return f(q, k, v)
  return fused


@pytest.mark.parametrize("n", [21, 20])
def test_cudnn_path_trains_at_odd_sequence_lengths(monkeypatch, n):
  """The encoder's 1 + h*w tokens are odd at 420x560 (1201): the fused kernel runs the forward,
  XLA's attention gives the gradient; even lengths keep the fused kernel's own gradient."""
  calls = []
  fused = _fused_like_jax_cudnn(calls)
  q, k, v = _qkv(2, n, n, 2, 8)
  loss = lambda f: lambda q, k, v: jnp.sum(f(q, k, v) * jnp.cos(q))  # noqa: E731
  if n % 2:  # the stand-in fails the way the real kernel does, so the test can fail
    with pytest.raises(NotImplementedError, match="Unsupported sequence length"):
      jax.grad(loss(lambda q, k, v: fused(q, k, v, 8 ** -0.5)))(q, k, v)
  monkeypatch.setattr(layers, "_cudnn_attention", fused)
  calls.clear()
  ours = lambda q, k, v: layers.dot_product_attention(q, k, v, 8 ** -0.5, "cudnn")  # noqa: E731
  # Under jit, remat and scan, as the model's blocks run it.
  body = jax.checkpoint(lambda c, _: (ours(c, k, v), None))
  stacked = lambda q, k, v: jax.lax.scan(body, q, None, length=2)[0]  # noqa: E731
  g = jax.jit(jax.grad(loss(stacked), argnums=(0, 1, 2)))(q, k, v)
  assert calls and set(calls) == {n}
  ref_body = jax.checkpoint(lambda c, _: (_xla(c, k, v), None))
  g_ref = jax.grad(loss(lambda q, k, v: jax.lax.scan(ref_body, q, None, length=2)[0]),
                   argnums=(0, 1, 2))(q, k, v)
  for a, b in zip(g, g_ref):
    np.testing.assert_allclose(a, b, atol=1e-5, rtol=1e-5)
  np.testing.assert_allclose(jax.jit(ours)(q, k, v), _xla(q, k, v), atol=1e-6)
