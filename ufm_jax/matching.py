"""Sparse matches from UFM's dense flow + covisibility, for pose / SfM tools (OpenCV, COLMAP).

  m = ufm_jax.match(model, variables, source, target, num=5000, min_covisibility=0.5)
  m["keypoints0"], m["keypoints1"]   # [N, 2] float pixels (x right, y down, pixel centres at
                                     # integers) of the ORIGINAL source / target images
  m["confidence"]                    # [N] predicted covisibility of each match
  m["eligible"]                      # source pixels it could draw from: N < num when fewer

The sampling is the pose benchmark's (ufm_jax.metrics.sample_matches: covisibility-weighted,
KDE-balanced), so matches fed to a solver here are distributed as in the paper's Table 4.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ufm_jax import metrics
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
                       backward_flow=None, max_fb_error_px=1.0, seed=0) -> dict[str, np.ndarray]:
  """Samples matches from a dense source->target flow [H, W, 2] and covisibility [H, W].

  With `backward_flow` (target->source, [H1, W1, 2]) only mutually consistent pixels (forward-
  backward error <= max_fb_error_px) are drawn.
  """
  flow = np.asarray(flow, np.float32)
  if covisibility is None:
    raise ValueError("matches are drawn by predicted covisibility, and this model predicts none "
                     "(it has no uncertainty head, as the refinement training recipe's model); "
                     "use a model with covisibility (UFM-Base, UFM-Refine)")
  covis = np.asarray(covisibility, np.float32)
  if backward_flow is not None:
    covis = np.where(forward_backward_error(flow, backward_flow) <= max_fb_error_px, covis, 0.0)
  stats = {}
  k0, k1, idx = metrics.sample_matches(flow, covis, num, np.random.default_rng(seed),
                                       target_hw=target_hw, min_covisibility=min_covisibility,
                                       return_index=True, stats=stats)
  return {"keypoints0": k0.astype(np.float32), "keypoints1": k1.astype(np.float32),
          "confidence": covis.reshape(-1)[idx].astype(np.float32),
          "eligible": np.int64(stats["eligible"])}


def shortfall(m: dict, num: int, min_covisibility: float, bidirectional: bool = False) -> str:
  """Why a match dict holds fewer than the `num` matches asked for ("" when it holds them all):
  only m["eligible"] source pixels pass the rules a match must meet."""
  n = len(m["keypoints0"])
  if n >= num:
    return ""
  rules = f"covisibility >= {min_covisibility:g} and a match inside the target"
  if bidirectional:
    rules += ", forward-backward consistent"
  return (f"{n} of the {num} asked: only {int(m['eligible'])} source pixels have {rules} (lower "
          f"--min-covisibility / the threshold for more)")


def match(model, variables, source, target, num=5000, min_covisibility=0.5, bidirectional=False,
          max_fb_error_px=1.0, seed=0) -> dict[str, np.ndarray]:
  """Matches between two HWC uint8 RGB images (any sizes) in their original pixel coordinates;
  `variables` as the loaders return them."""
  from ufm_jax import inference
  source, target = np.asarray(source), np.asarray(target)
  if bidirectional:
    fwd, bwd = inference.predict(model, variables, [source, target], [target, source])
  else:
    fwd, bwd = inference.predict(model, variables, source, target), None
  return matches_from_dense(fwd["flow"], fwd.get("covisibility"), num=num,
                            min_covisibility=min_covisibility, target_hw=target.shape[:2],
                            backward_flow=None if bwd is None else bwd["flow"],
                            max_fb_error_px=max_fb_error_px, seed=seed)


def save_matches(path, m: dict, image0_hw, image1_hw) -> pathlib.Path:
  """Writes a match dict as .npz (keypoints0, keypoints1, confidence, image0_hw, image1_hw)
  atomically, creating the folder; the file `python -m ufm_jax match --out` writes."""
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
