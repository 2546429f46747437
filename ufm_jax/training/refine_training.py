"""The refinement losses of the official training code (supplementary "Training the Refinement").

The P x P attention of a pixel is a distribution over integer offsets around the regressed flow;
it is supervised with cross-entropy against the ground-truth location spread bilinearly over its
4 neighbouring offsets ("4_point_average"), on covisible pixels whose residual lies inside the
window.

  RefinementCE      RefinementCrossEntropyLossEfficient, the train loss of the refine recipes
                    (loss/refinement_cross_entropy_efficient.py): recomputes the attention from
                    the two feature maps at the supervised pixels only.
  RefinementCEEval  RefinementCrossEntropyLoss, their test loss (loss/refinement_cross_entropy.py):
                    reads the model's log-softmax windows.

Both are terms of a `ufm_jax.training.losses.Recipe`; the windows are row-major over (dy, dx), index
dy_index * P + dx_index, offset = index - P // 2.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from ufm_jax.training import loss_common

_DTYPES = {"bfloat16": jnp.bfloat16, "float32": jnp.float32}


def _window_weights(start_xy, frac_xy, p: int):
  """[..., P*P] bilinear weights of the 4 window cells around a location: (1-fy)(1-fx) at
  (y0, x0), fy(1-fx) at (y0+1, x0), (1-fy)fx at (y0, x0+1), fy fx at (y0+1, x0+1), as the
  official scatter of w0..w3 at offsets 0, P, 1, P+1 (start_xy [..., 2] int, frac_xy float)."""
  fx, fy = frac_xy[..., 0], frac_xy[..., 1]
  base = start_xy[..., 1] * p + start_xy[..., 0]
  cells = jnp.arange(p * p)
  out = 0.0
  for w, off in (((1 - fy) * (1 - fx), 0), (fy * (1 - fx), p), ((1 - fy) * fx, 1), (fy * fx, p + 1)):
    out = out + jnp.where(cells == (base + off)[..., None], w[..., None], 0.0)
  return out


def cap_pixels(mask, max_pixels: Optional[int], rng):
  """The official cap (refinement_cross_entropy_efficient.py:301-311): with n > max_pixels
  selected pixels, each is kept independently with probability max_pixels / n."""
  if max_pixels is None:
    return mask
  n = jnp.sum(mask)
  keep = jax.random.uniform(rng, mask.shape) < max_pixels / jnp.maximum(n, 1).astype(jnp.float32)
  return jnp.where(n > max_pixels, mask & keep, mask)


def buffer_size(num_pixels: int, max_pixels: Optional[int]) -> int:
  """Static number of pixel slots: every pixel, or the cap plus 8 standard deviations of the
  Bernoulli count (beyond that the surplus pixels are dropped; chance below 1e-15)."""
  if max_pixels is None:
    return num_pixels
  return min(num_pixels, max_pixels + 8 * math.isqrt(max_pixels) + 8)


@dataclasses.dataclass(frozen=True)
class RefinementCE:
  """RefinementCrossEntropyLossEfficient (refinement_cross_entropy_efficient.py:85-311).

  A pixel is supervised iff its residual r = GT - regressed flow (no gradient to the flow) lies in
  [-P/2 + 0.5 + window_margin, P/2 - 0.5 - window_margin) on both axes (float32 compare), it is
  covisible, its GT has no NaN and |u| + |v| < max_gt, and its row's dataset is in `datasets`.
  The target map is read at (P+1)^2 integer taps around the regressed target and blended
  bilinearly into the P x P window; score = <target window, source feature> / temperature +
  attention_bias; loss = multiplier * sum(CE) / (eps + number of pixels).
  """
  multiplier: float = 10.0
  # Datasets whose rows train the refiner (`suitable_for_refinement` in the official dataset
  # classes: blendedmvs.py:105, flyingthings3d.py:113, hypersim.py:144; every other is False).
  # None: every row.
  datasets: Optional[Tuple[str, ...]] = ("blendedmvs", "flyingthings", "hypersim")
  # At most this many pixels per loss evaluation, drawn as the official cap (cap_pixels; the
  # official evaluates per GPU). None: no cap.
  max_pixels: Optional[int] = 400_000
  # Quirk (efficient.py:209-211): the window bounds are shrunk by this margin; 0 gives the
  # eval loss's [0.5, P - 0.5) on r + P/2.
  window_margin: float = 1e-4
  # Quirk (efficient.py:41): "truncate" takes the taps with `.long()` (towards zero: a tap at a
  # position in (-1, 0) reads row/column 0 instead of the zero padding); "floor" rounds down.
  taps: str = "truncate"
  # Quirk (efficient.py:46, 64): the gathered target features are cast to this dtype before the
  # bilinear blend (their gradients pass through the cast; `_bf16_window_blend`); "float32"
  # keeps them exact.
  gather_dtype: str = "bfloat16"
  # Quirk (efficient.py:292): the mean divides by count + eps; None divides by max(count, 1).
  eps: Optional[float] = 1e-4
  max_gt: float = loss_common.MAX_GT
  temperature: Optional[float] = None   # None: the model's (Recipe.temperature)

  def __post_init__(self):
    loss_common.check_choice("taps", self.taps, ("truncate", "floor"))
    loss_common.check_choice("gather_dtype", self.gather_dtype, tuple(_DTYPES))

  def __call__(self, outputs, batch, shared, ctx):
    f0 = outputs["feature_map_0"].astype(jnp.float32)
    f1 = outputs["feature_map_1"].astype(jnp.float32)
    bias = outputs["attention_bias"].astype(jnp.float32)
    p = int(math.sqrt(bias.shape[0] + 1e-6))
    temperature = self.temperature if self.temperature is not None else ctx["temperature"]
    if temperature is None:
      raise ValueError("refinement_ce: no temperature (set it on the term or the recipe)")
    gt, regression = shared["gt"], shared["pred"]
    ref_mask = batch["covisibility"].astype(bool) & ~loss_common.invalid_gt_mask(gt, self.max_gt)
    gt = jnp.where(jnp.isnan(gt), 0.0, gt)
    regression = jax.lax.stop_gradient(regression)
    r = gt - regression
    lo = np.float32(-p / 2 + 0.5 + self.window_margin)
    hi = np.float32(p / 2 - 0.5 - self.window_margin)
    ok = jnp.all(r >= lo, -1) & jnp.all(r < hi, -1) & ref_mask
    rows = ctx.get("suitable_rows")
    if rows is not None:
      ok = ok & rows[:, None, None]
    ok = cap_pixels(ok, self.max_pixels, ctx["rng"])

    b, h, w = ok.shape
    k = buffer_size(b * h * w, self.max_pixels)
    count = jnp.minimum(jnp.sum(ok), k)
    (flat,) = jnp.nonzero(ok.reshape(-1), size=k, fill_value=0)
    sel = jnp.arange(k) < count
    bi, yi, xi = flat // (h * w), (flat // w) % h, flat % w

    src = f0[bi, yi, xi]                                                    # [K, C]
    xs, ys = loss_common.pixel_grid(h, w)
    target = (regression + jnp.stack(jnp.broadcast_arrays(xs, ys), -1)) + 0.5
    # Unused slots (beyond `count`) read pixel 0; keep them finite so no NaN reaches a gradient.
    t = jnp.where(sel[:, None], target[bi, yi, xi], 0.5)                   # [K, 2]
    window = self._window_features(f1, bi, t, p)                            # [K, P, P, C]
    scores = jnp.einsum("kac,kc->ka", window.reshape(k, p * p, -1), src,
                        precision=jax.lax.Precision.HIGHEST) / temperature + bias
    logp = jax.nn.log_softmax(scores, axis=-1)

    rk = jnp.where(sel[:, None], r[bi, yi, xi], 0.0) + p / 2                # [K, 2] in the window
    start = (rk - 0.5).astype(jnp.int32)                                   # >= 0 where selected
    frac = rk - (start.astype(jnp.float32) + 0.5)
    weights = _window_weights(start, frac, p)
    ce = -jnp.sum(weights * logp, axis=-1)
    n = count.astype(jnp.float32)
    value = jnp.sum(jnp.where(sel, ce, 0.0)) / (n + self.eps if self.eps is not None
                                                 else jnp.maximum(n, 1.0))
    logs = {"refinement_cross_entropy@non_occluded_mask": value,
            "ratio_in_refinement_range": n / (1e-4 + jnp.sum(ref_mask.astype(jnp.float32)))}
    return self.multiplier * value, logs, dict(shared, gt=gt)

  def _window_features(self, f1, bi, t, p):
    """The official obtain_neighboirhood_features_batched (efficient.py:13-82) at positions t
    (pixel index + flow + 0.5) of the rows bi: [K, P, P, C] float32."""
    _, h, w, _ = f1.shape
    offsets = jnp.arange(p + 1, dtype=jnp.float32) - (p // 2) - 0.5
    pos_x = offsets[None, None, :] + t[:, None, None, 0]                   # [K, 1, P+1]
    pos_y = offsets[None, :, None] + t[:, None, None, 1]                   # [K, P+1, 1]
    rnd = (lambda v: v.astype(jnp.int32)) if self.taps == "truncate" else \
        (lambda v: jnp.floor(v).astype(jnp.int32))
    qx, qy = jnp.broadcast_arrays(rnd(pos_x), rnd(pos_y))                  # [K, P+1, P+1]
    valid = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
    taps = f1[bi[:, None, None], jnp.clip(qy, 0, h - 1), jnp.clip(qx, 0, w - 1)]
    taps = jnp.where(valid[..., None], taps, 0.0)
    frac = (t - 0.5) - jnp.floor(t - 0.5)                                  # [K, 2]
    rx, ry = frac[:, 0, None, None, None], frac[:, 1, None, None, None]
    if self.gather_dtype == "bfloat16":
      return _bf16_window_blend(taps, rx, ry)
    return _blend(taps, rx, ry)


def _blend(taps, rx, ry):
  """The official bilinear blend of the (P+1)^2 taps into the P x P window (efficient.py:74-80):
  float32 weights times the taps, summed in the official order."""
  rx1, ry1 = 1 - rx, 1 - ry
  return (rx1 * ry1 * taps[:, :-1, :-1] + rx1 * ry * taps[:, 1:, :-1]
          + rx * ry1 * taps[:, :-1, 1:] + rx * ry * taps[:, 1:, 1:])


def _round_bf16(x):
  """float32 rounded to bfloat16's precision, kept float32: an explicit rounding that XLA may
  not drop (a bfloat16 round trip may be elided, `xla_allow_excess_precision`)."""
  return jax.lax.reduce_precision(x, exponent_bits=8, mantissa_bits=7)


@jax.custom_vjp
def _bf16_window_blend(taps, rx, ry):
  """`_blend` of the taps cast to bfloat16 (the official `features_output`, a bfloat16 tensor,
  efficient.py:46, 64), with the official gradient: torch's autograd gives the bfloat16 taps the
  four terms' gradients (each float32 product rounded to bfloat16) summed in bfloat16 in the
  reverse order of their use, the [1:, 1:] slice's first, then [:-1, 1:], [1:, :-1], [:-1, :-1],
  rounding after every sum. Written out here because XLA keeps a fused sum of bfloat16 terms in
  float32 (the jitted step then missed the official gradient by up to 3.1e-3 of its largest
  value on the fixtures' cases, 4.8e-5 op by op). No other order is the official one: summed in
  use order, or without the roundings, the gradient misses by 1.7e-3 to 6.9e-3 of its max
  (tests/test_official_losses.py, `test_refinement_gradient_in_the_jitted_step`).

  What stays is rounding ties: of c0's 342k rounded contributions, 11 lie within one float32
  ulp of a bfloat16 tie, so the last bits of the float32 gradient above (the log-softmax and
  matmul backward, summed in another order than torch's) decide them; one that rounds the other
  way moves the gradient by one bfloat16 ulp of that contribution (up to 2^-8 of the max: c0
  measures 4.8e-5 op by op, 7.6e-4 jitted)."""
  return _blend(_round_bf16(taps), rx, ry)


def _bf16_window_blend_fwd(taps, rx, ry):
  return _bf16_window_blend(taps, rx, ry), (rx, ry)


def _bf16_window_blend_bwd(res, g):
  rx, ry = res
  rx1, ry1 = 1 - rx, 1 - ry
  # (weight, (row, column) offset of its slice of the (P+1)^2 taps), in torch's backward order.
  terms = ((rx * ry, (1, 1)), (rx * ry1, (0, 1)), (rx1 * ry, (1, 0)), (rx1 * ry1, (0, 0)))
  acc = None
  for w, (dy, dx) in terms:
    gi = jnp.pad(_round_bf16(g * w), ((0, 0), (dy, 1 - dy), (dx, 1 - dx), (0, 0)))
    acc = gi if acc is None else _round_bf16(acc + gi)
  return acc, None, None


_bf16_window_blend.defvjp(_bf16_window_blend_fwd, _bf16_window_blend_bwd)


@dataclasses.dataclass(frozen=True)
class RefinementCEEval:
  """RefinementCrossEntropyLoss (refinement_cross_entropy.py:79-185), the refine recipes' test
  loss, on the model's log-softmax windows [B, H, W, P, P]: the target weights stay
  differentiable w.r.t. the regressed flow; window [0.5, P - 0.5) on GT - flow + P/2, computed
  as (GT + pixel) - (flow + pixel) as the official code does."""
  multiplier: float = 10.0
  max_gt: float = loss_common.MAX_GT
  eps: Optional[float] = 1e-4

  def __call__(self, outputs, batch, shared, ctx):
    logp = outputs["log_softmax"].astype(jnp.float32)
    p = logp.shape[-1]
    gt, regression = shared["gt"], shared["pred"]
    covis = batch["covisibility"].astype(bool)
    ref_mask = covis & ~loss_common.invalid_gt_mask(gt, self.max_gt)
    gt = jnp.where(jnp.isnan(gt), 0.0, gt)
    h, w = gt.shape[1:3]
    xs, ys = loss_common.pixel_grid(h, w)
    grid = jnp.stack(jnp.broadcast_arrays(xs, ys), -1)
    local = (gt + grid) - (regression + grid) + p / 2                     # [B, H, W, (x, y)]
    inside = jnp.all(local >= 0.5, -1) & jnp.all(local < p - 0.5, -1)
    start = (local - 0.5).astype(jnp.int32)
    frac = local - (start.astype(jnp.float32) + 0.5)
    weights = _window_weights(start, frac, p)
    mask = inside & ref_mask
    ce = -jnp.sum(weights * logp.reshape(logp.shape[:3] + (p * p,)), axis=-1)
    value = loss_common.masked_mean(jnp.where(mask, ce, 0.0), mask, self.eps)
    n = jnp.sum(mask.astype(jnp.float32))
    logs = {"refinement_cross_entropy@non_occluded_mask": value,
            "ratio_in_refinement_range": n / (1e-4 + jnp.sum(covis.astype(jnp.float32)))}
    return self.multiplier * value, logs, dict(shared, gt=gt)
