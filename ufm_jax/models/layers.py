"""Transformer building blocks shared by the DINOv2 encoder and the info-sharing transformer.

Submodule and parameter names follow the PyTorch modules (timm / DINOv2 / UniCeption), so the
weight conversion in `ufm_jax.official` is a mechanical rename: `qkv`, `proj`, `fc1`, `fc2`,
`norm1`, `norm2`, `ls1.gamma`, `ls2.gamma`, `q_norm`, `k_norm`, `w12`, `w3`.
"""

import functools
from typing import Any, Callable, Optional

import flax.linen as nn
import jax
import jax.numpy as jnp

Dtype = Any

# Every LayerNorm of UFM uses eps 1e-6. Two-pass variance (as torch) instead of E[x^2]-E[x]^2.
# Block and final norms run in the residual dtype (float32) even in bf16 mode, as torch autocast
# does; the following Dense casts to bf16.
LN_EPS = 1e-6


def layer_norm(name: str, dtype: Optional[Dtype] = None) -> nn.LayerNorm:
  return nn.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, dtype=dtype, name=name)


def identity(x):
  return x


class LayerScale(nn.Module):
  """x * gamma (the DINOv2 / timm LayerScale)."""
  init_values: float = 1.0

  @nn.compact
  def __call__(self, x):
    gamma = self.param("gamma", nn.initializers.constant(self.init_values), (x.shape[-1],))
    return x * gamma.astype(x.dtype)


def tied_qkv_init(scale: float = 1.0, base=nn.initializers.lecun_normal()):
  """Initializer of a fused [c, 3c] qkv kernel whose key block starts equal to its query block,
  both `scale` x a `base` draw (the value block is an independent `base` draw).

  Attention logits then start as q.k = |W x|^2-like feature similarity (sharper for larger
  `scale`), so a token attends to look-alike tokens from step 0. A from-scratch option:
  pretrained weights replace it anyway.
  """
  def init(key, shape, dtype=jnp.float32):
    c = shape[0]
    if shape[-1] != 3 * c:
      raise ValueError(f"tied_qkv_init needs a [c, 3c] qkv kernel, got shape {shape}")
    kq, kv = jax.random.split(key)
    wq = scale * base(kq, (c, c), dtype)
    return jnp.concatenate([wq, wq, base(kv, (c, c), dtype)], axis=-1)
  return init


LOW_PRECISION = (jnp.bfloat16, jnp.float16)


def _on_cpu(wide: Callable, plain: Callable, *operands):
  """`wide(*operands)` where the computation is lowered for CPU, `plain(*operands)` elsewhere
  (chosen per platform at lowering, so a multi-platform export carries both)."""
  return jax.lax.platform_dependent(*operands, cpu=wide, default=plain)


def _bits(x):
  """bf16/f16 -> the same bits as uint16 (other dtypes unchanged). XLA:CPU widens bf16 operands
  of dynamic slices, gathers and concatenates to float32, and then hoists that widening out of
  loops: a loop slicing a bf16 array would carry (and read) a float32 copy of all of it. Integers
  are moved as they are."""
  return jax.lax.bitcast_convert_type(x, jnp.uint16) if x.dtype in LOW_PRECISION else x


def _unbits(x, dtype):
  return jax.lax.bitcast_convert_type(x, dtype) if x.dtype != dtype else x


def dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None, **kw):
  """lax.dot_general for the model's Dense layers. bf16/f16 operands on CPU accumulate into a
  float32 result that is then rounded: XLA:CPU runs that form with its bf16 (AVX-512 BF16/AMX)
  kernels, while a bf16-out dot is upcast to a float32 dot and gains nothing over float32.
  Other platforms (chosen when lowering) keep the plain dot, which already accumulates in f32."""
  plain = functools.partial(jax.lax.dot_general, dimension_numbers=dimension_numbers,
                            precision=precision, preferred_element_type=preferred_element_type, **kw)
  dtype = jnp.result_type(lhs, rhs)
  if preferred_element_type is not None or dtype not in LOW_PRECISION:
    return plain(lhs, rhs)
  def wide(l, r):
    return jax.lax.dot_general(l, r, dimension_numbers, precision,
                               preferred_element_type=jnp.float32, **kw).astype(dtype)
  return _on_cpu(wide, plain, lhs, rhs)


Dense = functools.partial(nn.Dense, dot_general=dot_general)


def einsum(spec: str, a, b):
  """Two-operand jnp.einsum with dot_general's rule: bf16/f16 on CPU as bf16 x bf16 -> f32,
  rounded back (the weight-only einsums of the up-convolutions)."""
  dtype = jnp.result_type(a, b)
  plain = functools.partial(jnp.einsum, spec)
  if dtype not in LOW_PRECISION:
    return plain(a, b)
  wide = lambda a, b: jnp.einsum(spec, a, b, preferred_element_type=jnp.float32).astype(dtype)  # noqa: E731
  return _on_cpu(wide, plain, a, b)


# Output rows of the bf16 convolution loop per step are sized so that the step's column matrix
# ([batch x rows x width, kh x kw x channels] bf16) holds about this many values (8 MiB).
# benchmarks/cpu_attention.py --conv sweeps it (docs/cpu_inference.md).
CPU_CONV_TILE = 2**22
# A kh x kw convolution from c to o channels runs as dots only when c o / (c + o) exceeds this:
# a narrow one (the U-Net's 64-channel full-resolution level, 128 -> 128 at 420x560) spends
# more on writing and reading its column matrix than the bf16 dots save, and XLA's (float32)
# convolution is as fast or faster there.
CPU_CONV_MIN_WIDTH = 64


def conv_as_dots(x, k, strides=(1, 1), padding=((0, 0), (0, 0)), tile: int = CPU_CONV_TILE,
                 dtype=jnp.float32):
  """NHWC x HWIO convolution as dots with float32 accumulation, the result rounded to `dtype`.

  XLA:CPU compiles a bf16 convolution as a float32 one between converts, so it never reaches the
  bf16 x bf16 -> f32 dot kernels (about twice its float32 rate on this CPU). Here: 1x1
  convolutions are one dot, patchifying ones (stride = kernel, the patch embedding) a reshape and
  one dot, and the others a loop over blocks of output rows: each step stacks its rows' kh x kw
  taps side by side ([b rows wo, kh kw c], im2col of the block) and takes one dot with the
  [kh kw c, o] kernel (kh dots of the kw column taps, one per kernel row, were slower in the
  sweep of benchmarks/cpu_attention.py --conv). A whole-map column matrix (kh kw times the input) made the
  convolution memory-bound. The loop slices and stacks the taps as uint16 bits (`_bits`), so
  they stay one bf16 copy.
  """
  b, _, _, c = x.shape
  kh, kw, _, o = k.shape
  sh, sw = strides
  if any(p != 0 for pp in padding for p in pp):
    x = jnp.pad(x, ((0, 0), tuple(padding[0]), tuple(padding[1]), (0, 0)))
  hi, wi = x.shape[1:3]
  ho, wo = (hi - kh) // sh + 1, (wi - kw) // sw + 1
  f32 = jnp.float32
  if kh == kw == 1:
    x = x[:, :sh * (ho - 1) + 1:sh, :sw * (wo - 1) + 1:sw]
    return jnp.dot(x.reshape(-1, c), k.reshape(c, o), preferred_element_type=f32).reshape(
        b, ho, wo, o).astype(dtype)
  if (sh, sw) == (kh, kw):
    x = x[:, :ho * kh, :wo * kw].reshape(b, ho, kh, wo, kw, c).transpose(0, 1, 3, 2, 4, 5)
    return jnp.dot(x.reshape(-1, kh * kw * c), k.reshape(kh * kw * c, o),
                   preferred_element_type=f32).reshape(b, ho, wo, o).astype(dtype)
  width = kh * kw * c
  rows = max(1, min(ho, tile // max(1, b * wo * width)))
  x_dtype, x = x.dtype, _bits(x)

  def block(r0, rows):
    """Output rows r0 .. r0 + rows, [b, rows, wo, o] in `dtype`."""
    span = sh * (rows - 1) + kh
    xs = jax.lax.dynamic_slice_in_dim(x, r0 * sh, span, axis=1)
    cols = jnp.stack([xs[:, i:i + sh * (rows - 1) + 1:sh, j:j + sw * (wo - 1) + 1:sw]
                      for i in range(kh) for j in range(kw)], -2)
    acc = jnp.dot(_unbits(cols, x_dtype).reshape(-1, width), k.reshape(width, o),
                  preferred_element_type=f32)
    return acc.reshape(b, rows, wo, o).astype(dtype)

  if rows >= ho:
    return block(0, ho)
  steps = -(-ho // rows)

  def step(i, out):
    # A last block that would overhang starts earlier and recomputes a few rows.
    r0 = jnp.minimum(i * rows, ho - rows)
    return jax.lax.dynamic_update_slice_in_dim(out, block(r0, rows), r0, axis=1)

  return jax.lax.fori_loop(0, steps, step, jnp.zeros((b, ho, wo, o), dtype))


_NHWC = ("NHWC", "HWIO", "NHWC")


def conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None,
                         dimension_numbers=None, feature_group_count=1, batch_group_count=1,
                         precision=None, preferred_element_type=None):
  """lax.conv_general_dilated for the model's convolutions (flax nn.Conv's hook). bf16/f16 NHWC
  convolutions without dilation or groups run on CPU as `conv_as_dots` (bf16 x bf16 -> f32 dots,
  rounded back), except narrow ones (CPU_CONV_MIN_WIDTH); float32 and other platforms keep XLA's
  convolution."""
  plain = functools.partial(
      jax.lax.conv_general_dilated, window_strides=window_strides, padding=padding,
      lhs_dilation=lhs_dilation, rhs_dilation=rhs_dilation, dimension_numbers=dimension_numbers,
      feature_group_count=feature_group_count, batch_group_count=batch_group_count,
      precision=precision, preferred_element_type=preferred_element_type)
  dtype = jnp.result_type(lhs, rhs)
  if (preferred_element_type is not None or dtype not in LOW_PRECISION or lhs.ndim != 4
      or feature_group_count != 1 or batch_group_count != 1
      or any(d != 1 for d in (lhs_dilation or ()) + tuple(rhs_dilation or ()))
      or jax.lax.conv_dimension_numbers(lhs.shape, rhs.shape, dimension_numbers)
      != jax.lax.conv_dimension_numbers(lhs.shape, rhs.shape, _NHWC)):
    return plain(lhs, rhs)
  if isinstance(padding, str):
    padding = jax.lax.padtype_to_pads(lhs.shape[1:3], rhs.shape[:2], window_strides, padding)
  padding = tuple(tuple(int(v) for v in p) for p in padding)
  c, o = rhs.shape[2:]
  if any(v < 0 for p in padding for v in p) or (
      rhs.shape[:2] != (1, 1) and tuple(window_strides) != rhs.shape[:2]
      and c * o <= CPU_CONV_MIN_WIDTH * (c + o)):
    return plain(lhs, rhs)
  wide = lambda x, k: conv_as_dots(x, k, tuple(window_strides), padding, dtype=dtype)  # noqa: E731
  return _on_cpu(wide, plain, lhs, rhs)


Conv = functools.partial(nn.Conv, conv_general_dilated=conv_general_dilated)


ATTENTION_IMPLS = (None, "auto", "xla", "cudnn", "cpu")

# The "cpu" path's logits tile ([batch, query chunk, keys] float32), counted in logits: 4 Mi logits
# are 16 MiB, small enough to stay in the 32 MiB L3 between the two matmuls and the softmax.
# benchmarks/cpu_attention.py sweeps it; benchmarks/inference.py --breakdown measures the layers.
CPU_ATTENTION_TILE = 4 * 2**20


def attention_implementation(impl: Optional[str], dtype, head_dim: int) -> str:
  """"xla", "cudnn" or "cpu" for `dot_product_attention`. None/"auto": cuDNN's fused flash
  kernel on GPU for bf16/f16 with a head dim it takes (a multiple of 8, at most 128; 256 on
  Hopper is not assumed); elsewhere "auto" (the cpu path on CPU, XLA on TPU/GPU, chosen per
  platform at lowering so a multi-platform export carries both)."""
  if impl not in ATTENTION_IMPLS:
    raise ValueError(f"attention_impl {impl!r}; expected one of {ATTENTION_IMPLS}")
  if impl in ("xla", "cudnn", "cpu"):
    return impl
  if (jax.default_backend() == "gpu" and jnp.dtype(dtype) in (jnp.bfloat16, jnp.float16)
      and head_dim % 8 == 0 and head_dim <= 128):
    return "cudnn"
  return "auto"


def cpu_attention(q, k, v, scale: float, tile: int = CPU_ATTENTION_TILE):
  """Exact softmax attention as a loop over heads and query chunks ([B, N, heads, hd] in/out).

  XLA:CPU runs the one-shot formulation (all heads' [B, heads, N, M] logits at once) at 20-35%
  of its matmul peak on UFM's shapes, memory-bound on the logits; one head and query chunk at a
  time keeps each logits tile in cache and reaches ~90%. Logits and the softmax are float32 for
  any input dtype, as in jax.nn.dot_product_attention. The batch stays a dimension of every op
  (no loop over it), so a batch-sharded input needs no collective.

  Each step slices its head and chunk straight out of the [B, N, heads, hd] operands and writes
  its output back in place: head-major copies of q, k, v and of the output (four XLA:CPU
  transposes per layer) made the attention core 6-9% slower at UFM-Base's shapes
  (benchmarks/cpu_attention.py --compare). A last chunk that would overhang N starts earlier
  and recomputes a few rows, so q needs no padded copy either.
  """
  b, n, h, d = q.shape
  m = k.shape[1]
  # A symbolic batch (jax.export) sizes the chunks for one pair.
  chunks = max(1, -(-(b if isinstance(b, int) else 1) * n * m // tile))
  cq = -(-n // chunks)
  dtype = q.dtype
  scale = jnp.asarray(scale, dtype)
  # bf16 operands are sliced as their uint16 bits (_bits): else XLA:CPU carries float32 copies.
  q, k, v = _bits(q), _bits(k), _bits(v)

  def step(i, out):
    hi = i // chunks
    start = jnp.minimum((i % chunks) * cq, n - cq)
    qc = _unbits(jax.lax.dynamic_slice_in_dim(
        jax.lax.dynamic_index_in_dim(q, hi, axis=2, keepdims=False), start, cq, axis=1),
                 dtype) * scale
    kh = _unbits(jax.lax.dynamic_index_in_dim(k, hi, axis=2, keepdims=False), dtype)
    vh = _unbits(jax.lax.dynamic_index_in_dim(v, hi, axis=2, keepdims=False), dtype)
    s = jnp.einsum("bqd,bkd->bqk", qc, kh, preferred_element_type=jnp.float32)
    p = jnp.exp(s - jnp.max(s, axis=-1, keepdims=True))
    o = jnp.einsum("bqk,bkd->bqd", p.astype(vh.dtype), vh, preferred_element_type=jnp.float32)
    o = (o / jnp.sum(p, axis=-1, keepdims=True)).astype(out.dtype)
    zero = jnp.zeros((), start.dtype)
    return jax.lax.dynamic_update_slice(out, o[:, :, None],
                                        (zero, start, hi.astype(start.dtype), zero))

  return jax.lax.fori_loop(0, h * chunks, step, jnp.zeros(q.shape, dtype))


def _xla_attention(q, k, v, scale):
  return jax.nn.dot_product_attention(q, k, v, scale=scale, implementation="xla")


def _cudnn_attention(q, k, v, scale):
  return jax.nn.dot_product_attention(q, k, v, scale=scale, implementation="cudnn")


def fused_forward_xla_backward(forward: Callable) -> Callable:
  """(q, k, v, scale) -> attention whose forward is `forward` (the fused kernel) and whose
  gradient is XLA's attention's (logits recomputed from the saved q, k, v).

  jax's cuDNN attention refuses to be differentiated at an odd sequence length ("Unsupported
  sequence length Q 1201, KV 1201", seen with jax 0.11.2 on an H200): its training check counts
  the empty placeholder it passes for "no bias" as a bias, and biased training needs even
  lengths. UFM's encoder sees 1 + h*w tokens (1201 at 420x560, 3711 at 742x980), so the UFM-560
  train step failed on GPU; its forward runs fused at those lengths.
  """
  @functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
  def attention(q, k, v, scale):
    return forward(q, k, v, scale)

  def fwd(q, k, v, scale):
    return forward(q, k, v, scale), (q, k, v)

  def bwd(scale, res, g):
    _, vjp = jax.vjp(lambda q, k, v: _xla_attention(q, k, v, scale), *res)
    return vjp(g)

  attention.defvjp(fwd, bwd)
  return attention


# The kernel is looked up at each call, so a test can stand in for cuDNN on CPU.
_cudnn_forward_xla_backward = fused_forward_xla_backward(
    lambda q, k, v, scale: _cudnn_attention(q, k, v, scale))


def _cudnn(q, k, v, scale):
  """cuDNN's fused attention, trainable at any sequence length: its own gradient where the
  lengths are even, else XLA's (fused_forward_xla_backward)."""
  n, m = q.shape[1], k.shape[1]
  if isinstance(n, int) and isinstance(m, int) and n % 2 == 0 and m % 2 == 0:
    return _cudnn_attention(q, k, v, scale)
  return _cudnn_forward_xla_backward(q, k, v, scale)


def dot_product_attention(q, k, v, scale: float, impl: Optional[str] = None):
  """[B, N, heads, hd] attention by `attention_implementation`. In auto mode a cuDNN refusal
  at trace time (cuDNN missing, an unsupported GPU or shape) falls back to XLA; a forced
  "cudnn" raises it."""
  chosen = attention_implementation(impl, q.dtype, q.shape[-1])
  xla = lambda q, k, v: _xla_attention(q, k, v, scale)  # noqa: E731
  if chosen == "cudnn" and impl in (None, "auto"):
    try:
      return _cudnn(q, k, v, scale)
    except (NotImplementedError, RuntimeError, ValueError):
      chosen = "xla"
  if chosen == "auto":
    return jax.lax.platform_dependent(q, k, v, cpu=lambda q, k, v: cpu_attention(q, k, v, scale),
                                      default=xla)
  if chosen == "cpu":
    return cpu_attention(q, k, v, scale)
  if chosen == "xla":
    return xla(q, k, v)
  return _cudnn(q, k, v, scale)


class Attention(nn.Module):
  """Multi-head self-attention: fused qkv projection, optional per-head q/k LayerNorm."""
  num_heads: int
  qkv_bias: bool = True
  qk_norm: bool = False
  dtype: Optional[Dtype] = None
  implementation: Optional[str] = None  # None/"auto", "xla", "cudnn", "cpu" (attention_implementation)
  tied_qk_init: Optional[float] = None  # from-scratch: W_k = W_q, this scale (tied_qkv_init)
  query_scale: float = 1.0  # extra factor on the logits (UniCeption's scalable softmax/entropy)

  @nn.compact
  def __call__(self, x):
    b, n, c = x.shape
    head_dim = c // self.num_heads
    kernel_init = (nn.initializers.lecun_normal() if self.tied_qk_init is None
                   else tied_qkv_init(self.tied_qk_init))
    qkv = Dense(3 * c, use_bias=self.qkv_bias, dtype=self.dtype, kernel_init=kernel_init,
                   name="qkv")(x)
    # torch: reshape(B, N, 3, heads, head_dim); jax.nn.dot_product_attention wants [B, N, heads, hd].
    qkv = qkv.reshape(b, n, 3, self.num_heads, head_dim)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
    if self.qk_norm:
      q = layer_norm("q_norm", self.dtype)(q)
      k = layer_norm("k_norm", self.dtype)(k)
    if q.dtype == jnp.float64:
      # jax.nn.dot_product_attention always takes the softmax in float32; keep float64 exact.
      logits = jnp.einsum("bqhd,bkhd->bhqk", q, k) * (head_dim ** -0.5 * self.query_scale)
      out = jnp.einsum("bhqk,bkhd->bqhd", jax.nn.softmax(logits, axis=-1), v)
    else:
      out = dot_product_attention(q, k, v, head_dim ** -0.5 * self.query_scale,
                                  self.implementation)
    out = out.reshape(b, n, c)
    return Dense(c, dtype=self.dtype, name="proj")(out)


class Mlp(nn.Module):
  """fc1 -> exact (erf) GELU -> fc2."""
  hidden_dim: int
  dtype: Optional[Dtype] = None

  @nn.compact
  def __call__(self, x):
    c = x.shape[-1]
    h = Dense(self.hidden_dim, dtype=self.dtype, name="fc1")(x)
    h = jax.nn.gelu(h, approximate=False)
    return Dense(c, dtype=self.dtype, name="fc2")(h)


class SwiGLUFFN(nn.Module):
  """DINOv2 ViT-g feed-forward: w12 -> (silu(x1) * x2) -> w3 (names as `SwiGLUFFNFused`)."""
  hidden_dim: int
  dtype: Optional[Dtype] = None

  @nn.compact
  def __call__(self, x):
    c = x.shape[-1]
    x12 = Dense(2 * self.hidden_dim, dtype=self.dtype, name="w12")(x)
    x1, x2 = jnp.split(x12, 2, axis=-1)
    return Dense(c, dtype=self.dtype, name="w3")(jax.nn.silu(x1) * x2)


def swiglu_hidden_dim(dim: int, mlp_ratio: float) -> int:
  """DINOv2's SwiGLUFFNFused rounds 2/3 of the MLP width up to a multiple of 8."""
  hidden = int(dim * mlp_ratio)
  return (int(hidden * 2 / 3) + 7) // 8 * 8


class Block(nn.Module):
  """Pre-norm transformer block: x + ls1(attn(norm1(x))); x + ls2(mlp(norm2(x)))."""
  num_heads: int
  mlp_ratio: float = 4.0
  qkv_bias: bool = True
  qk_norm: bool = False
  init_values: Optional[float] = None  # LayerScale when set
  ffn: str = "mlp"  # "mlp" or "swiglu"
  dtype: Optional[Dtype] = None
  attention_impl: Optional[str] = None
  tied_qk_init: Optional[float] = None
  query_scale: float = 1.0

  @nn.compact
  def __call__(self, x):
    c = x.shape[-1]
    ls = (lambda name: LayerScale(self.init_values, name=name)) if self.init_values else (
        lambda name: identity)
    y = layer_norm("norm1")(x)
    y = Attention(num_heads=self.num_heads, qkv_bias=self.qkv_bias, qk_norm=self.qk_norm,
                  dtype=self.dtype, implementation=self.attention_impl,
                  tied_qk_init=self.tied_qk_init, query_scale=self.query_scale, name="attn")(y)
    x = x + ls("ls1")(y)
    y = layer_norm("norm2")(x)
    if self.ffn == "mlp":
      y = Mlp(int(c * self.mlp_ratio), self.dtype, name="mlp")(y)
    elif self.ffn == "swiglu":
      y = SwiGLUFFN(swiglu_hidden_dim(c, self.mlp_ratio), self.dtype, name="mlp")(y)
    else:
      raise ValueError(f"unknown ffn {self.ffn!r}; expected 'mlp' or 'swiglu'")
    return x + ls("ls2")(y)


def block_class(remat: bool) -> type:
  """The Block class, wrapped in nn.remat (gradient checkpointing per block) when asked."""
  return nn.remat(Block) if remat else Block


ActivationHook = Optional[Callable[[jax.Array], jax.Array]]
