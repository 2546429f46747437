"""DPT feature head, regression processor and output adaptors (UniCeption `DPTFeature`,
`DPTRegressionProcessor`, `FlowAdaptor`, `MaskAdaptor`; `Covariance2DAdaptor` is
models/covariance.py), NHWC.

Module names follow the PyTorch ones with list indices joined by "_" (`input_process.0.0.1` ->
`input_process_0_0_1`); `input_process_k_1` is the module UniCeption also registers as
`scratch.layer{k+1}_rn` / `scratch.layer_rn.{k}`.
"""

import dataclasses
from typing import Callable, Optional, Sequence, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.models import layers


@dataclasses.dataclass(frozen=True)
class DPTConfig:
  input_feature_dims: Tuple[int, int, int, int] = (1024, 768, 768, 768)
  layer_dims: Tuple[int, int, int, int] = (96, 192, 384, 768)
  feature_dim: int = 256
  hooks: Tuple[int, int, int, int] = (0, 1, 2, 3)
  output_dim: int = 2
  hidden_dims: Optional[Tuple[int, int]] = None  # processor widths; default feature_dim // 2


# Every scale strategy of UniCeption ee7fa0b's FlowAdaptor._get_xy_scale (prediction_heads/
# adaptors.py:121-139); anything else raises there too.
SCALE_STRATEGIES = ("none", "scale_width", "scale_height", "scale_both")


@dataclasses.dataclass(frozen=True)
class FlowAdaptorConfig:
  flow_mean: Tuple[float, float] = (0.0, 0.0)
  flow_std: Tuple[float, float] = (1.0, 1.0)
  base_shape: Tuple[int, int] = (420, 560)  # (H, W)
  scale_strategy: str = "scale_both"  # none | scale_width | scale_height | scale_both
  output_normalized_coordinate: bool = False

  def __post_init__(self):
    if self.scale_strategy not in SCALE_STRATEGIES:
      raise ValueError(f"invalid FlowAdaptor scale_strategy {self.scale_strategy!r}; expected "
                       f"one of {', '.join(SCALE_STRATEGIES)}")


# Channels each official adaptor takes from a head's output (UniCeption's `required_channels`).
ADAPTOR_CHANNELS = {"flow": 2, "flow_cov": 3, "non_occluded_mask": 1}


def adaptor_slices(names: Sequence[str]) -> dict:
  """{adaptor name: (first, end) channel} of a head whose adaptors are `names`, in order."""
  out, start = {}, 0
  for name in names:
    out[name] = (start, start + ADAPTOR_CHANNELS[name])
    start += ADAPTOR_CHANNELS[name]
  return out


def split_adaptor_channels(x: jax.Array, names: Sequence[str]) -> dict:
  """A head's output [..., C] -> {adaptor name: its channels}, in the order of `names` (the
  official AdaptorMap hands out channels in the order of its keys)."""
  slices = adaptor_slices(names)
  total = sum(ADAPTOR_CHANNELS[n] for n in names)
  if total != x.shape[-1]:
    raise ValueError(f"head output has {x.shape[-1]} channels; adaptors {tuple(names)} take "
                     f"{total}")
  return {name: x[..., a:b] for name, (a, b) in slices.items()}


# The ConvTranspose modules of DPTFeature (by name): torch's default init counts their fan-in
# over the output channels (torch_default_init).
CONV_TRANSPOSE = ("input_process_0_0_1", "input_process_1_0_1")


def torch_default_init(key, kernel_shape, transposed: bool = False, dtype=jnp.float32):
  """(kernel, bias) as torch's Conv2d / ConvTranspose2d / Linear `reset_parameters` draws them:
  both U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (kaiming_uniform with a = sqrt(5)); fan_in = every axis
  but the output one (our kernels are HWIO or [in, out]), or for a transposed conv the output
  channels times the window (torch reads it from dim 1 of its [in, out, kh, kw] weight)."""
  shape = tuple(kernel_shape)
  fan_in = int(np.prod(shape[:-2])) * shape[-1] if transposed else int(np.prod(shape[:-1]))
  bound = 1.0 / np.sqrt(fan_in)
  kk, kb = jax.random.split(key)
  kernel = jax.random.uniform(kk, shape, dtype, -bound, bound)
  bias = jax.random.uniform(kb, shape[-1:], dtype, -bound, bound)
  return kernel, bias


def _conv(features, k, stride=1, pad=0, bias=True, name=None, dtype=None):
  return layers.Conv(features, (k, k), strides=(stride, stride), padding=((pad, pad), (pad, pad)),
                     use_bias=bias, dtype=dtype, name=name)


class ConvTranspose(nn.Module):
  """torch ConvTranspose2d with kernel == stride, no padding: every input pixel writes one
  disjoint k x k output block, out[i*k+a, j*k+b, o] = sum_c x[i, j, c] W[c, o, a, b] + bias.
  kernel is stored [k, k, in, out]."""
  features: int
  k: int
  dtype: Optional[jnp.dtype] = None

  @nn.compact
  def __call__(self, x):
    b, h, w, c = x.shape
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (self.k, self.k, c, self.features))
    bias = self.param("bias", nn.initializers.zeros, (self.features,))
    dtype = self.dtype or jnp.promote_types(x.dtype, kernel.dtype)
    y = layers.einsum("nhwc,abco->nhawbo", x.astype(dtype), kernel.astype(dtype))
    return y.reshape(b, h * self.k, w * self.k, self.features) + bias.astype(dtype)


def _interp_axis(n_in: int, n_out: int, f=np.float32):
  """torch bilinear align_corners=True along one axis: (i0, i1, w0, w1) in precision f."""
  scale = f(n_in - 1) / f(n_out - 1) if n_out > 1 else f(0)
  src = scale * np.arange(n_out, dtype=f)
  i0 = np.floor(src).astype(np.int64)
  i0 = np.minimum(i0, n_in - 1)
  w1 = (src - i0.astype(f)).astype(f)
  i1 = np.minimum(i0 + 1, n_in - 1)
  return i0, i1, (f(1) - w1).astype(f), w1


def resize_bilinear_align_corners(x: jax.Array, out_h: int, out_w: int) -> jax.Array:
  """F.interpolate(mode='bilinear', align_corners=True) on NHWC.

  Evaluated as torch's CPU kernel does, h0 * (w0 * x00 + w1 * x01) + h1 * (...), so the float32
  rounding matches too.
  """
  _, h, w, _ = x.shape
  f = np.float64 if x.dtype == jnp.float64 else np.float32
  j0, j1, b0, b1 = _interp_axis(w, out_w, f)
  x = (x[:, :, j0] * jnp.asarray(b0, x.dtype)[None, None, :, None]
       + x[:, :, j1] * jnp.asarray(b1, x.dtype)[None, None, :, None])
  i0, i1, a0, a1 = _interp_axis(h, out_h, f)
  return (x[:, i0] * jnp.asarray(a0, x.dtype)[None, :, None, None]
          + x[:, i1] * jnp.asarray(a1, x.dtype)[None, :, None, None])


class ResidualConvUnit(nn.Module):
  """x + conv2(relu(conv1(relu(x))))."""
  features: int
  dtype: Optional[jnp.dtype] = None

  @nn.compact
  def __call__(self, x):
    y = _conv(self.features, 3, pad=1, name="conv1", dtype=self.dtype)(jax.nn.relu(x))
    y = _conv(self.features, 3, pad=1, name="conv2", dtype=self.dtype)(jax.nn.relu(y))
    return x + y


class FusionBlock(nn.Module):
  """out_conv(up2(resConfUnit2(x0 [+ resConfUnit1(x1)]))), bilinear x2 align_corners=True."""
  features: int
  has_skip: bool = True  # refinenet4 has no second input (and no resConfUnit1 weights)
  dtype: Optional[jnp.dtype] = None

  @nn.compact
  def __call__(self, x0, x1=None):
    out = x0
    if self.has_skip:
      out = out + ResidualConvUnit(self.features, self.dtype, name="resConfUnit1")(x1)
    out = ResidualConvUnit(self.features, self.dtype, name="resConfUnit2")(out)
    _, h, w, _ = out.shape
    out = resize_bilinear_align_corners(out, 2 * h, 2 * w)
    return _conv(self.features, 1, name="out_conv", dtype=self.dtype)(out)


class Scratch(nn.Module):
  feature_dim: int
  dtype: Optional[jnp.dtype] = None

  def setup(self):
    self.refinenet1 = FusionBlock(self.feature_dim, dtype=self.dtype)
    self.refinenet2 = FusionBlock(self.feature_dim, dtype=self.dtype)
    self.refinenet3 = FusionBlock(self.feature_dim, dtype=self.dtype)
    self.refinenet4 = FusionBlock(self.feature_dim, has_skip=False, dtype=self.dtype)


class DPTFeature(nn.Module):
  """Four [B, h, w, C_k] maps at patch resolution -> [B, 8h, 8w, feature_dim].

  `dtype` (None: the inputs' float32) is the compute and activation dtype; params stay float32.
  `constrain` (the model's activation-sharding hook) is applied to every stage's output."""
  config: DPTConfig
  dtype: Optional[jnp.dtype] = None
  constrain: Optional[Callable] = None

  @nn.compact
  def __call__(self, feats: Sequence[jax.Array]):
    cfg = self.config
    ld, fd = cfg.layer_dims, cfg.feature_dim
    for k, hook in enumerate(cfg.hooks):
      if feats[hook].shape[-1] != cfg.input_feature_dims[k]:
        raise ValueError(f"DPT hook {hook}: got {feats[hook].shape[-1]} channels, expected "
                         f"{cfg.input_feature_dims[k]}")
    x = [feats[hook] for hook in cfg.hooks]
    dt = self.dtype
    # Branch resampling: x4 (1x1, ConvT 4/4), x2 (1x1, ConvT 2/2), x1 (1x1), x1/2 (1x1, 3x3 s2).
    x[0] = ConvTranspose(ld[0], 4, dt, name="input_process_0_0_1")(
        _conv(ld[0], 1, name="input_process_0_0_0", dtype=dt)(x[0]))
    x[1] = ConvTranspose(ld[1], 2, dt, name="input_process_1_0_1")(
        _conv(ld[1], 1, name="input_process_1_0_0", dtype=dt)(x[1]))
    x[2] = _conv(ld[2], 1, name="input_process_2_0_0", dtype=dt)(x[2])
    x[3] = _conv(ld[3], 3, stride=2, pad=1, name="input_process_3_0_1", dtype=dt)(
        _conv(ld[3], 1, name="input_process_3_0_0", dtype=dt)(x[3]))
    # layer{k}_rn: 3x3 to feature_dim, no bias.
    c = self.constrain or (lambda t: t)
    x = [c(_conv(fd, 3, pad=1, bias=False, name=f"input_process_{k}_1", dtype=dt)(x[k]))
         for k in range(4)]
    for k in range(4):
      self.sow("intermediates", f"layer{k}", x[k])
    scratch = Scratch(fd, dt, name="scratch")
    path4 = c(scratch.refinenet4(x[3]))
    self.sow("intermediates", "refinenet4_out", path4)
    path4 = path4[:, :x[2].shape[1], :x[2].shape[2]]  # top-left crop for odd grids
    path3 = c(scratch.refinenet3(path4, x[2]))
    self.sow("intermediates", "refinenet3_out", path3)
    path2 = c(scratch.refinenet2(path3, x[1]))
    self.sow("intermediates", "refinenet2_out", path2)
    path1 = c(scratch.refinenet1(path2, x[0]))
    self.sow("intermediates", "refinenet1_out", path1)
    return path1


class DPTRegressionProcessor(nn.Module):
  """conv3x3 -> bilinear (align_corners=True) resize to (H, W) -> conv3x3 -> ReLU -> conv1x1.
  `extra` [B, H, W, k] (ufm_jax's uncertainty cues, not official) joins the channels after the
  resize, so conv2_0 reads them at full resolution.

  `dtype` as DPTFeature's; the output is returned in the input features' dtype (float32)."""
  config: DPTConfig
  dtype: Optional[jnp.dtype] = None
  constrain: Optional[Callable] = None

  @nn.compact
  def __call__(self, x, out_hw: Tuple[int, int], extra=None):
    cfg = self.config
    c = self.constrain or (lambda t: t)
    out_dtype = jnp.promote_types(x.dtype, jnp.float32)
    h1, h2 = cfg.hidden_dims or (cfg.feature_dim // 2,) * 2
    x = c(_conv(h1, 3, pad=1, name="conv1", dtype=self.dtype)(x))
    self.sow("intermediates", "conv1_out", x)
    x = c(resize_bilinear_align_corners(x, *out_hw))
    if extra is not None:
      x = jnp.concatenate([x, extra.astype(x.dtype)], -1)
    x = c(jax.nn.relu(_conv(h2, 3, pad=1, name="conv2_0", dtype=self.dtype)(x)))
    return c(_conv(cfg.output_dim, 1, name="conv2_2", dtype=self.dtype)(x).astype(out_dtype))


def flow_adaptor(x: jax.Array, cfg: FlowAdaptorConfig) -> jax.Array:
  """Normalised network output [B, H, W, 2] -> flow in pixels (UniCeption FlowAdaptor)."""
  _, h, w, _ = x.shape
  f32 = np.float32
  if not cfg.output_normalized_coordinate:
    if cfg.scale_strategy == "none":
      sx, sy = 1.0, 1.0
    elif cfg.scale_strategy == "scale_width":
      sx = sy = w / cfg.base_shape[1]
    elif cfg.scale_strategy == "scale_height":
      sx = sy = h / cfg.base_shape[0]
    else:  # scale_both
      sx, sy = w / cfg.base_shape[1], h / cfg.base_shape[0]
    # torch: float32 buffers times torch.tensor([sx, sy], float32); the mean is scaled too.
    scale = np.array([sx, sy], f32)
    std = jnp.asarray(np.array(cfg.flow_std, f32), x.dtype) * jnp.asarray(scale, x.dtype)
    mean = jnp.asarray(np.array(cfg.flow_mean, f32), x.dtype) * jnp.asarray(scale, x.dtype)
    return x * std + mean
  # The network predicts normalised target coordinates in [-1, 1]; subtract the pixel centres.
  wh = jnp.asarray(np.array([w, h], f32), x.dtype)
  x = 0.5 * (x + 1) * wh + 0.5
  xs = np.arange(w, dtype=f32) + f32(0.5)
  ys = np.arange(h, dtype=f32) + f32(0.5)
  coords = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)  # [H, W, 2]
  return x - jnp.asarray(coords, x.dtype)
