"""Sparse matches from UFM's dense flow + covisibility, for pose / SfM tools (OpenCV, COLMAP).

  m = ufm_jax.match(model, variables, source, target, num=5000, min_covisibility=0.5)
  m["keypoints0"], m["keypoints1"]   # [N, 2] float pixels (x right, y down, pixel centres at
                                     # integers) of the ORIGINAL source / target images
  m["confidence"]                    # [N] predicted covisibility of each match
  m["eligible"]                      # source pixels it could draw from: N < num when fewer

The sampling is the pose benchmark's (ufm_jax.evaluators.metrics.sample_matches: covisibility-weighted,
KDE-balanced), so matches fed to a solver here are distributed as in the paper's Table 4.

A model with a flow covariance also gives each match the uncertainty of keypoints1, in the
TARGET image's pixels (x, y) (the official predict scales the covariance by the source image's
ratios, `inference.unmap_covariance`; here it is brought to the target's, which differs only for
images of different sizes):

  m["covariance"]                    # [N, 2, 2] px^2
  m["precision"]                     # [N, 2, 2] its inverse, px^-2 (weights for a solver)
  m["sigma"]                         # [N] sqrt of the larger eigenvalue, px

and ranks the matches by it: they come most certain first (ascending sigma), and `max_sigma` (px)
drops those less certain than that.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ufm_jax.evaluators import metrics
from ufm_jax.data import io


def forward_backward_error(flow: np.ndarray, backward: np.ndarray) -> np.ndarray:
  """[H, W] |flow(p) + backward(p + flow(p))| in px (inf where p + flow(p) leaves the target)."""
  import cv2
  h, w = flow.shape[:2]
  ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
  mx, my = xs + flow[..., 0], ys + flow[..., 1]
  back = cv2.remap(np.ascontiguousarray(backward, np.float32), mx.astype(np.float32),
                   my.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                   borderValue=(np.nan, np.nan))
  err = np.linalg.norm(flow + back, axis=-1)
  return np.where(np.isfinite(err), err, np.inf)


def matches_from_dense(flow, covisibility, *, num=5000, min_covisibility=0.5, target_hw=None,
                       backward_flow=None, max_fb_error_px=1.0, seed=0, covariance=None,
                       covariance_inv=None, max_sigma=None) -> dict[str, np.ndarray]:
  """Samples matches from a dense source->target flow [H, W, 2] and covisibility [H, W].

  With `backward_flow` (target->source, [H1, W1, 2]) only mutually consistent pixels (forward-
  backward error <= max_fb_error_px) are drawn. With `covariance` (and its inverse
  `covariance_inv`, [H, W, 3] as `ufm_jax.predict` returns them) each match gets its covariance,
  precision and sigma in target pixels and the matches are ranked by sigma (module docstring).
  """
  flow = np.asarray(flow, np.float32)
  if covisibility is None:
    raise ValueError("matches are drawn by predicted covisibility, and this model predicts none "
                     "(no non_occluded_mask adaptor in any head: the refinement training "
                     "recipe's model, or a UniFlowMatch whose adaptor map is {flow}); use a model "
                     "with covisibility (UFM-Base, UFM-Refine)")
  covis = np.asarray(covisibility, np.float32)
  if backward_flow is not None:
    covis = np.where(forward_backward_error(flow, backward_flow) <= max_fb_error_px, covis, 0.0)
  stats = {}
  k0, k1, idx = metrics.sample_matches(flow, covis, num, np.random.default_rng(seed),
                                       target_hw=target_hw, min_covisibility=min_covisibility,
                                       return_index=True, stats=stats)
  m = {"keypoints0": k0.astype(np.float32), "keypoints1": k1.astype(np.float32),
       "confidence": covis.reshape(-1)[idx].astype(np.float32),
       "eligible": np.int64(stats["eligible"])}
  if covariance is None:
    if max_sigma is not None:
      raise ValueError("max_sigma ranks matches by the flow covariance, and this model predicts "
                       "none (no flow_cov head)")
    return m
  return _rank_by_uncertainty(m, idx, covariance, covariance_inv, flow.shape[:2],
                              target_hw or flow.shape[:2], max_sigma)


def _rank_by_uncertainty(m, idx, cov, cov_inv, source_hw, target_hw, max_sigma):
  """Adds covariance / precision / sigma of keypoints1 in target pixels, most certain first
  (with `max_sigma`, "sigma_dropped": how many drawn matches it removed)."""
  from ufm_jax.models import covariance as cov_lib
  (sh, sw), (th, tw) = source_hw, target_hw
  sx, sy = tw / sw, th / sh     # the official scaling used the source's ratios
  cov = cov_lib.rescale(np.asarray(cov, np.float64).reshape(-1, 3)[idx], sx, sy)
  inv = (cov_lib.inverse(cov) if cov_inv is None else
         cov_lib.rescale(np.asarray(cov_inv, np.float64).reshape(-1, 3)[idx], 1 / sx, 1 / sy))
  sigma = cov_lib.sigma_max(cov)
  order = np.argsort(sigma, kind="stable")
  out = dict(m)
  if max_sigma is not None:
    order = order[sigma[order] <= max_sigma]
    out["sigma_dropped"] = np.int64(len(sigma) - len(order))
  out.update({k: m[k][order] for k in ("keypoints0", "keypoints1", "confidence")})
  out.update(covariance=cov_lib.matrices(cov[order]).astype(np.float32),
             precision=cov_lib.matrices(inv[order]).astype(np.float32),
             sigma=sigma[order].astype(np.float32))
  return out


def shortfall(m: dict, num: int, min_covisibility: float, bidirectional: bool = False) -> str:
  """Why a match dict holds fewer than the `num` matches asked for ("" when it holds them all):
  only m["eligible"] source pixels pass the rules a match must meet, and `max_sigma` may have
  dropped drawn ones (m["sigma_dropped"])."""
  n = len(m["keypoints0"])
  if n >= num:
    return ""
  rules = f"covisibility >= {min_covisibility:g} and a match inside the target"
  if bidirectional:
    rules += ", forward-backward consistent"
  why = (f"{n} of the {num} asked: only {int(m['eligible'])} source pixels have {rules} (lower "
         f"--min-covisibility / the threshold for more)")
  if int(m.get("sigma_dropped", 0)):
    why = (f"{n} of the {num} asked: --max-sigma dropped {int(m['sigma_dropped'])} of the "
           f"drawn matches" + ("" if int(m["eligible"]) >= num else
                               f"; only {int(m['eligible'])} source pixels have {rules}"))
  return why


def match(model, variables, source, target, num=5000, min_covisibility=0.5, bidirectional=False,
          max_fb_error_px=1.0, seed=0, max_sigma=None) -> dict[str, np.ndarray]:
  """Matches between two HWC uint8 RGB images (any sizes) in their original pixel coordinates;
  `variables` as the loaders return them. With a flow covariance model also their covariance,
  precision and sigma, most certain first (`max_sigma` px drops the others)."""
  from ufm_jax.runtime import inference
  source, target = np.asarray(source), np.asarray(target)
  if bidirectional:
    fwd, bwd = inference.predict(model, variables, [source, target], [target, source])
  else:
    fwd, bwd = inference.predict(model, variables, source, target), None
  return matches_from_dense(fwd["flow"], fwd.get("covisibility"), num=num,
                            min_covisibility=min_covisibility, target_hw=target.shape[:2],
                            backward_flow=None if bwd is None else bwd["flow"],
                            max_fb_error_px=max_fb_error_px, seed=seed,
                            covariance=fwd.get("flow_covariance"),
                            covariance_inv=fwd.get("flow_covariance_inv"), max_sigma=max_sigma)


def save_matches(path, m: dict, image0_hw, image1_hw) -> pathlib.Path:
  """Writes a match dict as .npz (keypoints0, keypoints1, confidence, image0_hw, image1_hw, and
  covariance, precision, sigma when it has them) atomically, creating the folder; the file
  `python -m ufm_jax match --out` writes."""
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  with io.atomic_file(path, ".npz") as tmp:  # np.savez appends .npz otherwise
    np.savez(tmp, **m, image0_hw=np.array(image0_hw[:2]), image1_hw=np.array(image1_hw[:2]))
  return path


def draw_matches(source, target, keypoints0, keypoints1, max_lines=300, seed=0) -> np.ndarray:
  """source | target side by side (heights padded) with up to max_lines matches as lines."""
  import cv2
  h = max(source.shape[0], target.shape[0])
  pad = lambda im: np.pad(im, ((0, h - im.shape[0]), (0, 0), (0, 0)))  # noqa: E731
  canvas = np.ascontiguousarray(np.concatenate([pad(source), pad(target)], 1))
  sel = np.random.default_rng(seed).permutation(len(keypoints0))[:max_lines]
  off = np.array([source.shape[1], 0], np.float32)
  colours = cv2.applyColorMap(np.linspace(0, 255, max(len(sel), 1)).astype(np.uint8)[:, None],
                              cv2.COLORMAP_HSV)[:, 0]
  for c, i in zip(colours, sel):
    p0 = tuple(int(round(v)) for v in keypoints0[i])
    p1 = tuple(int(round(v)) for v in keypoints1[i] + off)
    cv2.line(canvas, p0, p1, tuple(int(v) for v in c), 1, cv2.LINE_AA)
  return canvas
