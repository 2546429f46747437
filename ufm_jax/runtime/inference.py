"""High-level inference: `predict(model, variables, source, target)`.

Reproduces the official `predict_correspondences_batched` (uniflowmatch/models/base.py with
utils/flow_resizing.py) step by step:
  1. uint8 -> ImageNet-normalised float32 (`(x / 255 - mean) / std`, float32 arithmetic);
  2. `F.interpolate(mode='bilinear', align_corners=False, antialias=True)` of the NORMALISED image
     to the inference resolution whose aspect ratios are closest to the pair's (`closest_aspect`);
  3. forward pass (the model renormalises from 0..255, so the resized image is de-normalised
     first; the round trip costs ~1e-7, far below the parity tolerances);
  4. unmap to the source resolution with the official region bookkeeping, including the float32
     truncation of the representation region (`int64(float32(H_inf / H) * H)`).

The resize and unmap run in numpy on the host (they are cheap and must match PyTorch's float32
arithmetic); the forward pass is jitted once per model and traced once per inference shape.

A model without a covisibility output (`UFMConfig.has_covisibility`: the refinement training
recipe's `ufm_refine_recipe`, or a one-head UniFlowMatch without a non_occluded_mask adaptor)
predicts flow only: its predictions have no "covisibility" key (a warning says so once). A model
with a flow covariance adaptor adds "flow_covariance" (and its inverse, "flow_covariance_inv"),
unmapped like covisibility and rescaled to the source's pixels as the official predict does
(`unmap_covariance`).
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np

from ufm_jax.data.resize import resize_bilinear, resize_bilinear_aa, resize_nearest

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
DEFAULT_INFERENCE_RESOLUTION = (420, 560)  # (H, W); the official default (560, 420) is (W, H)

_f32 = np.float32


# ----------------------------------------------------------------------------------------------
# Normalisation
# ----------------------------------------------------------------------------------------------
def normalize(image: np.ndarray) -> np.ndarray:
  """HWC (or BHWC) uint8 / float 0..255 -> ImageNet-normalised float32, as the official code."""
  x = np.asarray(image).astype(np.float32) / _f32(255.0)
  return (x - IMAGENET_MEAN) / IMAGENET_STD


def denormalize(image: np.ndarray) -> np.ndarray:
  """Inverse of `normalize` (float32 in 0..255 up to rounding), for models that normalise inside."""
  return (np.asarray(image, np.float32) * IMAGENET_STD + IMAGENET_MEAN) * _f32(255.0)


# ----------------------------------------------------------------------------------------------
# Region bookkeeping
# ----------------------------------------------------------------------------------------------
def representation_region(in_hw: tuple[int, int], out_hw: tuple[int, int]) -> np.ndarray:
  """[top, bottom, left, right] of a resized image, with the official float32 truncation.

  The official code multiplies the int64 region [0, H, 0, W] by a float32 tensor of the resize
  ratios and casts back to int64, so e.g. 131 -> 168 rows gives 167 (float32(168/131)*131 < 168).
  """
  (h, w), (oh, ow) = in_hw, out_hw
  mult = np.array([oh / h, oh / h, ow / w, ow / w], np.float32)
  return (mult * np.array([0, h, 0, w], np.float32)).astype(np.int64)


def select_resolution(resolutions: Sequence[tuple[int, int]], src_hw, tgt_hw) -> tuple[int, int]:
  """The official `closest_aspect` choice among (H, W) inference resolutions (first wins ties)."""
  def cost(r):
    a = r[0] / r[1]
    return abs(a - src_hw[0] / src_hw[1]) + abs(a - tgt_hw[0] / tgt_hw[1])
  return tuple(min(resolutions, key=cost))


def unmap_flow(flow: np.ndarray, region0: np.ndarray, src_hw, tgt_hw) -> np.ndarray:
  """Inference-resolution flow [h, w, 2] -> source-resolution flow [H, W, 2] (official unmap).

  ROI = the source representation region; source pixel centres of the ROI (i + 0.5) are resized
  bilinearly to the source size, the flow with legacy nearest; target = source + flow; source
  coordinates are scaled by source_size / roi_size and target coordinates by target_size /
  roi_size (the official code uses the SOURCE representation region for both); flow = difference.
  """
  t, b, l, r = (int(v) for v in region0)
  roi = np.asarray(flow, np.float32)[t:b, l:r]
  rh, rw = roi.shape[:2]
  (sh, sw), (th, tw) = src_hw, tgt_hw
  grid = np.stack(np.meshgrid(np.arange(rw, dtype=np.float32) + _f32(0.5),
                              np.arange(rh, dtype=np.float32) + _f32(0.5), indexing="xy"), -1)
  src = resize_bilinear(grid, (sh, sw))
  tgt = resize_nearest(roi, (sh, sw)) + src
  src = src * np.array([_f32(sw) / _f32(rw), _f32(sh) / _f32(rh)], np.float32)
  tgt = tgt * np.array([_f32(tw) / _f32(rw), _f32(th) / _f32(rh)], np.float32)
  return (tgt - src).astype(np.float32)


def unmap_channels(values: np.ndarray, region0: np.ndarray, src_hw) -> np.ndarray:
  """[h, w, ...] at inference resolution -> [H, W, ...]: ROI then legacy nearest."""
  t, b, l, r = (int(v) for v in region0)
  return resize_nearest(np.asarray(values)[t:b, l:r], tuple(src_hw))


def unmap_covariance(cov: np.ndarray, region0: np.ndarray, src_hw, inference_hw,
                     inverse: bool = False) -> np.ndarray:
  """Covariance triplets [h, w, 3] (px^2 at inference resolution) -> [H, W, 3] at the source
  size: unmapped like covisibility, then scaled by (rw^2, rh^2, rw rh) with rw = W / w_inference,
  rh = H / h_inference, the SOURCE image's ratios over the whole inference image (the official
  base.py:294-319; the flow's target coordinates are scaled by the target's ratios, so for
  images of different sizes this describes the flow in source pixels). `inverse`: the triplets
  are precisions, scaled by the reciprocals."""
  (h, w), (hi, wi) = tuple(src_hw), tuple(inference_hw)
  # float32 like the official torch.tensor([w_ratio**2, ...]) (python floats -> float32)
  rw, rh = w / wi, h / hi
  out = unmap_channels(np.asarray(cov, np.float32), region0, src_hw)
  scale = np.array([rw ** 2, rh ** 2, rw * rh], np.float32)
  return (out / scale if inverse else out * scale).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Model plumbing
# ----------------------------------------------------------------------------------------------
def inference_resolutions(model) -> list[tuple[int, int]]:
  """(H, W) inference resolutions of a model (its config's `inference_resolution`)."""
  res = None
  for owner in (model, getattr(model, "config", None)):
    if owner is None:
      continue
    res = owner.get("inference_resolution") if isinstance(owner, dict) else getattr(
        owner, "inference_resolution", None)
    if res is not None:
      break
  if res is None:
    return [DEFAULT_INFERENCE_RESOLUTION]
  res = [tuple(int(v) for v in r) for r in (res if isinstance(res[0], (list, tuple)) else [res])]
  return res


_FORWARDS: dict[int, tuple[Any, Any, set]] = {}
# The forward outputs predict unmaps (those a model has).
PREDICTED = ("flow", "covisibility", "flow_covariance", "flow_covariance_inv")


def _forward_fn(model):
  """(jitted forward, set of input shapes already compiled) for a model object.

  One jax.jit per model object; jax re-traces per input shape and caches the executable.
  """
  import jax

  entry = _FORWARDS.get(id(model))
  if entry is None or entry[0] is not model:
    from ufm_jax.runtime import compile_cache
    compile_cache.enable()  # a new process on the same shapes loads the executable from disk

    def fwd(variables, source, target):
      out = model.apply(variables, source, target)
      if "covisibility" not in out:
        _warn_no_covisibility(model)
      return {k: out[k] for k in PREDICTED if k in out}
    entry = (model, jax.jit(fwd), set())
    _FORWARDS[id(model)] = entry
  return entry[1], entry[2]


def _check_image(x, what: str, smallest: int = 1) -> np.ndarray:
  x = np.asarray(x)
  if x.ndim != 3 or x.shape[-1] != 3:
    raise ValueError(f"{what}: expected an HWC RGB image [H, W, 3], got shape {x.shape}")
  if min(x.shape[:2]) < smallest:
    raise ValueError(f"{what} is {x.shape[0]}x{x.shape[1]} px (HxW), under this model's minimum "
                     f"of {smallest} px per side (one image pixel per encoder patch at its "
                     f"inference resolution, ufm_jax.runtime.inference.min_image_side); use a larger image")
  if x.dtype != np.uint8 and not np.issubdtype(x.dtype, np.floating):
    raise ValueError(f"{what}: expected uint8 (or float 0..255), got dtype {x.dtype}")
  if min(x.shape[:2]) < 1:
    raise ValueError(f"{what}: empty image of shape {x.shape}")
  return x


def prepare_pair(source, target, resolutions):
  """Normalise + resize one pair: (normalised source, normalised target, bookkeeping dict)."""
  src_hw, tgt_hw = source.shape[:2], target.shape[:2]
  res = select_resolution(resolutions, src_hw, tgt_hw)
  src = resize_bilinear_aa(normalize(source), res)
  tgt = resize_bilinear_aa(normalize(target), res)
  book = dict(resolution=res, src_hw=tuple(src_hw), tgt_hw=tuple(tgt_hw),
              region0=representation_region(src_hw, res), region1=representation_region(tgt_hw, res))
  return src, tgt, book


_NO_COVISIBILITY_WARNED: set = set()


def _warn_no_covisibility(model) -> None:
  """Says once per model class and config that its predictions carry no covisibility."""
  from absl import logging
  key = (type(model).__name__, getattr(model, "config", None))
  if key not in _NO_COVISIBILITY_WARNED:
    _NO_COVISIBILITY_WARNED.add(key)
    logging.warning("%s predicts no covisibility (no non_occluded_mask adaptor in any head): "
                    "predictions have no covisibility", type(model).__name__)


def unmap_prediction(pred: dict, book) -> dict[str, np.ndarray]:
  """Forward outputs of one pair at inference resolution ({"flow"[, "covisibility",
  "flow_covariance", "flow_covariance_inv"]}) -> the same keys at the source resolution."""
  out = {"flow": unmap_flow(pred["flow"], book["region0"], book["src_hw"], book["tgt_hw"])}
  if pred.get("covisibility") is not None:
    out["covisibility"] = unmap_channels(np.asarray(pred["covisibility"], np.float32),
                                         book["region0"], book["src_hw"])
  for key in ("flow_covariance", "flow_covariance_inv"):
    if pred.get(key) is not None:
      out[key] = unmap_covariance(pred[key], book["region0"], book["src_hw"], book["resolution"],
                                  inverse=key == "flow_covariance_inv")
  return out


def min_image_side(model) -> int:
  """The shortest image side `predict` takes for `model`: one image pixel per encoder patch.

  predict resizes both images to the model's inference resolution (420x560 for the released
  models, 30x40 patches of 14 px). A side shorter than its number of patches is stretched so that
  every image pixel covers more than a patch: the patches then carry no texture of their own and
  the flow means nothing (a 1x1 image gives a constant field). So the limit is
  ceil(inference side / patch size): 30 px for the released 420x560 models."""
  config = getattr(model, "config", None)
  patch = getattr(getattr(config, "encoder", None), "patch_size", 14)
  return max(-(-min(min(r) for r in inference_resolutions(model)) // patch), 1)


def predict(model, variables, source, target, *, batch_size: int = 8, resolutions=None,
            timings: list | None = None):
  """Official high-level inference (`predict_correspondences_batched`).

  Args:
    model, variables: a UFM model and its variables {"params"[, "batch_stats"]}, as
      `ufm_jax.load_official` / `ufm_jax.load` return them (a bare parameter tree is taken too).
    source, target: one pair of HWC uint8 RGB images (sizes may differ), or two equal-length
      lists of such images, or two [B, H, W, 3] arrays.
    batch_size: pairs per forward call (pairs are grouped by inference resolution).
    resolutions: (H, W) inference resolutions overriding the model config's.
    timings: if a list, gets one (seconds, n_pairs) entry per forward call that did not compile
      (device time of the jitted forward only: no resize, unmap or I/O).
  Returns:
    {"flow": [H, W, 2] float32 px, "covisibility": [H, W] float32} at the SOURCE size for a single
    pair; a list of such dicts for lists; stacked [B, ...] arrays for [B, H, W, 3] inputs. No
    "covisibility" from a model without a covisibility output. A model with a flow covariance adds
    "flow_covariance" [H, W, 3] = (var_x, var_y, cov_xy) in px^2 and its inverse
    "flow_covariance_inv" [H, W, 3] (`unmap_covariance`).
  """
  if getattr(source, "ndim", None) == 4:
    source, target = np.asarray(source), np.asarray(target)
    if target.ndim != 4 or len(target) != len(source):
      raise ValueError(f"batched predict: source {source.shape} and target {target.shape} must "
                       "both be [B, H, W, 3] with the same B")
    outs = predict(model, variables, list(source), list(target), batch_size=batch_size,
                   resolutions=resolutions, timings=timings)
    return {k: np.stack([o[k] for o in outs]) for k in outs[0]}
  single = not isinstance(source, (list, tuple))
  sources = [source] if single else list(source)
  targets = [target] if single else list(target)
  if len(sources) != len(targets):
    raise ValueError(f"predict: {len(sources)} source images but {len(targets)} target images")
  smallest = min_image_side(model)
  sources = [_check_image(s, f"source[{i}]", smallest) for i, s in enumerate(sources)]
  targets = [_check_image(t, f"target[{i}]", smallest) for i, t in enumerate(targets)]
  resolutions = [tuple(r) for r in resolutions] if resolutions else inference_resolutions(model)
  fwd, compiled_shapes = _forward_fn(model)
  from ufm_jax.models import ufm
  variables = ufm.variables(variables)   # one pytree structure: one compile per shape

  import jax

  prepared = [prepare_pair(s, t, resolutions) for s, t in zip(sources, targets)]
  results: list[dict | None] = [None] * len(prepared)
  by_res: dict[tuple, list[int]] = {}
  for i, (_, _, book) in enumerate(prepared):
    by_res.setdefault(book["resolution"], []).append(i)
  for idx in by_res.values():
    for start in range(0, len(idx), batch_size):
      chunk = idx[start:start + batch_size]
      src = denormalize(np.stack([prepared[i][0] for i in chunk]))
      tgt = denormalize(np.stack([prepared[i][1] for i in chunk]))
      t0 = time.perf_counter()
      out = jax.block_until_ready(fwd(variables, src, tgt))
      if timings is not None and src.shape in compiled_shapes:
        timings.append((time.perf_counter() - t0, len(chunk)))
      compiled_shapes.add(src.shape)
      out = {k: np.asarray(v, np.float32) for k, v in out.items()}
      for j, i in enumerate(chunk):
        results[i] = unmap_prediction({k: v[j] for k, v in out.items()}, prepared[i][2])
  return results[0] if single else results
