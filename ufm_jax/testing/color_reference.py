"""References of the official colour jitter for the tests of our implementations. Pure numpy,
the hue step of the PIL path (ufm_jax.data.hsv_tables): torchvision's `adjust_hue` on a PIL image
(torchvision/transforms/_functional_pil.py: `convert("HSV")`, the hue plane shifted by
int8(hue_factor * 255) with uint8 wrap-around, `convert("RGB")`) with Pillow's two conversions
written from its C code (libImaging/Convert.c `rgb2hsv_row`, `hsv2rgb`: float32 and double
arithmetic as C evaluates them, truncating casts, C's round-half-away-from-zero). They need
neither PIL nor torchvision, so CI checks the tables against the formula on every colour. In
torch (the torch extra), `torchvision_tensor_jitter`: ColorJitter on a float tensor, the Kubric
path, a HAND COPY of torchvision's functions (torchvision/transforms/_functional_tensor.py:
`_blend`, `rgb_to_grayscale`, `adjust_hue` with `_rgb2hsv` / `_hsv2rgb`, compared line by line
with pytorch/vision commit 0ffa6ae), not torchvision itself, which is not installed (PyPI's
torchvision does not import beside torch 2.13.0)."""

from __future__ import annotations

import numpy as np

_F, _D = np.float32, np.float64


def _clip8(v: np.ndarray) -> np.ndarray:
  return np.clip(v, 0, 255).astype(np.uint8)


def _c_round(x: np.ndarray) -> np.ndarray:
  """C `round` of non-negative doubles: halves away from zero (numpy rounds them to even)."""
  r = np.floor(x)
  return (r + (x - r >= 0.5)).astype(np.int64)


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
  """[..., 3] uint8 RGB -> [..., 3] uint8 HSV as Pillow's `convert("HSV")`."""
  r, g, b = (rgb[..., k].astype(np.int64) for k in range(3))
  maxc = np.maximum(r, np.maximum(g, b))
  minc = np.minimum(r, np.minimum(g, b))
  grey = maxc == minc
  cr = (maxc - minc).astype(_F)
  cr = np.where(grey, _F(1), cr)                      # keeps the grey pixels free of 0 / 0
  with np.errstate(divide="ignore"):                  # black: grey, s unused
    s = (cr / maxc.astype(_F)).astype(_F)
  rc, gc, bc = (((maxc - c).astype(_F) / cr).astype(_F) for c in (r, g, b))
  h = np.where(r == maxc, (bc - gc).astype(_F),
               np.where(g == maxc, (2.0 + rc.astype(_D) - bc.astype(_D)).astype(_F),
                        (4.0 + gc.astype(_D) - rc.astype(_D)).astype(_F)))
  h = np.fmod(h.astype(_D) / 6.0 + 1.0, 1.0).astype(_F)
  uh = _clip8(np.trunc(h.astype(_D) * 255.0))
  us = _clip8(np.trunc(s.astype(_D) * 255.0))
  out = np.stack([np.where(grey, 0, uh), np.where(grey, 0, us), maxc], -1)
  return out.astype(np.uint8)


def hsv_to_rgb(hsv: np.ndarray) -> np.ndarray:
  """[..., 3] uint8 HSV -> [..., 3] uint8 RGB as Pillow's `convert("RGB")` of an HSV image."""
  h, s, v = (hsv[..., k] for k in range(3))
  hd = h.astype(_F).astype(_D) * 6.0 / 255.0
  i = np.floor(hd).astype(np.int64)
  f = (hd - i.astype(_F).astype(_D)).astype(_F)
  fs = (s.astype(_F).astype(_D) / 255.0).astype(_F)
  vd = v.astype(_F).astype(_D)
  p = _clip8(_c_round(vd * (1.0 - fs.astype(_D))))
  q = _clip8(_c_round(vd * (1.0 - (fs * f).astype(_F).astype(_D))))
  t = _clip8(_c_round(vd * (1.0 - fs.astype(_D) * (1.0 - f.astype(_D)))))
  v = v.astype(np.uint8)
  sector = i % 6
  choose = lambda *opts: np.select([sector == k for k in range(6)], opts)  # noqa: E731
  out = np.stack([choose(v, q, p, p, t, v), choose(t, v, v, q, p, p),
                  choose(p, p, t, v, v, q)], -1).astype(np.uint8)
  grey = (s == 0)[..., None]
  return np.where(grey, v[..., None], out)


def adjust_hue(rgb: np.ndarray, hue_factor: float) -> np.ndarray:
  """torchvision's `adjust_hue` of a PIL RGB image, on its uint8 array."""
  hsv = rgb_to_hsv(rgb)
  hsv[..., 0] += np.int32(hue_factor * 255).astype(np.uint8)   # int8 cast, uint8 wrap-around
  return hsv_to_rgb(hsv)


def all_colours(chunks: int = 16):
  """Every packed colour c0 | c1 << 8 | c2 << 16 as [2^24 / chunks, 3] uint8 arrays, in order."""
  n = (1 << 24) // chunks
  for k in range(chunks):
    packed = np.arange(k * n, (k + 1) * n, dtype=np.uint32)
    yield packed.view(np.uint8).reshape(n, 4)[:, :3]


def torchvision_tensor_jitter(image: np.ndarray, params) -> np.ndarray:
  """Hand copy of torchvision's ColorJitter of `image / 255` as a float tensor (module
  docstring: which file and commit) with params = (order,
  brightness, contrast, saturation, hue), returned as `(img * 255).to(uint8)` (the official
  Kubric path, kubric4d.py:171-178). Needs torch."""
  import torch  # pylint: disable=g-import-not-at-top

  def blend(a, b, ratio):
    return (ratio * a + (1.0 - ratio) * b).clamp(0, 1.0)

  def gray(img):
    r, g, b = img.unbind(dim=-3)
    return (0.2989 * r + 0.587 * g + 0.114 * b).to(img.dtype).unsqueeze(-3)

  def rgb2hsv(img):
    r, g, b = img.unbind(dim=-3)
    maxc, minc = torch.max(img, dim=-3).values, torch.min(img, dim=-3).values
    eqc = maxc == minc
    cr = maxc - minc
    ones = torch.ones_like(maxc)
    s = cr / torch.where(eqc, ones, maxc)
    crd = torch.where(eqc, ones, cr)
    rc, gc, bc = (maxc - r) / crd, (maxc - g) / crd, (maxc - b) / crd
    h = ((maxc == r) * (bc - gc) + ((maxc == g) & (maxc != r)) * (2.0 + rc - bc)
         + ((maxc != g) & (maxc != r)) * (4.0 + gc - rc))
    return torch.stack((torch.fmod(h / 6.0 + 1.0, 1.0), s, maxc), dim=-3)

  def hsv2rgb(img):
    h, s, v = img.unbind(dim=-3)
    i = torch.floor(h * 6.0)
    f = h * 6.0 - i
    i = i.to(torch.int32) % 6
    p = torch.clamp(v * (1.0 - s), 0.0, 1.0)
    q = torch.clamp(v * (1.0 - s * f), 0.0, 1.0)
    t = torch.clamp(v * (1.0 - s * (1.0 - f)), 0.0, 1.0)
    mask = i.unsqueeze(-3) == torch.arange(6).view(-1, 1, 1)
    a = torch.stack((torch.stack((v, q, p, p, t, v), -3), torch.stack((t, v, v, q, p, p), -3),
                     torch.stack((p, p, t, v, v, q), -3)), -4)
    return torch.einsum("...ijk, ...xijk -> ...xjk", mask.to(img.dtype), a)

  order, b, c, s, hue = params
  x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float() / 255
  for op in order:
    if op == 0:
      x = blend(x, torch.zeros_like(x), b)
    elif op == 1:
      x = blend(x, torch.mean(gray(x), dim=(-3, -2, -1), keepdim=True), c)
    elif op == 2:
      x = blend(x, gray(x), s)
    else:
      h, sat, val = rgb2hsv(x).unbind(dim=-3)
      x = hsv2rgb(torch.stack(((h + hue) % 1.0, sat, val), dim=-3))
  return (x * 255).to(torch.uint8).permute(1, 2, 0).numpy()
