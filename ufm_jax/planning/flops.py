"""FLOPs of a train step: counted on the step's jaxpr, and derived from the model's dimensions.

`jaxpr_flops` walks a traced program and adds up its matrix products (`dot_general`) and
convolutions, 2 FLOPs per multiply-add: the model FLOPs that MFU divides by the chips' peak
(elementwise work, softmax, norms and the optimizer's update are not counted, as in the usual
MFU convention). Every loop body counts as often as it runs: a `scan` (the scanned blocks, the
gradient-accumulation loop, fori_loops with static bounds) by its length, nested loops by the
product. XLA's own cost analysis counts a loop body once, which made the step's count shrink with
`grad_accum` and with scanned blocks. A `cond` counts the branch that runs: for the model's
platform-dependent code (`jax.lax.platform_dependent`: the CPU attention loop, CPU convolutions)
the branch of the platform the step is planned for; otherwise the costliest branch. A `while`
loop whose trip count the jaxpr does not say is counted once and reported (`unknown_loops`).

`analytic_train_flops` counts the same products from the model config alone (encoder, fusion
transformer, DPT heads, refiner, the refinement loss), forward plus backward: a product with
trainable weights costs its forward again for the weight gradient, and again for the gradient of
its input where that input depends on trainable parameters. It is the independent check that
the jaxpr count counts what the step computes (tests/test_flops.py, docs/scale.md).
"""

from __future__ import annotations

import dataclasses
import math

import jax

_CPU = "cpu"


@dataclasses.dataclass
class Count:
  flops: float = 0.0
  unknown_loops: int = 0   # while loops counted once: their trip count is not in the jaxpr

  def __iadd__(self, other: "Count"):
    self.flops += other.flops
    self.unknown_loops += other.unknown_loops
    return self

  def scaled(self, n: float) -> "Count":
    return Count(self.flops * n, self.unknown_loops)


def _shape(v):
  return tuple(getattr(v.aval, "shape", ()))


def _dot_flops(eqn) -> float:
  (contract, _), _ = eqn.params["dimension_numbers"]   # ((lhs, rhs) contracting, batch)
  lhs = _shape(eqn.invars[0])
  k = math.prod(lhs[d] for d in contract)
  return 2.0 * math.prod(_shape(eqn.outvars[0])) * k


def _conv_flops(eqn) -> float:
  """2 x output elements x the kernel's taps x its input features. An input dilated by the
  transpose of a strided convolution (its input gradient) is mostly inserted zeros: only
  1 / prod(lhs_dilation) of the taps meet data, as in the forward convolution."""
  dn = eqn.params["dimension_numbers"]
  rhs = _shape(eqn.invars[1])
  rhs_spec = dn.rhs_spec           # (out feature dim, in feature dim, spatial dims...)
  taps = math.prod(rhs[d] for d in rhs_spec[2:]) * rhs[rhs_spec[1]]
  dilation = math.prod(eqn.params.get("lhs_dilation") or (1,))
  return 2.0 * math.prod(_shape(eqn.outvars[0])) * taps / dilation


def _sub_jaxprs(value):
  values = value if isinstance(value, (tuple, list)) else (value,)
  for v in values:
    if isinstance(v, jax.extend.core.ClosedJaxpr):
      yield v.jaxpr
    elif isinstance(v, jax.extend.core.Jaxpr):
      yield v


def _cond_branch(eqn, platform: str):
  """The index of the branch that runs on `platform` for a platform-dependent cond, else None."""
  platforms = eqn.params.get("branches_platforms")
  if not platforms:
    return None
  default = None
  for i, names in enumerate(platforms):
    if names is None:
      default = i
    elif platform in names or (platform == "gpu" and {"cuda", "rocm"} & set(names)):
      return i
  return default


def jaxpr_flops(jaxpr, platform: str = "tpu") -> Count:
  """Matrix-product and convolution FLOPs of `jaxpr` (a Jaxpr or ClosedJaxpr), every loop body
  times its trip count; `platform` picks the branch of platform-dependent code."""
  if isinstance(jaxpr, jax.extend.core.ClosedJaxpr):
    jaxpr = jaxpr.jaxpr
  total = Count()
  for eqn in jaxpr.eqns:
    name = eqn.primitive.name
    if name == "dot_general":
      total.flops += _dot_flops(eqn)
    elif name == "conv_general_dilated":
      total.flops += _conv_flops(eqn)
    elif name == "scan":
      total += jaxpr_flops(eqn.params["jaxpr"], platform).scaled(eqn.params["length"])
    elif name == "while":
      body = jaxpr_flops(eqn.params["body_jaxpr"], platform)
      total += body
      total.unknown_loops += 1
    elif name == "cond":
      branches = [jaxpr_flops(b, platform) for b in eqn.params["branches"]]
      pick = _cond_branch(eqn, platform)
      total += branches[pick] if pick is not None else max(branches, key=lambda c: c.flops)
    else:
      # Calls (jit, remat, custom_jvp/vjp, closed_call, shard_map): their jaxprs run once.
      for value in eqn.params.values():
        for sub in _sub_jaxprs(value):
          total += jaxpr_flops(sub, platform)
  return total


def step_flops(ts, batch: int, image_shape, platform: str = "tpu") -> Count:
  """FLOPs of one call of `ts.train_step` (a trainer.TrainSetup) at global `batch` rows of
  `image_shape`, counted on its jaxpr (traced, never compiled): the program as configured, remat's
  recomputation included."""
  traced = ts.train_step.trace(ts.sharded_abstract_state(), ts.abstract_batch(batch, image_shape))
  return jaxpr_flops(live(traced.jaxpr), platform)


def live(closed):
  """The jaxpr without the equations no output depends on, as XLA drops them when it compiles
  (a model output that no loss term reads, e.g. the refined flow in refinement training)."""
  from jax._src.interpreters import partial_eval as pe  # pylint: disable=g-import-not-at-top
  jaxpr = closed.jaxpr if isinstance(closed, jax.extend.core.ClosedJaxpr) else closed
  return pe.dce_jaxpr(jaxpr, [True] * len(jaxpr.outvars))[0]


def model_flops(config, image_shape, batch: int, platform: str = "tpu") -> Count:
  """Model FLOPs of one train step of `config` at global `batch`: its jaxpr with remat off (MFU
  counts what the model computes, not what remat computes again), traced for one device (the
  count does not depend on the mesh: the jaxpr is the global program)."""
  import copy

  from ufm_jax.training import sharding, trainer
  config = copy.deepcopy(config)
  if config.model.get("remat"):
    config.model.remat = False
  mesh = sharding.make_mesh("data:1,fsdp:1", jax.devices()[:1])
  from ufm_jax.training import teacher as teacher_lib
  ts = trainer.setup(config, mesh, image_shape, total_steps=1000,
                     teacher=teacher_lib.from_config(config, mesh))
  return step_flops(ts, batch, image_shape, platform)


# ----------------------------------------------------------------------------- analytic count


@dataclasses.dataclass
class _Product:
  """A matrix product of the model: its multiply-adds per step, whether it has trainable
  weights, and whether its input depends on trainable parameters (then its input gradient runs).
  A product of two activations (attention) has no weights and both operands' gradients."""
  part: str
  macs: float
  weights: bool
  input_grad: bool
  two_operands: bool = False

  def train_flops(self) -> float:
    f = 2.0 * self.macs
    backward = 0.0
    if self.weights:
      backward += f
    if self.input_grad:
      backward += f * (2 if self.two_operands else 1)
    return f + backward


def _transformer(part, tokens, seqs, dim, depth, mlp_ratio, trainable, input_grad):
  """A stack of pre-norm blocks on `seqs` sequences of `tokens`: qkv, logits, weights x values,
  projection, MLP. Returns the products."""
  hidden = int(dim * mlp_ratio)
  n = seqs * tokens
  out = []
  for i in range(depth):
    g = input_grad or (trainable and i > 0)
    out += [_Product(part, n * dim * 3 * dim, trainable, g),
            _Product(part, seqs * tokens * tokens * dim, False, trainable or input_grad, True),
            _Product(part, seqs * tokens * tokens * dim, False, trainable or input_grad, True),
            _Product(part, n * dim * dim, trainable, trainable or input_grad),
            _Product(part, n * dim * hidden, trainable, trainable or input_grad),
            _Product(part, n * hidden * dim, trainable, trainable or input_grad)]
  return out


def _conv(part, pixels, cin, cout, k, trainable, input_grad):
  return _Product(part, pixels * cin * cout * k * k, trainable, input_grad)


def _dpt(part, cfg, h, w, hw_out, rows, trainable, input_grad):
  """DPTFeature + DPTRegressionProcessor on `rows` maps of h x w patches (models/dpt.py)."""
  ld, fd = cfg.layer_dims, cfg.feature_dim
  cin = cfg.input_feature_dims
  n = rows * h * w
  g = trainable or input_grad
  h3, w3 = (h - 1) // 2 + 1, (w - 1) // 2 + 1            # 3x3 stride 2, pad 1
  n3 = rows * h3 * w3
  out = [_conv(part, n, cin[0], ld[0], 1, trainable, input_grad),
         _Product(part, n * 16 * ld[0] * ld[0], trainable, g),          # ConvT 4x4 / 4
         _conv(part, n, cin[1], ld[1], 1, trainable, input_grad),
         _Product(part, n * 4 * ld[1] * ld[1], trainable, g),           # ConvT 2x2 / 2
         _conv(part, n, cin[2], ld[2], 1, trainable, input_grad),
         _conv(part, n, cin[3], ld[3], 1, trainable, input_grad),
         _conv(part, n3, ld[3], ld[3], 3, trainable, g)]
  # layer{k}_rn (3x3 to feature_dim) at 4x, 2x, 1x, 1/2 the patch grid.
  grids = [(4 * h, 4 * w), (2 * h, 2 * w), (h, w), (h3, w3)]
  out += [_conv(part, rows * a * b, ld[k], fd, 3, trainable, g) for k, (a, b) in enumerate(grids)]
  # refinenet4 (on the 1/2 grid, no skip), 3, 2, 1: residual units of two 3x3 convs, then x2
  # bilinear and a 1x1 conv at the doubled size; path4 is cropped to the patch grid.
  for k, (a, b) in zip((4, 3, 2, 1), [(h3, w3), (h, w), (2 * h, 2 * w), (4 * h, 4 * w)]):
    units = 1 if k == 4 else 2
    out += [_conv(part, rows * a * b, fd, fd, 3, trainable, g) for _ in range(2 * units)]
    out.append(_conv(part, rows * 4 * a * b, fd, fd, 1, trainable, g))
  h1, h2 = cfg.hidden_dims or (fd // 2,) * 2
  out += [_conv(part, rows * 64 * h * w, fd, h1, 3, trainable, g),
          _conv(part, rows * hw_out[0] * hw_out[1], h1, h2, 3, trainable, g),
          _conv(part, rows * hw_out[0] * hw_out[1], h2, cfg.output_dim, 1, trainable, g)]
  return out


def _unet(part, features, out_channels, images, hh, ww, trainable):
  """The refiner's U-Net (models/refine.py UNet) on `images` of hh x ww."""
  out, sizes, c = [], [], 3
  a, b = hh, ww
  for i, f in enumerate(features):
    out += [_conv(part, images * a * b, c, f, 3, trainable, trainable and i > 0),
            _conv(part, images * a * b, f, f, 3, trainable, trainable)]
    sizes.append((a, b))
    c, a, b = f, a // 2, b // 2
  bottleneck = 2 * features[-1]
  out += [_conv(part, images * a * b, c, bottleneck, 3, trainable, trainable),
          _conv(part, images * a * b, bottleneck, bottleneck, 3, trainable, trainable)]
  c = bottleneck
  for f, (sa, sb) in zip(reversed(features), reversed(sizes)):
    out.append(_Product(part, images * a * b * 4 * c * f, trainable, trainable))   # up 2x2 / 2
    out += [_conv(part, images * sa * sb, 2 * f, f, 3, trainable, trainable),
            _conv(part, images * sa * sb, f, f, 3, trainable, trainable)]
    c, a, b = f, sa, sb
  out.append(_conv(part, images * hh * ww, c, out_channels, 1, trainable, trainable))
  return out


PARTS = ("encoder", "info_sharing", "output_head", "uncertainty_head", "refiner")


def analytic_products(model_cfg, image_shape, rows: int, symmetrized: bool = True,
                      trainable=PARTS, covisibility_read: bool = True,
                      refine_loss_pixels: int = 0) -> list:
  """The matrix products of one train step (one microbatch) of the UFM (or UFMRefine)
  `model_cfg` on `rows` batch rows of `image_shape`, by part. `trainable`: the parts whose weights
  train (the refine recipe freezes the base). `covisibility_read`: whether a loss term reads the
  covisibility head (else, frozen, XLA drops it). `refine_loss_pixels`: pixels the refinement
  cross-entropy scores (refine_training.RefinementCE)."""
  hh, ww = image_shape
  enc, fus = model_cfg.encoder, model_cfg.info_sharing
  p = enc.patch_size
  h, w = hh // p, ww // p
  n = h * w
  images = rows if symmetrized else 2 * rows
  out = []
  t_enc = "encoder" in trainable
  # Encoder: patch embedding, the position table resized to the grid (a constant matrix, once per
  # step), the blocks up to the last returned one.
  out.append(_conv("encoder", images * n, 3, enc.embed_dim, p, t_enc, False))
  out.append(_Product("encoder", n * (1 + enc.pos_grid ** 2) * enc.embed_dim, t_enc, False))
  tokens = 1 + enc.num_register_tokens + n
  depth = max(enc.take_indices()) + 1
  # The blocks' input depends on the patch embedding and the position table: trained with them.
  out += _transformer("encoder", tokens, images, enc.embed_dim, depth, enc.mlp_ratio, t_enc,
                      t_enc)
  # Fusion transformer: both views' tokens in one sequence per row.
  t_fus = "info_sharing" in trainable
  if fus.input_embed_dim != fus.dim:
    out.append(_Product("info_sharing", rows * 2 * n * fus.input_embed_dim * fus.dim, t_fus,
                        t_enc))
  out += _transformer("info_sharing", 2 * n, rows, fus.dim, fus.depth, fus.mlp_ratio, t_fus,
                      t_enc or (t_fus and fus.input_embed_dim != fus.dim))
  trunk = t_enc or t_fus
  out += _dpt("output_head", model_cfg.flow_head, h, w, image_shape, rows,
              "output_head" in trainable, trunk)
  t_cov = "uncertainty_head" in trainable
  if model_cfg.covisibility_head is not None and (covisibility_read or t_cov):
    out += _dpt("uncertainty_head", model_cfg.covisibility_head, h, w, image_shape, rows,
                "uncertainty_head" in trainable, trunk and not model_cfg.detach_uncertainty_head)
  if hasattr(model_cfg, "unet_features"):
    out += _refiner(model_cfg, hh, ww, h, w, rows, images, trunk, "refiner" in trainable,
                    refine_loss_pixels)
  return out


def _refiner(cfg, hh, ww, h, w, rows, images, trunk, trainable, loss_pixels):
  """U-Net, classification head, combination and the local window attention (models/refine.py)."""
  out = []
  c = cfg.refine_feature_dim
  if cfg.use_unet_feature:
    # With BatchNorm in training the U-Net runs once per view (each image of a symmetrized batch
    # twice), as the official forward does; otherwise on each image once.
    unet_images = 2 * rows if cfg.use_unet_batchnorm else images
    out += _unet("refiner", cfg.unet_features, c, unet_images, hh, ww, trainable)
  tokens_dim = cfg.encoder.embed_dim + cfg.info_sharing.dim
  hidden = int(tokens_dim * cfg.refine_mlp_ratio)
  views = 2 * rows * h * w
  p = cfg.encoder.patch_size
  out += [_Product("refiner", views * tokens_dim * hidden, trainable, trunk),
          _Product("refiner", views * hidden * tokens_dim, trainable, trainable or trunk),
          _Product("refiner", views * tokens_dim * c * p * p, trainable, trainable or trunk)]
  if cfg.use_unet_feature and cfg.feature_combine_method == "modulate":
    out.append(_conv("refiner", 2 * rows * hh * ww, c, c, 1, trainable, trainable or trunk))
  elif cfg.use_unet_feature:    # conv1 on [features, U-Net] (2c -> 2c), conv2 (2c -> c)
    out += [_conv("refiner", 2 * rows * hh * ww, 2 * c, 2 * c, 1, trainable, trainable or trunk),
            _conv("refiner", 2 * rows * hh * ww, 2 * c, c, 1, trainable, trainable or trunk)]
  # The window search (refine._refine_rows) gives the refined flow, which no training loss reads
  # (the regression terms take flow_before_refinement): XLA drops it from the train step. The
  # refinement cross-entropy scores its r x r window of features at each selected pixel instead.
  r = cfg.refinement_range
  if loss_pixels:
    out.append(_Product("refiner", loss_pixels * r * r * c, False, trainable or trunk, True))
  return out


def analytic_train_flops(model_cfg, image_shape, rows: int, **kw) -> dict:
  """{part: forward-plus-backward FLOPs of one microbatch} and "total" (`analytic_products`)."""
  out: dict = {}
  for prod in analytic_products(model_cfg, image_shape, rows, **kw):
    out[prod.part] = out.get(prod.part, 0.0) + prod.train_flops()
  out["total"] = sum(out.values())
  return out


def trainable_parts(labels) -> set:
  """The analytic parts with a parameter that trains, from the optimizer's labels
  (optim.param_labels: "frozen" or a group name per leaf)."""
  from flax import traverse_util

  from ufm_jax.training import optim
  parts = set()
  for path, label in traverse_util.flatten_dict(labels, sep="/").items():
    if label == optim.FROZEN:
      continue
    top = path.split("/")[0]
    if top in ("encoder", "info_sharing"):
      parts.add(top)
    elif top.startswith("head1_"):
      parts.add("output_head")
    elif top.startswith("uncertainty_head_"):
      parts.add("uncertainty_head")
    else:   # unet_feature, classification_head, conv1, conv2, classification_bias
      parts.add("refiner")
  return parts


def analytic_step_flops(config, ts, image_shape, batch: int) -> dict:
  """`analytic_train_flops` of the train step `ts` (trainer.setup of `config`) at global `batch`:
  config.grad_accum microbatches, the trainable parts from its optimizer, the loss terms of
  config.loss. By part, and "total"."""
  from ufm_jax.training import refine_training
  k = int(config.get("grad_accum", 1))
  rows = batch // k
  terms = {name: dict(config.loss[name]) for name in config.loss.terms}
  kinds = {t.get("type") for t in terms.values()}
  pixels = 0
  for t in terms.values():
    if t.get("type") == "refinement_ce":
      pixels = refine_training.buffer_size(rows * image_shape[0] * image_shape[1],
                                           t.get("max_pixels"))
  micro = analytic_train_flops(
      ts.model.config, image_shape, rows,
      symmetrized=bool(dict(config.apply_kwargs).get("symmetrized")),
      trainable=trainable_parts(ts.labels), covisibility_read="bce" in kinds,
      refine_loss_pixels=pixels)
  return {part: k * v for part, v in micro.items()}
