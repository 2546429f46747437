"""DINOv2 ViT encoder (facebookresearch/dinov2 hub models, as wrapped by UniCeption).

Tokens are [cls, registers..., patches]; the learned position table (1 + 37x37 rows for the
518-px pretraining size) is resized to the input grid with the hub's `interpolate_pos_encoding`
(see `pos_embed_resize_matrix`). `get_intermediate_layers(n=indices, norm=True)` semantics:
the selected block outputs go through the final `norm`, cls/register tokens are dropped.
"""

import dataclasses
from typing import Callable, Optional, Sequence, Tuple, Union

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.models import layers, scan

# (embed_dim, depth, num_heads, ffn) of the hub models dinov2_vit{s,b,l,g}14.
SIZES = {
    "small": (384, 12, 6, "mlp"),
    "base": (768, 12, 12, "mlp"),
    "large": (1024, 24, 16, "mlp"),
    "giant": (1536, 40, 24, "swiglu"),
}


@dataclasses.dataclass(frozen=True)
class DinoV2Config:
  """Structure of the encoder. `depth` is the number of blocks kept (`keep_first_n_layers`)."""
  embed_dim: int = 1024
  depth: int = 24
  num_heads: int = 16
  mlp_ratio: float = 4.0
  ffn: str = "mlp"  # "swiglu" for ViT-g
  patch_size: int = 14
  pos_grid: int = 37  # pretraining grid (518 / 14)
  # Initial position table when training from scratch: "trunc_normal" (DINOv2's, std 0.02) or
  # "sincos" (fixed-frequency 2D sin-cos as in MAE, a usable position signal from step 0).
  pos_embed_init: str = "trunc_normal"
  num_register_tokens: int = 0
  init_values: Optional[float] = 1.0  # LayerScale
  # The hub's *_reg models interpolate with antialias and no offset; the others with offset 0.1.
  interpolate_antialias: bool = False
  interpolate_offset: float = 0.1
  # Which block outputs to return: a tuple of indices or an int (the last n blocks).
  indices: Union[Tuple[int, ...], int] = (23,)
  norm_intermediate: bool = True
  # False: UniCeption replaces the hub model's final norm by an identity (no `norm` params), so
  # the returned maps are raw block outputs whatever norm_intermediate says.
  norm_returned_features: bool = True

  def take_indices(self) -> Tuple[int, ...]:
    if isinstance(self.indices, int):
      return tuple(range(self.depth - self.indices, self.depth))
    # The hub appends block outputs in block order while running the blocks (`if i in n`).
    idx = tuple(sorted({i % self.depth if i < 0 else i for i in self.indices}))
    for i in idx:
      if not 0 <= i < self.depth:
        raise ValueError(f"encoder index {i} out of range for depth {self.depth}")
    return idx


def dinov2_config(size: str, **overrides) -> DinoV2Config:
  """The hub model `dinov2_vit{s,b,l,g}14[_reg]` structure; overrides e.g. depth=, indices=."""
  if size not in SIZES:
    raise ValueError(f"unknown DINOv2 size {size!r}; expected one of {sorted(SIZES)}")
  dim, depth, heads, ffn = SIZES[size]
  return DinoV2Config(**{**dict(embed_dim=dim, depth=depth, num_heads=heads, ffn=ffn,
                                indices=(depth - 1,)), **overrides})


def _cubic_weights(t: np.ndarray, a: float, f=np.float32) -> np.ndarray:
  """The 4 Keys cubic coefficients for taps at offsets -1, 0, 1, 2 (torch's formulas, in the
  tensor's precision f)."""
  a = f(a)

  def c1(x):  # |x| <= 1
    return ((a + f(2)) * x - (a + f(3))) * x * x + f(1)

  def c2(x):  # 1 < |x| < 2
    return ((a * x - f(5) * a) * x + f(8) * a) * x - f(4) * a

  return np.stack([c2(t + f(1)), c1(t), c1(f(1) - t), c2(f(2) - t)], axis=-1).astype(f)


def _bicubic_matrix(n_in: int, n_out: int, inv_scale: float, f=np.float32) -> np.ndarray:
  """[n_out, n_in] weights of torch bicubic (align_corners=False, no antialias, A=-0.75).

  src = (dst + 0.5) * inv_scale - 0.5 in the tensor's precision f; taps clamped to the border.
  """
  dst = np.arange(n_out, dtype=f)
  src = (dst + f(0.5)) * f(inv_scale) - f(0.5)
  i0 = np.floor(src)
  w = _cubic_weights((src - i0).astype(f), -0.75, f)
  m = np.zeros((n_out, n_in), np.float64)
  for k in range(4):
    idx = np.clip(i0.astype(np.int64) - 1 + k, 0, n_in - 1)
    np.add.at(m, (np.arange(n_out), idx), w[:, k])
  return m


def _bicubic_aa_matrix(n_in: int, n_out: int) -> np.ndarray:
  """[n_out, n_in] weights of torch bicubic with antialias=True (size-based, align_corners=False).

  torch's separable anti-aliased kernel (as PIL): cubic with A=-0.5 stretched by the scale when
  downsampling, window truncated at the borders and weights renormalised.
  """
  scale = n_in / n_out
  support = 2.0 * scale if scale >= 1.0 else 2.0
  inv = 1.0 / scale if scale >= 1.0 else 1.0

  def cubic(x, a=-0.5):
    x = abs(x)
    if x < 1.0:
      return ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
    if x < 2.0:
      return (((x - 5.0) * x + 8.0) * x - 4.0) * a
    return 0.0

  m = np.zeros((n_out, n_in), np.float64)
  for i in range(n_out):
    center = scale * (i + 0.5)
    lo = max(int(center - support + 0.5), 0)
    hi = min(int(center + support + 0.5), n_in)
    w = np.array([cubic((j - center + 0.5) * inv) for j in range(lo, hi)])
    total = w.sum()
    m[i, lo:hi] = w / total if total != 0 else w
  return m


def sincos_pos_embed(grid: int, dim: int) -> np.ndarray:
  """[1, 1 + grid*grid, dim] 2D sin-cos table (MAE's get_2d_sincos_pos_embed, cls row 0):
  the first half encodes x (column), the second y (row), each as [sin | cos] of dim/4 freqs."""
  if dim % 4:
    raise ValueError(f"sincos position table needs embed_dim divisible by 4, got {dim}")
  omega = 1.0 / 10000.0 ** (np.arange(dim // 4) / (dim // 4))
  ys, xs = np.meshgrid(np.arange(grid, dtype=np.float64), np.arange(grid, dtype=np.float64),
                       indexing="ij")
  def axis(pos):
    a = pos.reshape(-1)[:, None] * omega[None]
    return np.concatenate([np.sin(a), np.cos(a)], axis=1)
  table = np.concatenate([axis(xs), axis(ys)], axis=1)
  return np.concatenate([np.zeros((1, dim)), table], axis=0)[None].astype(np.float32)


def _pos_embed_init(cfg: DinoV2Config):
  """The flax initializer of `pos_embed`: DINOv2's random table or the config's sin-cos one."""
  if cfg.pos_embed_init == "sincos":
    return lambda _key, shape, dtype=jnp.float32: jnp.asarray(
        sincos_pos_embed(cfg.pos_grid, shape[-1]), dtype)
  if cfg.pos_embed_init == "trunc_normal":
    # torch trunc_normal_(std=0.02) truncates at +-2 absolute, i.e. 100 std: a plain normal.
    return nn.initializers.normal(0.02)
  raise ValueError(f"encoder.pos_embed_init must be 'trunc_normal' or 'sincos', got "
                   f"{cfg.pos_embed_init!r}")


def pos_embed_resize_matrices(cfg: DinoV2Config, h: int, w: int, f=np.float32):
  """(Mh [h, G], Mw [w, G]) resampling the G x G position grid to the h x w patch grid."""
  g = cfg.pos_grid
  if cfg.interpolate_offset:
    # A scale factor is passed to F.interpolate, so torch maps with 1/scale = G / (n + offset).
    mh = _bicubic_matrix(g, h, g / (h + cfg.interpolate_offset), f)
    mw = _bicubic_matrix(g, w, g / (w + cfg.interpolate_offset), f)
  elif cfg.interpolate_antialias:
    mh, mw = _bicubic_aa_matrix(g, h), _bicubic_aa_matrix(g, w)
  else:
    mh = _bicubic_matrix(g, h, g / h, f)
    mw = _bicubic_matrix(g, w, g / w, f)
  return mh, mw


def interpolate_pos_embed(pos_embed: jax.Array, cfg: DinoV2Config, h: int, w: int) -> jax.Array:
  """[1, 1 + G*G, C] -> [1, 1 + h*w, C]; the cls row is passed through untouched."""
  g = cfg.pos_grid
  if h == g and w == g:  # the hub returns the table as is at the pretraining size
    return pos_embed
  cls_row, grid = pos_embed[:, :1], pos_embed[0, 1:].reshape(g, g, -1)
  dtype = grid.dtype
  mh, mw = pos_embed_resize_matrices(cfg, h, w, np.float64 if dtype == jnp.float64 else np.float32)
  hp = jax.lax.Precision.HIGHEST
  out = jnp.einsum("hg,gkc->hkc", jnp.asarray(mh, dtype), grid, precision=hp)
  out = jnp.einsum("wk,hkc->hwc", jnp.asarray(mw, dtype), out, precision=hp)
  return jnp.concatenate([cls_row, out.reshape(1, h * w, -1)], axis=1)


class PatchEmbed(nn.Module):
  """Conv p x p / stride p, flattened to [B, h*w, C] (row-major y, x)."""
  dim: int
  patch_size: int
  dtype: Optional[jnp.dtype] = None

  @nn.compact
  def __call__(self, images):
    p = self.patch_size
    x = layers.Conv(self.dim, (p, p), strides=(p, p), padding="VALID", dtype=self.dtype,
                    name="proj")(images)
    b, h, w, c = x.shape
    return x.reshape(b, h * w, c)


class DinoV2(nn.Module):
  """The ViT; returns the selected block outputs as [B, h, w, C] maps (and sows internals)."""
  config: DinoV2Config
  dtype: Optional[jnp.dtype] = None  # compute dtype (bf16 option); params stay float32
  remat: bool = False
  activation_sharding: layers.ActivationHook = None
  attention_impl: Optional[str] = None
  scan: bool = False  # blocks as stacked params + lax.scan (models/scan.py)
  layer_gather: Optional[Callable] = None  # scan.LayerGather: FSDP per-layer gather (scan only)

  @nn.compact
  def __call__(self, images: jax.Array) -> Sequence[jax.Array]:
    """images: [B, H, W, 3] normalised; H, W multiples of the patch size."""
    cfg = self.config
    b, hh, ww, _ = images.shape
    p = cfg.patch_size
    h, w = hh // p, ww // p
    c = cfg.embed_dim
    constrain = self.activation_sharding or layers.identity

    cls_token = self.param("cls_token", nn.initializers.normal(1e-6), (1, 1, c))
    pos_embed = self.param("pos_embed", _pos_embed_init(cfg), (1, 1 + cfg.pos_grid ** 2, c))
    # The residual stream stays in the parameter dtype (float32), as under torch autocast where
    # cat(cls, patches) + pos promotes to float32; only the matmuls run in `dtype`.
    x = PatchEmbed(c, p, self.dtype, name="patch_embed")(images).astype(pos_embed.dtype)
    self.sow("intermediates", "patch_embed_tokens", x)
    pos = interpolate_pos_embed(pos_embed, cfg, h, w)
    self.sow("intermediates", "pos_embed_interp", pos)
    x = jnp.concatenate([jnp.broadcast_to(cls_token, (b, 1, c)), x], axis=1) + pos
    if cfg.num_register_tokens:
      reg = self.param("register_tokens", nn.initializers.normal(1e-6),
                       (1, cfg.num_register_tokens, c))
      x = jnp.concatenate(
          [x[:, :1], jnp.broadcast_to(reg, (b, cfg.num_register_tokens, c)),
           x[:, 1:]], axis=1)
    self.sow("intermediates", "tokens_in", x)
    x = constrain(x)

    take = cfg.take_indices()
    # float32 out, as torch autocast runs LayerNorm
    norm = layers.layer_norm("norm") if cfg.norm_returned_features else layers.identity
    kw = dict(num_heads=cfg.num_heads, mlp_ratio=cfg.mlp_ratio, qkv_bias=True, qk_norm=False,
              init_values=cfg.init_values, ffn=cfg.ffn, dtype=self.dtype,
              attention_impl=self.attention_impl)
    outs = {}
    # Blocks after the last returned index cannot change any output, so they are not run.
    if self.scan:
      # One scan per segment ending at a returned index: each tap is a segment's final carry.
      block = layers.Block(**kw, parent=None)
      stack = scan.stacked_params(self, "blocks", block, cfg.depth, c)
      collect = self.is_mutable_collection("intermediates")
      path = "/".join((*self.scope.path, "blocks"))
      for lo, hi in scan.segments([i + 1 for i in take]):
        x, ys = scan.run(block, stack, x, lo, hi, self.remat, constrain, collect,
                         self.layer_gather, path)
        for i in range(lo, hi) if collect else ():
          self.sow("intermediates", f"block{i}_out", ys[i - lo])
        outs[hi - 1] = x
    else:
      block = layers.block_class(self.remat)
      for i in range(max(take) + 1):
        x = block(**kw, name=f"blocks_{i}")(x)
        x = constrain(x)
        self.sow("intermediates", f"block{i}_out", x)
        if i in take:
          outs[i] = x
    skip = 1 + cfg.num_register_tokens
    result = []
    for i in take:
      y = norm(outs[i]) if cfg.norm_intermediate else outs[i]
      result.append(y[:, skip:].reshape(b, h, w, c))
      self.sow("intermediates", f"out{len(result) - 1}", result[-1])
    # Parameters of blocks that are never run still exist in the checkpoint: create them so the
    # tree has the checkpoint's structure (init only; apply never touches them). The stacked
    # tree of the scan holds all `depth` blocks already.
    if self.is_initializing() and not self.scan:
      for i in range(max(take) + 1, cfg.depth):
        block(**kw, name=f"blocks_{i}")(x)
    if self.is_initializing() and not cfg.norm_intermediate:
      norm(x)  # the hub model's final norm exists (unused) unless norm_returned_features=False
    return result


def resize_pos_embed(pe: np.ndarray, new_shape) -> np.ndarray:
  """[1, extra + g*g, D] -> [1, extra + g'*g', D]: bicubic on the square grid, extra tokens kept."""
  pe = np.asarray(pe, np.float32)
  n_old, n_new = pe.shape[1], new_shape[1]
  for extra in (1, 0):
    g_old, g_new = np.sqrt(n_old - extra), np.sqrt(n_new - extra)
    if g_old == int(g_old) and g_new == int(g_new):
      g_old, g_new = int(g_old), int(g_new)
      grid = pe[0, extra:].reshape(g_old, g_old, -1)
      grid = jax.image.resize(jnp.asarray(grid), (g_new, g_new, grid.shape[-1]), "cubic")
      return np.concatenate([pe[0, :extra], np.asarray(grid).reshape(g_new * g_new, -1)])[None]
  raise ValueError(f"cannot resize position embedding {pe.shape} -> {tuple(new_shape)}")

