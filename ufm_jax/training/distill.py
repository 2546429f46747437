"""The teacher of a distillation run (configs/distill.py), run inside the jitted train step.

A student learns from a frozen teacher's predictions instead of labels. Each training row
carries the student's input (the official augmentation: the flow pathway's resize and shared
crop, then colour unless `input.augment.photometric` is off; ufm_jax.data.distill_rows) and the
same pair un-augmented at the teacher's resolution, with the two affine maps from teacher pixels
to crop pixels (one per view). In the step, before the student's forward, the teacher predicts
on the un-augmented pair and `warp_to_crop` carries its outputs into the student's crop; the loss
(ufm_jax.training.distill_loss) reads only those targets. No pre-pass, no label.

Where the teacher's parameters live: neither in the train state nor as constants of the
compiled step, but as an explicit argument of the jitted step (`BoundStep`), placed on the mesh
by the student's sharding rules (FSDP included) and bound once. In the state they would be
checkpointed with every step, restored and counted as the student's, and the student's
checkpoints would stop being ordinary UFM checkpoints (`ufm_jax.load`, `to-official`); as
constants closed over by jit they would be embedded in the program (a 428M-parameter UFM-Base
serialised into the HLO and into every compile) instead of staying device buffers sharded like
the student's. As an argument they are neither: no optimizer state, no gradient (the targets
leave the teacher through stop_gradient, so no backward pass runs through it), one transfer.

The teacher itself is loaded and placed by ufm_jax.training.teacher (`config.teacher`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from ufm_jax.data.distill_rows import TEACHER_KEYS
from ufm_jax.models.sampling import sample

INTERPOLATIONS = ("bilinear", "nearest")


@dataclasses.dataclass
class Teacher:
  """A loaded teacher, built for a mesh. `variables()` are host arrays ({"params"[,
  "batch_stats"]}, in the layout of `model`); `abstract` their sharded ShapeDtypeStructs."""
  model: Any
  abstract: Any
  shardings: Any
  resolution: tuple
  interpolation: str
  source: str
  _load: Callable[[], Any]
  _host: Any = None

  def variables(self):
    if self._host is None:
      self._host = self._load()
    return self._host

  def device_variables(self):
    """The variables on the mesh, sharded like the student's parameters."""
    import jax
    return jax.device_put(self.variables(), self.shardings)

  def describe(self) -> str:
    from ufm_jax.training import optim
    n = optim.count_params(self.abstract["params"])["total"]
    return (f"teacher {self.source}: {type(self.model).__name__}, {n:,} parameters, "
            f"{self.model.config.dtype}, sees {self.resolution[0]}x{self.resolution[1]}")


# ------------------------------------------------------------------------------------ the warp


def _apply(m, xy):
  """[B, 2, 3] affine on [B, H, W, 2] points."""
  import jax.numpy as jnp
  return jnp.einsum("bij,bhwj->bhwi", m[:, :, :2], xy) + m[:, None, None, :, 2]


def _inverse(m):
  """Inverse of a [B, 2, 3] affine."""
  import jax.numpy as jnp
  a, b = m[:, :, :2], m[:, :, 2]
  det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
  inv = jnp.stack([jnp.stack([a[:, 1, 1], -a[:, 0, 1]], -1),
                   jnp.stack([-a[:, 1, 0], a[:, 0, 0]], -1)], -2) / det[:, None, None]
  return jnp.concatenate([inv, -jnp.einsum("bij,bj->bi", inv, b)[..., None]], -1)


def warp_to_crop(outputs, to_crop0, to_crop1, crop_hw, interpolation: str = "bilinear"):
  """The teacher's outputs on the un-augmented pair -> targets at the student's crop pixels.

  outputs: {"flow" [B, h, w, 2], optional "covisibility" [B, h, w] (probability) and
  "flow_covariance" [B, h, w, 3] (var_x, var_y, cov_xy, px^2)} at teacher resolution.
  to_crop0 / to_crop1: [B, 2, 3] affines from teacher pixels of the row's source / target view
  to crop pixels. For crop pixel p: q = to_crop0^-1 p is where the teacher saw it, f the
  teacher's flow there, and the target is to_crop1(q + f) - p. Returns the batch keys of
  ufm_jax.training.distill_loss: teacher_flow, teacher_in_view (q inside the teacher's image), teacher_in_crop
  (the match inside [0, W) x [0, H) of the target crop, the pipeline's in-frame rule),
  teacher_covisibility (its probability at q, 0 out of the crop) and teacher_flow_covariance
  (A C A^T with A the target map's linear part) where the teacher has them.
  """
  import jax.numpy as jnp
  h, w = crop_hw
  b, th, tw = outputs["flow"].shape[:3]
  ys, xs = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32),
                        indexing="ij")
  p = jnp.broadcast_to(jnp.stack([xs, ys], -1), (b, h, w, 2))
  q = _apply(_inverse(to_crop0.astype(jnp.float32)), p)
  in_view = ((q[..., 0] >= -0.5) & (q[..., 0] <= tw - 0.5) &
             (q[..., 1] >= -0.5) & (q[..., 1] <= th - 0.5))
  f = sample(outputs["flow"].astype(jnp.float32), q, interpolation)
  p1 = _apply(to_crop1.astype(jnp.float32), q + f)
  in_crop = (p1[..., 0] >= 0) & (p1[..., 0] < w) & (p1[..., 1] >= 0) & (p1[..., 1] < h)
  out = {"teacher_flow": p1 - p, "teacher_in_view": in_view, "teacher_in_crop": in_crop}
  if "covisibility" in outputs:
    covis = sample(outputs["covisibility"].astype(jnp.float32)[..., None], q, interpolation)
    out["teacher_covisibility"] = jnp.where(in_crop, covis[..., 0], 0.0)
  if "flow_covariance" in outputs:
    c = sample(outputs["flow_covariance"].astype(jnp.float32), q, interpolation)
    sigma = jnp.stack([jnp.stack([c[..., 0], c[..., 2]], -1),
                       jnp.stack([c[..., 2], c[..., 1]], -1)], -2)
    a = to_crop1.astype(jnp.float32)[:, None, None, :, :2]
    s = a @ sigma @ jnp.swapaxes(a, -1, -2)
    out["teacher_flow_covariance"] = jnp.stack([s[..., 0, 0], s[..., 1, 1], s[..., 0, 1]], -1)
  return out


# ------------------------------------------------------------------------------- in the step


def make_targets_fn(teacher: Teacher, gather_params=None, symmetrized: bool = False):
  """targets(teacher_variables, batch) -> the batch with the teacher's targets added and the
  teacher's inputs removed: what the loss sees. Runs the teacher (train=False: BatchNorm with
  its running statistics) on the un-augmented pair and warps its outputs into the crop; the
  outputs leave through stop_gradient."""
  import jax

  model = teacher.model

  def targets(variables, batch):
    if gather_params is not None:
      variables = dict(variables, params=gather_params(variables["params"]))
    out = model.apply(variables, batch["teacher_image0"], batch["teacher_image1"],
                      symmetrized=symmetrized)
    out = jax.lax.stop_gradient({k: out[k] for k in ("flow", "covisibility", "flow_covariance")
                                 if k in out})
    warped = warp_to_crop(out, batch["teacher_to_crop0"], batch["teacher_to_crop1"],
                          batch["image0"].shape[1:3], teacher.interpolation)
    rest = {k: v for k, v in batch.items() if k not in TEACHER_KEYS}
    return {**rest, **warped}

  return targets


class BoundStep:
  """The jitted step(state, batch, teacher_variables) called and lowered as (state, batch):
  `lower` and `trace` take the teacher's sharded abstract variables (AOT compiles and FLOP counts
  need no weights); the
  first call puts the teacher's variables on the mesh (or `bind` gives them)."""

  def __init__(self, jitted, teacher: Teacher):
    self.jitted, self.teacher, self.bound = jitted, teacher, None

  def bind(self, variables=None):
    self.bound = self.teacher.device_variables() if variables is None else variables
    return self

  def __call__(self, state, batch):
    if self.bound is None:
      self.bind()
    return self.jitted(state, batch, self.bound)

  def lower(self, state, batch):
    return self.jitted.lower(state, batch, self.teacher.abstract)

  def trace(self, state, batch):
    return self.jitted.trace(state, batch, self.teacher.abstract)
