"""Closed-form parameter counts of the official modules (torch Linear / Conv2d / LayerNorm sizes),
written from the module definitions (timm's ViT block, DINOv2, UniCeption's fusion transformer,
the DPT head), so that a test compares a model's parameters with a count that did not come from
the model's own code."""


def linear(i, o, bias=True):
  return i * o + (o if bias else 0)


def conv(i, o, k, bias=True):
  return i * o * k * k + (o if bias else 0)


def mlp(d, hidden):
  return linear(d, hidden) + linear(hidden, d)


def vit_block(d, hidden, layerscale=True, swiglu=False):
  ffn = linear(d, 2 * hidden) + linear(hidden, d) if swiglu else mlp(d, hidden)
  return 4 * d + linear(d, 3 * d) + linear(d, d) + ffn + (2 * d if layerscale else 0)


def dinov2_count(d, depth, swiglu_hidden=None, patch=14, grid=37, hidden=None):
  """Patch embedding, class token, position table (1 + grid^2 rows), `depth` blocks with layer
  scale, the final norm. `hidden`: the MLP width (default 4 d)."""
  hidden = swiglu_hidden or hidden or 4 * d
  return (conv(3, d, patch) + d + (1 + grid * grid) * d
          + depth * vit_block(d, hidden, swiglu=swiglu_hidden is not None) + 2 * d)


def fusion_count(input_dim, d, depth, hidden):
  """UniCeption's global-attention fusion: the input projection where the widths differ,
  `depth` blocks without layer scale, the final norm."""
  return (linear(input_dim, d) if input_dim != d else 0) + depth * vit_block(
      d, hidden, layerscale=False) + 2 * d


def dpt_count(in_dims, layer_dims, f, out):
  n = conv(in_dims[0], layer_dims[0], 1) + conv(layer_dims[0], layer_dims[0], 4)
  n += conv(in_dims[1], layer_dims[1], 1) + conv(layer_dims[1], layer_dims[1], 2)
  n += conv(in_dims[2], layer_dims[2], 1)
  n += conv(in_dims[3], layer_dims[3], 1) + conv(layer_dims[3], layer_dims[3], 3)
  n += sum(conv(l, f, 3, bias=False) for l in layer_dims)  # layer{k}_rn
  rcu = 2 * conv(f, f, 3)
  n += 3 * (2 * rcu + conv(f, f, 1)) + (rcu + conv(f, f, 1))  # refinenet4 has one RCU
  return n + conv(f, f // 2, 3) + conv(f // 2, f // 2, 3) + conv(f // 2, out, 1)
