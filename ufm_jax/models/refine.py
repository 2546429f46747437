"""UFM-Refine pieces: U-Net, classification feature head, local attention refinement.

Port of the refinement stage of the official `UniFlowMatchClassificationRefinement`:
  features_i = conv2(relu(conv1(concat[patch_mlp(tokens_i), unet(image_i)])))     (i = source, target)
    (feature_combine_method "modulate": conv2(patch_mlp(tokens_i) * tanh(unet(image_i))))
  logits[a, b] = <f_src(x, y), f_tgt(x + u + b - R, y + v + a - R)> / temperature + bias[a * P + b]
  flow = flow_regressed + sum softmax(logits) * (b - R, a - R)
where f_tgt is read with torch `grid_sample(mode="bicubic", padding_mode="zeros", align_corners=False)`.

Param names mirror the PyTorch modules (`unet_feature.downs.0.conv.0` -> `unet_feature/downs_0/conv_0`).
"""

import dataclasses
from typing import Any, Optional, Sequence, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.models import layers, ufm

_A = -0.75  # torch's bicubic convolution constant


# ----------------------------------------------------------------------------------------------
# U-Net


class BatchNorm(nn.Module):
  """torch BatchNorm2d over the channel (last) axis, with torch's names and update rule.

  train=True normalises with the batch's statistics (biased variance) and updates the running
  ones in the "batch_stats" collection: momentum 0.1, the unbiased variance, num_batches_tracked
  + 1 (call `apply` with mutable=["batch_stats"]). train=False normalises with the running ones.

  group_rows: train=True takes the statistics over each group of that many consecutive rows
  separately, as DDP without sync_batchnorm takes them over each GPU's rows (the official
  trainer, train_pl.py:531-533), and the running statistics follow the first group's, as DDP's
  broadcast of rank 0's buffers before every forward keeps rank 0's (the ones its checkpoint
  saves). None: one set over the whole batch (what sync_batchnorm gives).
  """
  momentum: float = 0.1
  epsilon: float = 1e-5
  group_rows: Optional[int] = None

  @nn.compact
  def __call__(self, x, train: bool = False):
    c = x.shape[-1]
    scale = self.param("scale", nn.initializers.ones, (c,))
    bias = self.param("bias", nn.initializers.zeros, (c,))
    mean = self.variable("batch_stats", "running_mean", lambda: jnp.zeros((c,), jnp.float32))
    var = self.variable("batch_stats", "running_var", lambda: jnp.ones((c,), jnp.float32))
    count = self.variable("batch_stats", "num_batches_tracked", lambda: jnp.zeros((), jnp.int32))
    xf = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    if not train:
      m, v = mean.value, var.value
      return ((xf - m) * jax.lax.rsqrt(v + self.epsilon) * scale + bias).astype(x.dtype)
    rows = x.shape[0] if self.group_rows is None else int(self.group_rows)
    if rows <= 0 or x.shape[0] % rows:
      raise ValueError(f"BatchNorm statistics per {rows} rows (model.unet_batchnorm_group_rows) "
                       f"do not divide a batch of {x.shape[0]} rows")
    # [groups, rows, ...]: a group never straddles two devices' rows when it divides them.
    xg = xf.reshape((x.shape[0] // rows, rows) + x.shape[1:])
    axes = tuple(range(1, xg.ndim - 1))
    m = xg.mean(axes, keepdims=True)
    v = jnp.square(xg - m).mean(axes, keepdims=True)
    if not self.is_initializing():
      n = xg[0].size // c
      mom = self.momentum
      m0, v0 = (jax.lax.stop_gradient(a[0]).reshape(c) for a in (m, v))
      mean.value = (1 - mom) * mean.value + mom * m0
      var.value = (1 - mom) * var.value + mom * v0 * (n / max(n - 1, 1))
      count.value = count.value + 1
    y = (xg - m) * jax.lax.rsqrt(v + self.epsilon) * scale + bias
    return y.reshape(x.shape).astype(x.dtype)


class DoubleConv(nn.Module):
  """(conv3x3 pad 1, ReLU) x 2, biases on; with batch_norm a BatchNorm after the first ReLU
  (the official Sequential: conv.0, relu, conv.2 = BatchNorm2d, conv.3, relu)."""
  features: int
  dtype: Any = jnp.float32
  batch_norm: bool = False
  batch_norm_group_rows: Optional[int] = None

  @nn.compact
  def __call__(self, x, train: bool = False):
    conv = lambda name: layers.Conv(self.features, (3, 3), padding=((1, 1), (1, 1)),  # noqa: E731
                                    dtype=self.dtype, name=name)
    x = nn.relu(conv("conv_0")(x))
    if self.batch_norm:
      bn = BatchNorm(group_rows=self.batch_norm_group_rows, name="conv_2")
      return nn.relu(conv("conv_3")(bn(x, train)))
    return nn.relu(conv("conv_2")(x))


class UpConv2x2(nn.Module):
  """torch ConvTranspose2d(k=2, s=2): out[2i+a, 2j+b] = x[i, j] @ W[:, :, a, b] + bias.

  The stride equals the kernel size, so the taps never overlap and one einsum does it; the kernel
  is stored [a, b, in, out] (torch's [in, out, a, b] transposed (2, 3, 0, 1)).
  """
  features: int
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x):
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (2, 2, x.shape[-1], self.features))
    bias = self.param("bias", nn.initializers.zeros, (self.features,))
    x = x.astype(self.dtype)
    y = layers.einsum("nhwc,abco->nhawbo", x, kernel.astype(self.dtype))
    n, h, _, w, _, o = y.shape
    return y.reshape(n, 2 * h, 2 * w, o) + bias.astype(self.dtype)


def resize_nearest_legacy(x, size):
  """torch F.interpolate(mode='nearest', size=size) on NHWC: src = floor(dst * float32(in/out))."""
  def index(n_in, n_out):
    scale = np.float32(n_in) / np.float32(n_out)
    idx = np.floor(np.arange(n_out, dtype=np.float32) * scale).astype(np.int64)
    return np.minimum(idx, n_in - 1)
  rows = index(x.shape[1], size[0])
  cols = index(x.shape[2], size[1])
  return x[:, rows][:, :, cols]


class UNet(nn.Module):
  """The official U-Net (RoMa-style fine features): widths `features`, output `out_channels`.

  Max-pool 2x2 with floor rounding; after each 2x2 up-convolution the map is resized with legacy
  nearest when it is smaller than the skip (odd sizes), then concatenated as [skip, upsampled].
  """
  features: Sequence[int] = (64, 128, 256, 512)
  out_channels: int = 16
  dtype: Any = jnp.float32
  batch_norm: bool = False  # official use_unet_batchnorm
  batch_norm_group_rows: Optional[int] = None   # BatchNorm.group_rows

  @nn.compact
  def __call__(self, x, train: bool = False):
    def double(f, name):
      return lambda y: DoubleConv(f, dtype=self.dtype, batch_norm=self.batch_norm,
                                  batch_norm_group_rows=self.batch_norm_group_rows,
                                  name=name)(y, train)
    skips = []
    for i, f in enumerate(self.features):
      x = double(f, f"downs_{i}")(x)
      skips.append(x)
      # keywords: jax2onnx's patched max_pool takes no positional window shape
      x = nn.max_pool(x, window_shape=(2, 2), strides=(2, 2), padding="VALID")
    x = double(2 * self.features[-1], "bottleneck")(x)
    for k, f in enumerate(reversed(self.features)):
      x = UpConv2x2(f, dtype=self.dtype, name=f"ups_{2 * k}")(x)
      skip = skips[-1 - k]
      if x.shape[1:3] != skip.shape[1:3]:
        x = resize_nearest_legacy(x, skip.shape[1:3])
      x = double(f, f"ups_{2 * k + 1}")(jnp.concatenate([skip, x], -1))
    return layers.Conv(self.out_channels, (1, 1), dtype=self.dtype, name="final_conv")(x)


# ----------------------------------------------------------------------------------------------
# Classification feature head ("patch_mlp")


def pixel_shuffle(x, r):
  """torch pixel_shuffle on NHWC: channel c*r*r + i*r + j -> (row h*r+i, col w*r+j, channel c)."""
  n, h, w, c = x.shape
  x = x.reshape(n, h, w, c // (r * r), r, r)
  x = x.transpose(0, 1, 4, 2, 5, 3)
  return x.reshape(n, h * r, w * r, c // (r * r))


class Mlp(nn.Module):
  hidden_dim: int
  out_dim: int
  dtype: Any = None

  @nn.compact
  def __call__(self, x):
    x = layers.Dense(self.hidden_dim, dtype=self.dtype, name="fc1")(x)
    x = nn.gelu(x, approximate=False)
    return layers.Dense(self.out_dim, dtype=self.dtype, name="fc2")(x)


class MLPFeature(nn.Module):
  """Official MLPFeature: token MLP (in -> in*ratio -> in), 1x1 conv to out*p*p, pixel shuffle p."""
  output_dim: int = 16
  patch_size: int = 14
  mlp_ratio: float = 4.0
  dtype: Any = None  # compute dtype (None: the input's); params stay float32

  @nn.compact
  def __call__(self, x, return_mlp=False):  # [N, h, w, C] tokens -> [N, h*p, w*p, output_dim]
    c = x.shape[-1]
    x = Mlp(int(c * self.mlp_ratio), c, self.dtype, name="mlp")(x)
    if return_mlp:                           # the token MLP output alone (a parity checkpoint)
      return x
    p = self.patch_size
    x = layers.Conv(self.output_dim * p * p, (1, 1), dtype=self.dtype, name="linear")(x)
    return pixel_shuffle(x, p)


# ----------------------------------------------------------------------------------------------
# Local refinement


def cubic_weights(t):
  """torch's bicubic coefficients (A=-0.75) for taps at -1, 0, 1, 2 of fractional position t."""
  def near(s):
    return ((_A + 2) * s - (_A + 3)) * s * s + 1
  def far(s):
    return ((_A * s - 5 * _A) * s + 8 * _A) * s - 4 * _A
  return jnp.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], -1)


def grid_sample_coordinate(coord, size):
  """Pixel-index coordinate -> the coordinate torch's grid_sample actually samples, in float32.

  The official code normalises `((coord + 0.5) / size) * 2 - 1`; grid_sample (align_corners=False)
  maps back with `(g + 1) * (size / 2) - 0.5`. Ideally the identity; we repeat the float32 round trip.
  """
  size = jnp.asarray(size, coord.dtype)
  g = ((coord + 0.5) / size) * 2 - 1
  return (g + 1) * (size / 2) - 0.5


def _axis_weights(center, radius, size):
  """Per-offset bicubic weights along one axis, on a shared integer tap window.

  center: [...] float32 pixel coordinate of offset 0 (x + u, or y + v).
  Returns (start [...] int32, weights [..., P, P + 4]) with P = 2R+1: sample(offset k) =
  sum_j weights[..., k, j] * value(start + j). Each offset is rounded through grid_sample's
  normalisation on its own (as the official call does), so its floor may differ by one from the
  others near integers; the window holds one spare tap for that.
  """
  p = 2 * radius + 1
  offsets = jnp.arange(-radius, radius + 1, dtype=center.dtype)
  pos = grid_sample_coordinate(center[..., None] + offsets, size)       # [..., P]
  # Far outside the map every tap reads 0 wherever exactly; clipping keeps int32 indices sane.
  pos = jnp.clip(pos, -(p + 8), size + p + 8)
  base = jnp.floor(pos)
  frac = pos - base
  start = base[..., 0] - 1                                               # tap of offset -R at -1
  rel = jnp.clip(base - 1 - start[..., None], 0, p).astype(jnp.int32)   # [..., P], ~= k
  w4 = cubic_weights(frac)                                               # [..., P, 4]
  taps = jnp.arange(p + 4)
  # weights[..., k, j] = w4[..., k, j - rel_k] for 0 <= j - rel_k < 4.
  d = taps - rel[..., None]                                              # [..., P, P+4]
  weights = jnp.zeros(d.shape, w4.dtype)
  for i in range(4):
    weights = weights + jnp.where(d == i, w4[..., i:i + 1], 0.0)
  return start.astype(jnp.int32), weights


def _tap_products(f1, f2, x0, y0, ntaps):
  """dots[i, n, y, x, j] = <f1[n, y, x], f2[n, y0 + i, x0 + j]> (0 outside f2) for i, j < ntaps.

  One window row at a time (scan), so only [N, H, W, ntaps, C] gathered values are live at once;
  each row of the window is one contiguous slice (a gather of ntaps * C values, not ntaps gathers).
  The map is zero-padded by ntaps on every side, so a start index clamped into the padded map lands
  either exactly (window partly inside) or wholly in zeros (window entirely outside).
  """
  t = ntaps
  n, h, w, c = f2.shape
  f2p = jnp.pad(f2, ((0, 0), (t, t), (t, t), (0, 0)))
  xs = jnp.clip(x0 + t, 0, w + t)                                        # [N, h1, w1]
  ys = jnp.clip(y0 + t, 0, h + t)

  # Flat row indices into the padded map and one plain take: the same values as a vmapped
  # dynamic_slice, but a gather simple enough for ONNX export (jax2onnx converts it to Gather).
  wp = w + 2 * t
  f2f = f2p.reshape(-1, c)
  start = ((jnp.arange(n, dtype=jnp.int32)[:, None, None] * (h + 2 * t) + ys.astype(jnp.int32)) * wp
           + xs.astype(jnp.int32))                                       # [N, h1, w1]
  cols = jnp.arange(t, dtype=jnp.int32)

  @jax.checkpoint   # backward re-gathers instead of storing [T, N, H, W, T, C]
  def row(i):
    idx = (start + i * wp)[..., None] + cols                             # [N, h1, w1, T]
    vals = jnp.take(f2f, idx, axis=0, mode="clip")                       # [N, h1, w1, T, C]
    return jnp.einsum("nyxc,nyxtc->nyxt", f1, vals, precision=jax.lax.Precision.HIGHEST)

  _, dots = jax.lax.scan(lambda carry, i: (carry, row(i)), None, jnp.arange(t))
  return dots                                                            # [T rows, N, h1, w1, T cols]


def _refine_rows(f1, f2, flow, bias, temperature, radius, row0):
  """Refinement for the source rows row0 .. row0 + f1.shape[1] (f2 is the whole target map)."""
  _, h1, w1, _ = f1.shape
  h2, w2 = f2.shape[1:3]
  dt = flow.dtype
  xs = jnp.arange(w1, dtype=dt)
  ys = row0.astype(dt) + jnp.arange(h1, dtype=dt)
  cx = xs[None, None, :] + flow[..., 0]
  cy = ys[None, :, None] + flow[..., 1]
  x0, wx = _axis_weights(cx, radius, w2)                                 # [N,h,w], [N,h,w,P,P+4]
  y0, wy = _axis_weights(cy, radius, h2)
  dots = _tap_products(f1, f2, x0, y0, 2 * radius + 5)                   # [T,N,h,w,T] (rows, cols)
  # torch interpolates along x first (per tap row), then along y.
  along_x = jnp.einsum("nyxbj,inyxj->nyxib", wx, dots, precision=jax.lax.Precision.HIGHEST)
  scores = jnp.einsum("nyxai,nyxib->nyxab", wy, along_x, precision=jax.lax.Precision.HIGHEST)
  p = 2 * radius + 1
  logits = scores / temperature + bias.reshape(p, p)
  log_p = jax.nn.log_softmax(logits.reshape(logits.shape[:3] + (p * p,)), -1)
  log_p = log_p.reshape(logits.shape)
  prob = jnp.exp(log_p)
  offsets = jnp.arange(-radius, radius + 1, dtype=dt)
  residual = jnp.stack([jnp.einsum("nyxab,b->nyx", prob, offsets),
                        jnp.einsum("nyxab,a->nyx", prob, offsets)], -1)
  return residual, log_p


def local_refinement(f1, f2, flow, bias, *, temperature, radius, chunk=None):
  """The official classification refinement.

  Args:
    f1, f2: [N, H, W, C] refinement features of the source / target view.
    flow: [N, H, W, 2] regressed flow (pixels) around which the (2R+1)^2 window is searched.
    bias: [(2R+1)^2] per-offset classification bias (index a*(2R+1) + b).
    temperature: the score divisor; radius: R.
    chunk: rows of source pixels per step (lax.map) to bound memory at high resolution; None = all.
  Returns:
    residual [N, H, W, 2] (added to `flow` by the caller) and log_softmax [N, H, W, P, P]
    with [..., a, b] <-> offset (dx, dy) = (b - R, a - R).
  """
  # float32 even under bf16 compute (the official code runs it under fp32 autocast); float64 stays.
  dt = jnp.promote_types(jnp.result_type(f1, f2, flow), jnp.float32)
  f1, f2, flow, bias = (a.astype(dt) for a in (f1, f2, flow, bias))
  h = f1.shape[1]
  if chunk is None or chunk >= h:
    return _refine_rows(f1, f2, flow, bias, temperature, radius, jnp.int32(0))
  n_chunks = -(-h // chunk)
  pad = n_chunks * chunk - h

  def split(a):
    a = jnp.pad(a, [(0, 0), (0, pad)] + [(0, 0)] * (a.ndim - 2))
    a = a.reshape((a.shape[0], n_chunks, chunk) + a.shape[2:])
    return jnp.moveaxis(a, 1, 0)

  def one(args):
    f1c, flowc, row0 = args
    return _refine_rows(f1c, f2, flowc, bias, temperature, radius, row0)

  rows0 = jnp.arange(n_chunks, dtype=jnp.int32) * chunk
  residual, log_p = jax.lax.map(one, (split(f1), split(flow), rows0))

  def merge(a):
    a = jnp.moveaxis(a, 0, 1)
    return a.reshape((a.shape[0], n_chunks * chunk) + a.shape[3:])[:, :h]

  return merge(residual), merge(log_p)


# ----------------------------------------------------------------------------------------------
# The refinement stage (its params sit at the top level of the UFM-Refine tree, as in PyTorch)


class Refiner(nn.Module):
  """U-Net + patch_mlp feature maps for both views, then the local attention refinement.

  Children are named like the official module's attributes (unet_feature, classification_head,
  conv1, conv2, classification_bias) so UFMRefine can expose them at the root of its params.
  """
  unet_features: Sequence[int] = (64, 128, 256, 512)
  feature_dim: int = 16
  patch_size: int = 14
  mlp_ratio: float = 4.0
  use_unet_feature: bool = True
  feature_combine_method: str = "conv"
  refinement_range: int = 7
  temperature: float = 4.0
  chunk: Any = None
  unet_dtype: Any = jnp.float32
  use_unet_batchnorm: bool = False
  unet_batchnorm_group_rows: Optional[int] = None
  # Compute dtype of the classification head and the combining convolutions (None: float32).
  # The official code runs them with its DPT heads under autocast("cuda", float32), which a CPU
  # autocast does not undo: the model's head_dtype.
  head_dtype: Any = None

  def setup(self):
    if self.refinement_range % 2 != 1:
      raise ValueError(f"refinement_range must be odd, got {self.refinement_range}")
    if self.use_unet_feature and self.feature_combine_method not in ("conv", "modulate"):
      raise ValueError(f"feature_combine_method {self.feature_combine_method!r}; expected 'conv' "
                       "or 'modulate'")
    self.classification_head = MLPFeature(self.feature_dim, self.patch_size, self.mlp_ratio,
                                          self.head_dtype)
    if self.use_unet_feature:
      self.unet_feature = UNet(tuple(self.unet_features), self.feature_dim, dtype=self.unet_dtype,
                               batch_norm=self.use_unet_batchnorm,
                               batch_norm_group_rows=self.unet_batchnorm_group_rows)
      self.conv1 = layers.Conv(2 * self.feature_dim, (1, 1), dtype=self.head_dtype)
      self.conv2 = layers.Conv(self.feature_dim, (1, 1), dtype=self.head_dtype)
    p = self.refinement_range
    self.classification_bias = self.param("classification_bias", nn.initializers.zeros, (p * p,))

  def unet(self, image_norm, train: bool = False):
    """[N, H, W, 3] normalised images -> U-Net features (None when the model has no U-Net).
    train: BatchNorm on batch statistics, updating the running ones (`BatchNorm`)."""
    if not self.use_unet_feature:
      return None
    return self.unet_feature(image_norm, train)

  def combine(self, tokens, unet_out):
    """tokens [N, h, w, C_enc + C_info] (concat of encoder list[0] and info-sharing final) and the
    U-Net output -> [N, H, W, feature_dim] refinement features (float32, or float64)."""
    f = self.classification_head(tokens)
    if self.use_unet_feature:
      u = unet_out.astype(f.dtype)
      if self.feature_combine_method == "modulate":
        if self.is_initializing():  # the official module registers conv1 (32 -> 32) unused
          self.conv1(jnp.concatenate([f, u], -1))
        f = self.conv2(f * jnp.tanh(u))
      else:
        f = self.conv2(nn.relu(self.conv1(jnp.concatenate([f, u], -1))))
    return f.astype(tokens.dtype)

  def features(self, tokens, image_norm):
    return self.combine(tokens, self.unet(image_norm))

  def refine(self, f1, f2, flow):
    return local_refinement(f1, f2, flow, self.classification_bias, temperature=self.temperature,
                            radius=self.refinement_range // 2, chunk=self.chunk)

  def __call__(self, tokens1, tokens2, image1_norm, image2_norm, flow):
    """Both views' features in one batch (as the official code does), then the refinement."""
    n = tokens1.shape[0]
    feats = self.features(jnp.concatenate([tokens1, tokens2], 0),
                          jnp.concatenate([image1_norm, image2_norm], 0))
    f1, f2 = feats[:n], feats[n:]
    residual, log_p = self.refine(f1, f2, flow)
    return {"flow": flow + residual, "flow_before_refinement": flow, "residual": residual,
            "log_softmax": log_p, "feature_map_0": f1, "feature_map_1": f2}


# ----------------------------------------------------------------------------------------------
# PyTorch weights


def unet_widths(tensors, prefix="unet_feature."):
  """U-Net widths from the weight shapes (`downs.{i}.conv.0.weight.shape[0]`); () when absent."""
  widths = []
  while f"{prefix}downs.{len(widths)}.conv.0.weight" in tensors:
    w = tensors[f"{prefix}downs.{len(widths)}.conv.0.weight"]
    widths.append(int(w[0] if isinstance(w, tuple) else w.shape[0]))   # shape tuple or tensor
  return tuple(widths)



# ----------------------------------------------------------------------------------------------
# UFM-Refine (UniFlowMatchClassificationRefinement): the base UFM plus the refiner


@dataclasses.dataclass(frozen=True)
class UFMRefineConfig(ufm.UFMConfig):
  """UFMConfig plus the refiner's structure (U-Net widths come from the weights when loading)."""
  unet_features: Tuple[int, ...] = (64, 128, 256, 512)
  refine_feature_dim: int = 16          # classification_head_kwargs.output_dim
  refine_mlp_ratio: float = 4.0         # classification_head_kwargs.mlp_ratio
  use_unet_feature: bool = True
  feature_combine_method: str = "conv"  # or "modulate"
  use_unet_batchnorm: bool = False      # BatchNorm in the U-Net's DoubleConvs (batch_stats)
  # Training only: BatchNorm statistics per group of this many consecutive rows (the official
  # per-GPU statistics, BatchNorm.group_rows); None: over the whole batch.
  unet_batchnorm_group_rows: Optional[int] = None
  refinement_range: int = 7             # P: the window is P x P
  temperature: float = 4.0
  # Source rows per refinement step (lax.map): bounds the refinement's memory at 980 px.
  refine_chunk: Optional[int] = None

  def __post_init__(self):
    super().__post_init__()
    if "non_occluded_mask" in self.flow_head_adaptors:
      raise ValueError("UFMRefineConfig.flow_head_adaptors: UniFlowMatchClassificationRefinement "
                       "reads covisibility from the uncertainty head only (ufm.py:956-960 at "
                       "3732a50), so a 'non_occluded_mask' in its main head is not supported")

  def build_model(self, **kw) -> "UFMRefine":
    """ufm.model_from_config dispatches here, so train.py / the CLI build the refine model."""
    return UFMRefine(self, **kw)


def refine_config_from_dict(d):
  """Inverse of dataclasses.asdict(UFMRefineConfig) (JSON lists become tuples)."""
  base_names = {f.name for f in dataclasses.fields(ufm.UFMConfig)}
  extra_names = {f.name for f in dataclasses.fields(UFMRefineConfig)} - base_names
  unknown = set(d) - base_names - extra_names
  if unknown:
    raise ValueError(f"unknown refine model config keys {sorted(unknown)}")
  base = ufm.config_from_dict({k: v for k, v in d.items() if k in base_names})
  extra = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in extra_names}
  return UFMRefineConfig(**{n: getattr(base, n) for n in base_names}, **extra)


class UFMRefine(ufm.UFM):
  """UniFlowMatchClassificationRefinement.

  apply(...) returns the base contract with "flow" = refined flow, plus "flow_before_refinement",
  "residual", "log_softmax" [B, H, W, P, P] ([..., a, b] <-> offset dy = a - R, dx = b - R), the
  refinement feature maps "feature_map_0" / "feature_map_1" [B, H, W, C] and "attention_bias"
  [P*P] (the classification bias; the training loss recomputes the attention from these).
  """
  config: UFMRefineConfig

  def setup(self):
    super().setup()
    cfg = self.config
    unet_dtype = {"float32": jnp.float32, "bfloat16": jnp.bfloat16,
                  "float64": jnp.float64}[cfg.dtype]
    self.refiner = Refiner(
        unet_features=tuple(cfg.unet_features), feature_dim=cfg.refine_feature_dim,
        patch_size=cfg.encoder.patch_size, mlp_ratio=cfg.refine_mlp_ratio,
        use_unet_feature=cfg.use_unet_feature, feature_combine_method=cfg.feature_combine_method,
        refinement_range=cfg.refinement_range, temperature=cfg.temperature,
        chunk=cfg.refine_chunk, unet_dtype=unet_dtype, use_unet_batchnorm=cfg.use_unet_batchnorm,
        unet_batchnorm_group_rows=cfg.unet_batchnorm_group_rows,
        head_dtype=jnp.bfloat16 if cfg.head_dtype == "bfloat16" and cfg.dtype != "float64" else None)
    # The refiner's params sit at the root (unet_feature, classification_head, conv1, conv2,
    # classification_bias), like the attributes of the PyTorch module.
    nn.share_scope(self, self.refiner)

  def __call__(self, source, target, symmetrized: bool = False, train: bool = False):
    """train: the U-Net's BatchNorm (use_unet_batchnorm) normalises with batch statistics and
    updates the running ones; call apply with mutable=["batch_stats"]. No effect otherwise."""
    cfg = self.config
    ufm.check_images(source, target, cfg.encoder.patch_size, symmetrized)
    _, h, w, _ = source.shape
    head_dtype = jnp.float64 if cfg.dtype == "float64" else jnp.float32
    src, tgt = ufm.normalize(source), ufm.normalize(target)
    if cfg.dtype == "float64":
      src, tgt = src.astype(jnp.float64), tgt.astype(jnp.float64)

    # UFM.backbone is not reused: the refiner also needs the encoder's FIRST returned map and the
    # normalised images. The heads are shared (UFM.heads). Each image goes through the encoder
    # and the U-Net once, each pair's rows on one device (ufm.encoder_batch).
    images = self.constrain(ufm.encoder_batch(src, tgt, symmetrized))
    feats = self.encoder(images)
    first1, first2 = (self.constrain(v) for v in ufm.split_views(feats[0], symmetrized))
    last1, last2 = (self.constrain(v) for v in ufm.split_views(feats[-1], symmetrized))
    if train and cfg.use_unet_batchnorm:
      # As the official forward: one U-Net call per view, so each call's batch statistics (and
      # running-statistics update) cover one view's images.
      u1, u2 = (self.constrain(self.refiner.unet(x, train=True)) for x in (src, tgt))
    else:
      u = self.refiner.unet(images)
      u1, u2 = ((self.constrain(v) for v in ufm.split_views(u, symmetrized)) if u is not None
                else (None, None))

    (fin1, fin2), inters = self.info_sharing(last1, last2)
    head_in = [self.constrain(t.astype(head_dtype))
               for t in (last1, inters[0][0], inters[1][0], fin1)]
    out = self.heads(head_in, (h, w), (src, tgt))   # the base model's DPT heads + adaptors
    flow = out["flow"]

    # Official: cat(encoder list[0], info-sharing final.float()) per view (one batch there; the
    # combine is per image, so running it per view gives the same maps and keeps the batch layout).
    f1 = self.constrain(self.refiner.combine(
        jnp.concatenate([first1, fin1], -1).astype(head_dtype), u1))
    f2 = self.constrain(self.refiner.combine(
        jnp.concatenate([first2, fin2], -1).astype(head_dtype), u2))
    residual, log_p = self.refiner.refine(f1, f2, flow)
    residual, log_p = self.constrain(residual), self.constrain(log_p)
    return dict(out, flow=flow + residual, flow_before_refinement=flow, residual=residual,
                log_softmax=log_p, feature_map_0=f1, feature_map_1=f2,
                attention_bias=self.refiner.classification_bias)


def refine_model_from_config(cfg: UFMRefineConfig, **kw) -> UFMRefine:
  return UFMRefine(cfg, **kw)
