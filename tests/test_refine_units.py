"""Unit tests of the refiner's pieces against independent numpy reimplementations of torch ops."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ufm_jax.official import keymap
from ufm_jax.models import refine

A = -0.75


def np_grid_sample_bicubic(inp, gx, gy):
  """torch.nn.functional.grid_sample(mode='bicubic', padding_mode='zeros', align_corners=False).

  inp [C, H, W]; gx, gy normalised grid coordinates (any equal shapes). Float64, tap by tap.
  """
  c, h, w = inp.shape
  x = ((gx + 1) * w - 1) / 2
  y = ((gy + 1) * h - 1) / 2
  x0, y0 = np.floor(x), np.floor(y)
  tx, ty = x - x0, y - y0

  def k_near(t):
    return ((A + 2) * t - (A + 3)) * t * t + 1

  def k_far(t):
    return ((A * t - 5 * A) * t + 8 * A) * t - 4 * A

  wx = [k_far(tx + 1), k_near(tx), k_near(1 - tx), k_far(2 - tx)]
  wy = [k_far(ty + 1), k_near(ty), k_near(1 - ty), k_far(2 - ty)]
  out = np.zeros((c,) + np.shape(x))
  for i in range(4):
    row = np.zeros((c,) + np.shape(x))
    for j in range(4):
      xi = (x0 - 1 + j).astype(np.int64)
      yi = (y0 - 1 + i).astype(np.int64)
      ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
      v = inp[:, np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)] * ok
      row = row + wx[j] * v
    out = out + wy[i] * row
  return out


def np_local_refinement(f1, f2, flow, bias, temperature, radius):
  """The official refinement written out per offset, float64: NHWC inputs."""
  n, h, w, c = f1.shape
  p = 2 * radius + 1
  ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
  logits = np.zeros((n, h, w, p, p))
  for b_ in range(n):
    for a in range(p):
      for b in range(p):
        cx = xs + flow[b_, ..., 0] + (b - radius)
        cy = ys + flow[b_, ..., 1] + (a - radius)
        gx = ((cx + 0.5) / w) * 2 - 1
        gy = ((cy + 0.5) / h) * 2 - 1
        s = np_grid_sample_bicubic(f2[b_].transpose(2, 0, 1), gx, gy)    # [C, H, W]
        logits[b_, :, :, a, b] = (f1[b_] * s.transpose(1, 2, 0)).sum(-1) / temperature + bias[a * p + b]
  flat = logits.reshape(n, h, w, p * p)
  m = flat.max(-1, keepdims=True)
  log_p = flat - m - np.log(np.exp(flat - m).sum(-1, keepdims=True))
  prob = np.exp(log_p).reshape(n, h, w, p, p)
  off = np.arange(-radius, radius + 1)
  residual = np.stack([(prob * off[None, :]).sum((-1, -2)), (prob * off[:, None]).sum((-1, -2))], -1)
  return residual, log_p.reshape(n, h, w, p, p)


def test_sampler_matches_numpy_grid_sample_on_known_cases():
  # On a ramp value = x: at t = 0.25 the A=-0.75 weights of taps 3..6 are, by hand,
  # -0.10546875, 0.87890625, 0.26171875, -0.03515625 (they sum to 1), so the value is 4.296875 (not
  # 4.25: this kernel does not reproduce linear functions); t = 0.5 and integers are exact.
  # Far outside the map every tap reads 0 (zero padding).
  ramp = np.tile(np.arange(12, dtype=np.float64), (9, 1))[None]           # value = x
  gx = ((np.array([4.25, 5.5, 7.0]) + 0.5) / 12) * 2 - 1
  gy = ((np.array([4.0, 4.5, 3.75]) + 0.5) / 9) * 2 - 1
  np.testing.assert_allclose(np_grid_sample_bicubic(ramp, gx, gy)[0], [4.296875, 5.5, 7.0],
                             atol=1e-12)
  # At the border, taps -1 read 0: x = 0.0 exactly -> weights (0, 1, 0, 0) -> 0; x = 0.5 -> the
  # tap at -1 (weight -0.09375) is dropped: 0*0.59375 + 1*0.59375 + 2*(-0.09375) = 0.40625.
  gx = ((np.array([0.0, 0.5]) + 0.5) / 12) * 2 - 1
  gy = ((np.array([4.0, 4.0]) + 0.5) / 9) * 2 - 1
  np.testing.assert_allclose(np_grid_sample_bicubic(ramp, gx, gy)[0], [0.0, 0.40625], atol=1e-12)
  far = np_grid_sample_bicubic(ramp, np.array([5.0]), np.array([0.0]))
  np.testing.assert_array_equal(far, 0.0)


@pytest.mark.parametrize("radius,chunk", [(3, None), (3, 4), (1, 3), (2, None)])
def test_local_refinement_matches_numpy_reference(radius, chunk):
  rng = np.random.default_rng(radius * 10 + (chunk or 0))
  n, h, w, c = 2, 9, 13, 5
  f1 = rng.normal(size=(n, h, w, c))
  f2 = rng.normal(size=(n, h, w, c))
  # Flows reaching past every border (zero padding) plus some landing exactly on integers.
  flow = rng.uniform(-6, 6, size=(n, h, w, 2))
  flow[0, :2] = np.round(flow[0, :2])
  bias = rng.normal(size=(2 * radius + 1) ** 2)
  ref_res, ref_lp = np_local_refinement(f1, f2, flow, bias, 0.7, radius)
  fn = jax.jit(lambda *a: refine.local_refinement(*a, temperature=0.7, radius=radius, chunk=chunk))
  res, lp = fn(*(jnp.asarray(a, jnp.float32) for a in (f1, f2, flow, bias)))
  assert lp.shape == (n, h, w, 2 * radius + 1, 2 * radius + 1)
  np.testing.assert_allclose(np.asarray(lp), ref_lp, atol=2e-4)
  np.testing.assert_allclose(np.asarray(res), ref_res, atol=2e-5)


def test_offset_convention_from_bias():
  # f1 = 0 leaves only the bias: a dominant bias at (a, b) = (0, 5) means offset dy=-3, dx=+2.
  n, h, w, c, r = 1, 4, 5, 3, 3
  bias = np.zeros(49, np.float32)
  bias[0 * 7 + 5] = 60.0
  fn = jax.jit(lambda *a: refine.local_refinement(*a, temperature=4.0, radius=r))
  res, lp = fn(jnp.zeros((n, h, w, c)), jnp.ones((n, h, w, c)), jnp.zeros((n, h, w, 2)),
               jnp.asarray(bias))
  np.testing.assert_allclose(np.asarray(res)[..., 0], 2.0, atol=1e-5)
  np.testing.assert_allclose(np.asarray(res)[..., 1], -3.0, atol=1e-5)
  assert np.all(np.asarray(lp)[..., 0, 5] > -1e-5)


def test_pixel_shuffle_matches_torch_ordering():
  rng = np.random.default_rng(0)
  n, h, w, c, r = 2, 3, 4, 2, 3
  x = rng.normal(size=(n, h, w, c * r * r)).astype(np.float32)
  out = np.asarray(refine.pixel_shuffle(jnp.asarray(x), r))
  expected = np.zeros((n, h * r, w * r, c), np.float32)
  for ch in range(c):
    for i in range(r):
      for j in range(r):
        expected[:, i::r, j::r, ch] = x[..., ch * r * r + i * r + j]
  np.testing.assert_array_equal(out, expected)


def test_up_conv_matches_conv_transpose_definition():
  rng = np.random.default_rng(1)
  x = rng.normal(size=(1, 3, 2, 4)).astype(np.float32)
  w_torch = rng.normal(size=(4, 5, 2, 2)).astype(np.float32)            # [in, out, kh, kw]
  b = rng.normal(size=(5,)).astype(np.float32)
  expected = np.zeros((1, 6, 4, 5), np.float32) + b
  for i in range(3):
    for j in range(2):
      for a in range(2):
        for bb in range(2):
          expected[0, 2 * i + a, 2 * j + bb] += x[0, i, j] @ w_torch[:, :, a, bb]
  params = {"kernel": keymap.torch_to_flax_array("unet_feature.ups.2.weight", w_torch), "bias": b}
  out = refine.UpConv2x2(5).apply({"params": params}, jnp.asarray(x))
  np.testing.assert_allclose(np.asarray(out), expected, atol=1e-5)


def test_legacy_nearest_resize():
  x = jnp.arange(5.0)[None, :, None, None] * jnp.ones((1, 1, 3, 1))
  out = np.asarray(refine.resize_nearest_legacy(x, (7, 3)))[0, :, 0, 0]
  # src = floor(dst * 5/7)
  np.testing.assert_array_equal(out, [0, 0, 1, 2, 2, 3, 4])


def test_unet_handles_odd_sizes():
  m = refine.UNet(features=(2, 3), out_channels=4)
  x = jax.ShapeDtypeStruct((1, 11, 13, 3), jnp.float32)
  params = jax.eval_shape(lambda x: m.init(jax.random.PRNGKey(0), x), x)["params"]
  assert jax.eval_shape(lambda p, x: m.apply({"params": p}, x), params, x).shape == (1, 11, 13, 4)
  assert set(params) == {"downs_0", "downs_1", "bottleneck", "ups_0", "ups_1", "ups_2", "ups_3",
                         "final_conv"}
  assert set(params["downs_0"]) == {"conv_0", "conv_2"}


def test_torch_key_mapping():
  assert keymap.torch_key_to_path("unet_feature.downs.3.conv.2.weight", 4) == (
      "unet_feature", "downs_3", "conv_2", "kernel")
  assert keymap.torch_key_to_path("unet_feature.ups.4.weight", 4) == (
      "unet_feature", "ups_4", "kernel")
  assert keymap.torch_key_to_path("classification_head.mlp.fc1.bias", 1) == (
      "classification_head", "mlp", "fc1", "bias")
  assert keymap.torch_key_to_path("classification_bias", 1) == ("classification_bias",)
  w = np.arange(2 * 3 * 2 * 2, dtype=np.float32).reshape(2, 3, 2, 2)
  # ConvTranspose2d (even `ups` entries) [in, out, kh, kw]; the DoubleConvs are Conv2d [out, in, ...]
  assert keymap.torch_to_flax_array("unet_feature.ups.6.weight", w).shape == (2, 2, 2, 3)
  assert keymap.torch_to_flax_array("unet_feature.ups.7.conv.0.weight", w).shape == (2, 2, 3, 2)
  assert keymap.torch_to_flax_array("unet_feature.ups.10.weight", w).shape == (2, 2, 2, 3)


def test_windows_far_outside_read_zeros():
  # Every tap outside the target map reads 0 (zero padding), so only the bias remains, even for
  # flows far beyond int32-safe pixel indices.
  rng = np.random.default_rng(5)
  f1 = rng.normal(size=(1, 3, 4, 6)).astype(np.float32)
  f2 = rng.normal(size=(1, 3, 4, 6)).astype(np.float32)
  flow = np.array([1e9, -1e9, 40.0, -3e10], np.float32)[[0, 1, 2, 3, 0, 1]].reshape(1, 3, 2, 1)
  flow = np.concatenate([np.broadcast_to(flow, (1, 3, 2, 2))] * 2, 2)    # [1, 3, 4, 2]
  bias = rng.normal(size=49).astype(np.float32)
  fn = jax.jit(lambda *a: refine.local_refinement(*a, temperature=4.0, radius=3))
  _, lp = fn(f1, f2, flow, bias)
  want = bias - np.log(np.exp(bias.astype(np.float64)).sum())
  np.testing.assert_allclose(np.asarray(lp).reshape(-1, 49), np.broadcast_to(want, (12, 49)),
                             atol=1e-5)


def test_refinement_memory_at_560():
  """XLA's compiled temp memory of the refinement at 420 x 560, C=16 stays below 2x the 49-tap
  sampled feature block [1, H, W, 49, C] (what grid_sample would materialise); row chunks bound
  it further."""
  h, w, c = 420, 560, 16
  sds = lambda *s: jax.ShapeDtypeStruct(s, jnp.float32)
  block = h * w * 49 * c * 4

  def temp_bytes(chunk):
    fn = jax.jit(lambda a, b, f, z: refine.local_refinement(a, b, f, z, temperature=4.0, radius=3,
                                                             chunk=chunk))
    return fn.lower(sds(1, h, w, c), sds(1, h, w, c), sds(1, h, w, 2),
                    sds(49)).compile().memory_analysis().temp_size_in_bytes

  assert temp_bytes(None) < 2 * block
  assert temp_bytes(60) < 0.3 * block
