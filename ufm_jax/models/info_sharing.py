"""The fused two-view global-attention transformer ("info sharing",
UniCeption `MultiViewGlobalAttentionTransformerIFR`).

Tokens of both views are concatenated [view1 (row-major y, x); view2], projected, tagged with a
sinusoidal view embedding (row 0 for view 1, row 1 for view 2) and run through pre-norm
self-attention blocks; the selected intermediate outputs and the final output all go through the
same final `norm`.

The UniCeption v0.1.6 options keep their official names: no view embedding at all
(`distinguish_ref_and_non_ref_views=False`), none for view 2 (`use_pe_for_non_reference_views=
False`, a one-row table), and a query scale of log(N) (`use_scalable_softmax`) and/or
sqrt(growth * log(N) / log(base)) (`use_entropy_scaling`) for N tokens in the sequence.
`use_rand_idx_pe_for_non_reference_views`: the official forward draws view 2's row at random
from the table on every call (eval included); here view 2 always gets row 1, the row the
official code uses with the option off and the only one it can draw from a two-row table.
"""

import dataclasses
from typing import Optional, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.models import layers, scan


@dataclasses.dataclass(frozen=True)
class InfoSharingConfig:
  input_embed_dim: int = 1024
  dim: int = 768
  depth: int = 12
  num_heads: int = 12
  mlp_ratio: float = 4.0
  qkv_bias: bool = True
  qk_norm: bool = False
  init_values: Optional[float] = None  # LayerScale when set
  indices: Tuple[int, ...] = (5, 8)  # 0-based blocks whose (normed) output feeds the DPT heads
  norm_intermediate: bool = True
  max_num_views: int = 2  # rows of the view-embedding table (official max_num_views_for_pe)
  distinguish_ref_and_non_ref_views: bool = True   # False: no view embedding (and no table)
  use_pe_for_non_reference_views: bool = True      # False: view 2 untagged, a one-row table
  # Recorded for export only: the forward always uses row 1 (module docstring).
  use_rand_idx_pe_for_non_reference_views: bool = False
  use_scalable_softmax: bool = False
  use_entropy_scaling: bool = False
  base_token_count_for_entropy_scaling: int = 444
  entropy_scaling_growth_factor: float = 1.4
  # From-scratch init only: every block's key projection starts equal to its query projection,
  # both this scale x the default draw (layers.tied_qkv_init), so attention starts by matching
  # look-alike tokens across the views. None: independent draws, as PyTorch.
  tied_qk_init: Optional[float] = None

  def take_indices(self) -> Tuple[int, ...]:
    idx = tuple(sorted({i % self.depth if i < 0 else i for i in self.indices}))
    for i in idx:
      if not 0 <= i < self.depth:
        raise ValueError(f"info-sharing index {i} out of range for depth {self.depth}")
    return idx


def view_table_rows(cfg: InfoSharingConfig) -> int:
  """Rows of the official `view_pos_table` buffer (0: the module has none)."""
  if not cfg.distinguish_ref_and_non_ref_views:
    return 0
  return cfg.max_num_views if cfg.use_pe_for_non_reference_views else 1


def query_scale(cfg: InfoSharingConfig, num_tokens: int) -> float:
  """The factor UniCeption's attention multiplies the queries by for a sequence of `num_tokens`
  (scalable softmax: log N; entropy scaling: sqrt(growth log N / log base)), in float32 as the
  official tensors compute it."""
  scale = np.float32(1.0)
  log_n = np.log(np.float32(num_tokens))
  if cfg.use_scalable_softmax:
    scale = scale * log_n
  if cfg.use_entropy_scaling:
    scale = scale * np.sqrt(np.float32(cfg.entropy_scaling_growth_factor) * log_n
                            / np.log(np.float32(cfg.base_token_count_for_entropy_scaling)))
  return float(scale)


def sinusoid_table(n_position: int, dim: int, base: float = 10000.0) -> np.ndarray:
  """pe[p, j] = sin(p / base**(2*(j//2)/dim)) for even j, cos for odd j; float64 -> float32."""
  j = np.arange(dim)
  angle = np.arange(n_position)[:, None] / np.power(base, 2 * (j // 2) / dim)[None, :]
  table = np.where(j % 2 == 0, np.sin(angle), np.cos(angle))
  return table.astype(np.float32)


class InfoSharing(nn.Module):
  """Returns (final, [intermediates...]), each a pair (view1, view2) of [B, h, w, dim] maps."""
  config: InfoSharingConfig
  dtype: Optional[jnp.dtype] = None
  remat: bool = False
  activation_sharding: layers.ActivationHook = None
  attention_impl: Optional[str] = None
  scan: bool = False  # blocks as stacked params + lax.scan (models/scan.py)

  @nn.compact
  def __call__(self, feat1: jax.Array, feat2: jax.Array):
    cfg = self.config
    b, h, w, c = feat1.shape
    n = h * w
    constrain = self.activation_sharding or layers.identity
    x = jnp.concatenate([feat1.reshape(b, n, c), feat2.reshape(b, n, c)], axis=1)
    if cfg.input_embed_dim != cfg.dim:
      x = layers.Dense(cfg.dim, dtype=self.dtype, name="proj_embed")(x)
    self.sow("intermediates", "proj_embed_out", x)
    # A buffer in the PyTorch module, not a parameter: constant here (the loader checks it).
    if cfg.distinguish_ref_and_non_ref_views:
      table = sinusoid_table(max(view_table_rows(cfg), 2), cfg.dim)
      if not cfg.use_pe_for_non_reference_views:
        table[1] = 0.0
      view_pe = jnp.repeat(jnp.asarray(table[:2]), n, axis=0)  # [2n, dim]
      x = x + view_pe.astype(jnp.promote_types(x.dtype, jnp.float32))
    self.sow("intermediates", "tokens_in", x)
    x = constrain(x)

    norm = layers.layer_norm("norm")  # float32 out, as torch autocast runs LayerNorm
    take = cfg.take_indices()
    kw = dict(num_heads=cfg.num_heads, mlp_ratio=cfg.mlp_ratio, qkv_bias=cfg.qkv_bias,
              qk_norm=cfg.qk_norm, init_values=cfg.init_values, ffn="mlp", dtype=self.dtype,
              attention_impl=self.attention_impl, tied_qk_init=cfg.tied_qk_init,
              query_scale=query_scale(cfg, 2 * n))
    inters = []
    if self.scan:
      # One scan per segment ending at an intermediate tap (and one for the rest).
      block = layers.Block(**kw, parent=None)
      stack = scan.stacked_params(self, "self_attention_blocks", block, cfg.depth, cfg.dim)
      collect = self.is_mutable_collection("intermediates")
      for lo, hi in scan.segments([i + 1 for i in take] + [cfg.depth]):
        x, ys = scan.run(block, stack, x, lo, hi, self.remat, constrain, collect)
        for i in range(lo, hi) if collect else ():
          self.sow("intermediates", f"block{i}_out", ys[i - lo])
        if hi - 1 in take:
          inters.append(norm(x) if cfg.norm_intermediate else x)
    else:
      block = layers.block_class(self.remat)
      for i in range(cfg.depth):
        x = block(**kw, name=f"self_attention_blocks_{i}")(x)
        x = constrain(x)
        self.sow("intermediates", f"block{i}_out", x)
        if i in take:
          inters.append(norm(x) if cfg.norm_intermediate else x)

    def split(t):
      t = t.reshape(b, 2, h, w, cfg.dim)
      return t[:, 0], t[:, 1]

    final, inters = split(norm(x)), [split(t) for t in inters]
    self.sow("intermediates", "final", final)
    for k, t in enumerate(inters):
      self.sow("intermediates", f"inter{k}", t)
    return final, inters
