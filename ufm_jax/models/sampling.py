"""Sampling a feature map at sub-pixel points, and the per-pixel cues an uncertainty head can
read beside the trunk's features (`UFMConfig.uncertainty_cues`)."""

import jax
import jax.numpy as jnp


def sample(values, xy, interpolation: str = "bilinear"):
  """values [B, h, w, C] at the points xy [B, H, W, 2] (x, y; pixel centres at integers), the
  border pixels extended outwards -> [B, H, W, C]."""
  b, h, w, c = values.shape
  flat = values.reshape(b, h * w, c)

  def take(ix, iy):
    ix = jnp.clip(ix, 0, w - 1)
    iy = jnp.clip(iy, 0, h - 1)
    idx = (iy * w + ix).reshape(b, -1, 1)
    return jnp.take_along_axis(flat, idx, axis=1).reshape(xy.shape[:3] + (c,))

  x, y = xy[..., 0], xy[..., 1]
  if interpolation == "nearest":
    return take(jnp.floor(x + 0.5).astype(jnp.int32), jnp.floor(y + 0.5).astype(jnp.int32))
  x0, y0 = jnp.floor(x), jnp.floor(y)
  fx, fy = (x - x0)[..., None], (y - y0)[..., None]
  x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
  top = take(x0, y0) * (1 - fx) + take(x0 + 1, y0) * fx
  bottom = take(x0, y0 + 1) * (1 - fx) + take(x0 + 1, y0 + 1) * fx
  return top * (1 - fy) + bottom * fy


# Channels of each cue (UFMConfig.uncertainty_cues), in the order they are concatenated.
CUE_CHANNELS = {"warp_residual": 4, "flow_edges": 1}


def uncertainty_cues(names, source, target, flow):
  """[B, H, W, sum of CUE_CHANNELS] per-pixel evidence of where the flow is wrong, from the
  normalised images source, target [B, H, W, 3] and the predicted flow [B, H, W, 2] (px), with
  no gradient into the flow (the head that reads them must not train the flow):

    warp_residual  |source(p) - target(p + flow(p))| per colour channel (bilinear, border
                   extended), then 1 where p + flow(p) leaves the target (there the residual
                   compares with a border pixel and says nothing);
    flow_edges     log(1 + |grad flow|) with |grad flow|^2 the sum of the squared central
                   differences of both components along x and y (px per px): the motion
                   boundaries, which a coarse flow head blurs.
  """
  flow = jax.lax.stop_gradient(flow.astype(jnp.float32))
  _, h, w, _ = flow.shape
  out = []
  for name in names:
    if name == "warp_residual":
      ys, xs = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32),
                            indexing="ij")
      p1 = jnp.stack([xs, ys], -1) + flow
      warped = sample(target.astype(jnp.float32), p1)
      outside = ((p1[..., 0] < -0.5) | (p1[..., 0] > w - 0.5) |
                 (p1[..., 1] < -0.5) | (p1[..., 1] > h - 0.5))
      out += [jnp.abs(source.astype(jnp.float32) - warped),
              outside[..., None].astype(jnp.float32)]
    elif name == "flow_edges":
      pad = jnp.pad(flow, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
      dx = (pad[:, 1:-1, 2:] - pad[:, 1:-1, :-2]) / 2
      dy = (pad[:, 2:, 1:-1] - pad[:, :-2, 1:-1]) / 2
      out.append(jnp.log1p(jnp.sqrt((dx ** 2 + dy ** 2).sum(-1, keepdims=True))))
    else:
      raise ValueError(f"uncertainty cue {name!r}; expected one of {sorted(CUE_CHANNELS)}")
  return jnp.concatenate(out, -1)
