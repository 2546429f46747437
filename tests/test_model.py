"""UFM module behaviour: symmetrized batches, input errors, bf16, remat, sharding hook."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.training import trainer
from ufm_jax.models import dinov2, info_sharing, ufm, variants
from ufm_jax.official import snapshot



@pytest.fixture(scope="module")
def fixture(reference_dir):
  model, variables = snapshot.load_official(reference_dir / "base")
  params = variables["params"]
  io = dict(np.load(reference_dir / "base" / "io.npz"))
  return model, params, io


@pytest.mark.parametrize("shape,dtype,match", [
    ((98, 154, 3), np.uint8, r"rank 3.*expected rank 4"),
    ((1, 98, 154, 4), np.uint8, r"\(1, 98, 154, 4\).*3 channels"),
    ((1, 98, 154, 3), np.int32, r"dtype int32; expected uint8 or float"),
    ((1, 100, 154, 3), np.uint8, r"\(1, 100, 154, 3\).*multiples of the patch size 14"),
])
def test_input_errors(fixture, shape, dtype, match):
  model, params, _ = fixture
  x = np.zeros(shape, dtype)
  with pytest.raises(ValueError, match=match):
    model.apply({"params": params}, x, x)


def test_mismatched_views_and_odd_symmetrized_batch(fixture):
  model, params, _ = fixture
  a = np.zeros((1, 98, 154, 3), np.uint8)
  with pytest.raises(ValueError, match=r"source shape \(1, 98, 154, 3\) != target shape"):
    model.apply({"params": params}, a, np.zeros((1, 98, 140, 3), np.uint8))
  with pytest.raises(ValueError, match="even batch"):
    model.apply({"params": params}, a, a, symmetrized=True)


def test_bfloat16_compute(fixture):
  model, params, io = fixture
  m16 = model.clone(config=model.config.replace(dtype="bfloat16"))
  a, b = io["img1_uint8"], io["img2_uint8"]
  jaxpr = jax.make_jaxpr(lambda p: m16.apply({"params": p}, a, b))(params)
  def eqns(j):  # into sub-jaxprs too: on CPU the Dense dots sit in a platform_dependent branch
    for e in j.eqns:
      yield e
      for v in e.params.values():
        for sub in v if isinstance(v, (tuple, list)) else (v,):
          if hasattr(sub, "eqns"):
            yield from eqns(sub)
  dots = [e for e in eqns(jaxpr.jaxpr) if e.primitive.name == "dot_general"]
  assert any(e.invars[0].aval.dtype == jnp.bfloat16 for e in dots)  # encoder/fusion matmuls
  out = jax.jit(m16.apply)({"params": params}, a, b)
  assert out["flow"].dtype == jnp.float32 and out["covisibility_logits"].dtype == jnp.float32
  assert all(p.dtype == jnp.float32 for p in jax.tree.leaves(params))
  # bf16 has ~3 significant digits: close to the float32 reference, not equal.
  flow = np.asarray(out["flow"]).transpose(0, 3, 1, 2)
  err = np.abs(flow - io["flow"])
  assert err.mean() < 0.05 * np.abs(io["flow"]).mean() and err.max() < 1.0, err.max()


def test_remat_same_values_and_gradients():
  # remat wraps every transformer block (encoder and fusion use the same Block class)
  cfg = info_sharing.InfoSharingConfig(input_embed_dim=32, dim=32, depth=2, num_heads=2,
                                       indices=(0, 1))
  rng = np.random.default_rng(0)
  f1, f2 = (rng.standard_normal((1, 2, 3, 32)).astype(np.float32) for _ in range(2))
  plain, rem = info_sharing.InfoSharing(cfg), info_sharing.InfoSharing(cfg, remat=True)
  shapes = jax.eval_shape(lambda a, b: plain.init(jax.random.PRNGKey(0), a, b), f1, f2)["params"]
  params = jax.tree.map(lambda s: rng.standard_normal(s.shape).astype(np.float32) * 0.2, shapes)

  def loss(m):
    def f(p):
      (a, b), inters = m.apply({"params": p}, f1, f2)
      return jnp.sum(a ** 2) + jnp.sum(inters[0][1] * b)
    return f

  l0, g0 = jax.jit(jax.value_and_grad(loss(plain)))(params)
  l1, g1 = jax.jit(jax.value_and_grad(loss(rem)))(params)
  np.testing.assert_allclose(l1, l0, rtol=1e-6)
  jax.tree.map(lambda x, y: np.testing.assert_allclose(
      x, y, rtol=0, atol=1e-5 * max(1.0, float(np.abs(y).max()))), g1, g0)


def test_covisibility_head_is_gradient_stopped():
  # official detach_uncertainty_head: the covisibility loss trains only its own head
  model = ufm.model_from_config(variants.tiny())
  params = trainer.random_params(model)
  rng = np.random.default_rng(0)
  feats = [rng.standard_normal((1, 2, 2, 64)).astype(np.float32) for _ in range(4)]

  def loss(f, key):
    return jnp.sum(model.apply({"params": params}, f, (28, 28), method=ufm.UFM.heads)[key])

  g_cov, g_flow = jax.jit(lambda f: (jax.grad(loss)(f, "covisibility_logits"),
                                     jax.grad(loss)(f, "flow")))(feats)
  assert all(not np.any(np.asarray(g)) for g in g_cov)
  assert all(np.any(np.asarray(g)) for g in g_flow)
  nodetach = model.clone(config=model.config.replace(detach_uncertainty_head=False))
  g = jax.jit(jax.grad(lambda f: jnp.sum(nodetach.apply(
      {"params": params}, f, (28, 28), method=ufm.UFM.heads)["covisibility_logits"])))(feats)
  assert all(np.any(np.asarray(x)) for x in g)


def test_activation_sharding_hook_called_at_block_boundaries():
  cfg = variants.tiny()
  calls = []

  def hook(x):
    calls.append(x.shape)
    return x

  model = ufm.UFM(cfg, activation_sharding=hook)
  x = jax.ShapeDtypeStruct((2, 28, 42, 3), jnp.uint8)
  jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b), x, x)
  calls.clear()
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b), x, x)
  params = shapes["params"]
  calls.clear()
  jax.eval_shape(lambda p, a, b: model.apply({"params": p}, a, b), params, x, x)
  enc = [s for s in calls if s == (4, 1 + 2 * 3, 64)]  # both views as one batch, cls + 6 patches
  fus = [s for s in calls if s == (2, 2 * 2 * 3, 64)]  # both views' tokens concatenated
  # encoder: after the embedding and after each of its blocks; fusion: likewise
  assert len(enc) == 1 + cfg.encoder.depth and len(fus) == 1 + cfg.info_sharing.depth


def test_antialiased_pos_embed_weights_hand_computed():
  # The *_reg hub models: bicubic (A=-0.5) with antialias. 4 -> 2: scale 2, support 4, window
  # [0, 4) for output 0 centred at 1.0, taps at (j - 1 + 0.5) / 2 = -0.25, 0.25, 0.75, 1.25.
  w = np.array([0.8671875, 0.8671875, 0.2265625, -0.0703125])
  m = dinov2._bicubic_aa_matrix(4, 2)
  np.testing.assert_allclose(m[0], w / w.sum(), rtol=1e-12)
  np.testing.assert_allclose(m[1], (w / w.sum())[::-1], rtol=1e-12)
  np.testing.assert_allclose(dinov2._bicubic_aa_matrix(5, 5), np.eye(5), atol=1e-12)


def test_pos_embed_offset_mapping_hand_computed():
  # scale_factor=(n + 0.1)/G: src = (dst + 0.5) * G/(n + 0.1) - 0.5. G=4, n=2: dst 0 -> 0.4756...
  m = dinov2._bicubic_matrix(4, 2, 4 / 2.1, np.float64)
  src = 0.5 * 4 / 2.1 - 0.5
  t = src - np.floor(src)
  a = -0.75
  c1 = lambda x: ((a + 2) * x - (a + 3)) * x * x + 1
  c2 = lambda x: ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
  taps = [c2(t + 1), c1(t), c1(1 - t), c2(2 - t)]  # at indices -1 (clamped to 0), 0, 1, 2
  want = np.array([taps[0] + taps[1], taps[2], taps[3], 0.0])
  np.testing.assert_allclose(m[0], want, rtol=1e-12)
