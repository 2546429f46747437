"""The TA-WB geometric sampler (supplementary "TA-WB Training & Testing Dataset").

From TartanAir V2 trajectories with all six pinhole cube faces per pose (lcam_front/back/left/
right/top/bottom share one optical centre):
 1. voxelise the scene from the cube-face depths and record, per camera pose, the voxels its
    faces see (camera-to-voxel visibility: a voxel is visible when a depth pixel lands in it);
 2. pick a source pose and a visible voxel within [min_dist, max_dist] of it: the source looks at
    the voxel;
 3. pick a target pose that sees the same voxel and whose direction to it differs from the
    source's by an angle inside the requested bin;
 4. complete each viewing direction into a rotation with a roll ~ N(0, roll_sigma^2) about the
    optical axis, then perturb all axes by a rotation vector ~ N(0, perturb_sigma^2 I)
    (sigma = 0.1 rad by default: we read the paper's N(0, 0.1) as numpy's normal(0, 0.1));
 5. render both virtual pinhole views from the cube faces: image bilinear, depth bilinear in
    inverse depth (exact on planar patches) or nearest across depth edges, converted through the
    range to the virtual camera's z;
 6. filter: more than `max_bad_exposure` (10%) over- (>= 250) or under-exposed (<= 5) grey pixels
    in either image; forward or backward covisibility below `min_covis` (20%, fraction of all
    pixels); unsolvable pairs. Solvability: warp image 1 into image 0 by the ground-truth flow and
    match the warp to image 0 with OpenCV SIFT + Lowe's ratio test (0.8); the displacement of a
    correct match is ~0, so keep the pair when at least `min_matches` covisible matches have a
    mean displacement below `max_match_error` (6 px). The paper used SuperPoint + LightGlue,
    which is not available here (no learned matcher in this environment); SIFT is the
    substitution, so the filter is stricter on texture-poor pairs than the original.
 7. angle bins: [0, 30], [30, 60], [60, 90] degrees get equal counts, [90, 120] half as many.
Outputs use the extracted TA-WB layout read by the `tawb` source.
"""

from __future__ import annotations

import dataclasses
import json
import os

import cv2
import numpy as np

from ufm_jax.data.sources import exr, posed

FACES = ("front", "back", "left", "right", "top", "bottom")
ANGLE_BINS = ((0.0, 30.0), (30.0, 60.0), (60.0, 90.0), (90.0, 120.0))
BIN_WEIGHTS = (1.0, 1.0, 1.0, 0.5)


@dataclasses.dataclass
class SamplerConfig:
  voxel_size: float = 0.5
  point_stride: int = 4            # depth pixels subsampled for the voxel map
  max_depth: float = 200.0         # TA-WB's default sky cut (metres)
  min_dist: float = 0.5
  max_dist: float = 15.0
  height: int = 640
  width: int = 640
  fov_deg: float = 90.0
  roll_sigma: float = 0.1
  perturb_sigma: float = 0.1
  max_bad_exposure: float = 0.10
  min_covis: float = 0.20
  max_match_error: float = 6.0
  min_matches: int = 20
  ratio: float = 0.8
  max_attempts_per_pair: int = 50
  tau: tuple = (0.1, 0.01)         # TartanAir row of Table S1


def bin_counts(total: int, weights=BIN_WEIGHTS) -> list[int]:
  """Pairs per angle bin: equal for the first three bins, half for the last (rounded)."""
  w = np.asarray(weights, np.float64)
  raw = total * w / w.sum()
  counts = np.floor(raw).astype(int)
  for i in np.argsort(-(raw - counts))[:total - counts.sum()]:
    counts[i] += 1
  return counts.tolist()


# ------------------------------------------------------------------------------------ cube maps

@dataclasses.dataclass
class CubePose:
  centre: np.ndarray                    # [3]
  faces: dict                           # face name -> posed.View (OpenCV c2w)


def load_cube_pose(source, scene: str, index: int, prefix: str = "lcam") -> CubePose:
  faces = {f: source.load_view(scene, f"{prefix}_{f}/{index:06d}") for f in FACES}
  centres = np.stack([v.cam2world[:3, 3] for v in faces.values()])
  if np.abs(centres - centres[0]).max() > 1e-3:
    raise ValueError(f"{scene} pose {index}: the six {prefix} faces do not share an optical centre")
  return CubePose(centres[0], faces)


def face_points(view: posed.View, stride: int, max_depth: float) -> np.ndarray:
  d = view.depth[::stride, ::stride]
  v, u = np.mgrid[0:view.depth.shape[0]:stride, 0:view.depth.shape[1]:stride].astype(np.float64)
  ok = (d > 0) & (d < max_depth)
  rays = np.stack([(u - view.K[0, 2]) / view.K[0, 0], (v - view.K[1, 2]) / view.K[1, 1],
                   np.ones_like(u)], -1)
  pc = rays[ok] * d[ok][:, None]
  return pc @ view.cam2world[:3, :3].T + view.cam2world[:3, 3]


def voxelise(poses: list[CubePose], cfg: SamplerConfig):
  """-> (voxel centres [V, 3], per-pose arrays of visible voxel indices)."""
  keys = []
  for p in poses:
    pts = np.concatenate([face_points(v, cfg.point_stride, cfg.max_depth)
                          for v in p.faces.values()])
    keys.append(np.floor(pts / cfg.voxel_size).astype(np.int64))
  allk = np.concatenate(keys)
  uniq, inv = np.unique(allk, axis=0, return_inverse=True)
  inv = inv.reshape(-1)
  visible, start = [], 0
  for k in keys:
    visible.append(np.unique(inv[start:start + len(k)]))
    start += len(k)
  return (uniq + 0.5) * cfg.voxel_size, visible


def render_view(pose: CubePose, R: np.ndarray, K: np.ndarray, hw: tuple[int, int]):
  """Virtual pinhole (rotation R = camera-to-world, centre = pose.centre) from the cube faces."""
  h, w = hw
  v, u = np.mgrid[0:h, 0:w].astype(np.float64)
  rc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
  rw = rc @ R.T
  image = np.zeros((h, w, 3), np.float32)
  depth = np.zeros((h, w), np.float32)
  best = np.full((h, w), -np.inf)
  for view in pose.faces.values():
    fc = rw @ view.cam2world[:3, :3]  # face-camera coordinates of the rays
    z = fc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
      fu = view.K[0, 0] * fc[..., 0] / z + view.K[0, 2]
      fv = view.K[1, 1] * fc[..., 1] / z + view.K[1, 2]
    fh, fw = view.depth.shape
    # The face whose axis is closest to the ray owns it (ties at cube edges resolved by order).
    score = z / np.linalg.norm(fc, axis=-1)
    own = (z > 0) & (score > best) & (fu >= -0.5) & (fu <= fw - 0.5) & (fv >= -0.5) & \
        (fv <= fh - 0.5)
    if not own.any():
      continue
    best = np.where(own, score, best)
    mu, mv = np.where(own, fu, 0).astype(np.float32), np.where(own, fv, 0).astype(np.float32)
    img = cv2.remap(view.image, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    zf = _sample_depth(view.depth, np.where(own, fu, 0), np.where(own, fv, 0))
    # z_face -> range (along this ray) -> z of the virtual camera
    rng = zf * np.linalg.norm(fc / np.where(own, z, 1)[..., None], axis=-1)
    zv = rng / np.linalg.norm(rc, axis=-1)
    image[own] = img[own]
    depth[own] = np.where(zf[own] > 0, zv[own], 0)
  return np.clip(np.rint(image), 0, 255).astype(np.uint8), depth


def _sample_depth(depth, fu, fv, max_spread=0.05):
  """Face z-depth at fractional pixels: bilinear in inverse depth (exact on planes, since 1/z is
  affine in pixel coordinates there), nearest where the 4 neighbours differ by more than
  `max_spread` relative (depth edges) or any is invalid."""
  h, w = depth.shape
  u = np.clip(fu, 0, w - 1)
  v = np.clip(fv, 0, h - 1)
  x0 = np.minimum(np.floor(u).astype(np.int64), max(w - 2, 0))
  y0 = np.minimum(np.floor(v).astype(np.int64), max(h - 2, 0))
  ax, ay = u - x0, v - y0
  d = [depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]]
  lo, hi = np.minimum.reduce(d), np.maximum.reduce(d)
  smooth = (lo > 0) & (hi <= lo * (1 + max_spread))
  with np.errstate(divide="ignore"):
    inv = [np.where(di > 0, 1 / np.maximum(di, 1e-12), 0) for di in d]
  bil = (inv[0] * (1 - ax) * (1 - ay) + inv[1] * ax * (1 - ay) + inv[2] * (1 - ax) * ay
         + inv[3] * ax * ay)
  near = depth[np.clip(np.rint(fv), 0, h - 1).astype(np.int64),
               np.clip(np.rint(fu), 0, w - 1).astype(np.int64)]
  return np.where(smooth, 1 / np.where(smooth, bil, 1), near)


def look_rotation(direction: np.ndarray, down=(0.0, 0.0, 1.0)) -> np.ndarray:
  """OpenCV camera-to-world rotation looking along `direction`, image-down towards world `down`
  (TartanAir's world is NED: +z is down)."""
  z = direction / np.linalg.norm(direction)
  down = np.asarray(down, np.float64)
  y = down - z * (down @ z)
  if np.linalg.norm(y) < 1e-6:
    y = np.array([1.0, 0, 0]) - z * z[0]
  y /= np.linalg.norm(y)
  x = np.cross(y, z)
  return np.stack([x, y, z], 1)


def _rodrigues(vec):
  return cv2.Rodrigues(np.asarray(vec, np.float64).reshape(3, 1))[0]


def sample_rotation(direction, rng, cfg: SamplerConfig) -> np.ndarray:
  R = look_rotation(direction)
  R = R @ _rodrigues([0, 0, rng.normal(0, cfg.roll_sigma)])
  return _rodrigues(rng.normal(0, cfg.perturb_sigma, 3)) @ R


# --------------------------------------------------------------------------------------- filters

def exposure_ok(image: np.ndarray, cfg: SamplerConfig) -> bool:
  grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
  return float(((grey >= 250) | (grey <= 5)).mean()) <= cfg.max_bad_exposure


def match_error(image0, image1, flow, covis, cfg: SamplerConfig):
  """Mean SIFT displacement between image0 and image1 warped into image0 by the GT flow, over
  ratio-test matches whose keypoint in image0 is covisible. -> (mean error px, matches)."""
  h, w = flow.shape[:2]
  gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
  warped = cv2.remap(image1, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT)
  warped[~covis] = 0
  sift = cv2.SIFT_create()
  g0 = cv2.cvtColor(image0, cv2.COLOR_RGB2GRAY)
  g1 = cv2.cvtColor(warped, cv2.COLOR_RGB2GRAY)
  mask = covis.astype(np.uint8) * 255
  k0, d0 = sift.detectAndCompute(g0, mask)
  k1, d1 = sift.detectAndCompute(g1, mask)
  if d0 is None or d1 is None or len(k0) < 2 or len(k1) < 2:
    return np.inf, 0
  knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
  errs = [np.hypot(k0[m.queryIdx].pt[0] - k1[m.trainIdx].pt[0],
                   k0[m.queryIdx].pt[1] - k1[m.trainIdx].pt[1])
          for pair in knn if len(pair) == 2 for m, n in [pair] if m.distance < cfg.ratio * n.distance]
  if not errs:
    return np.inf, 0
  return float(np.mean(errs)), len(errs)


# -------------------------------------------------------------------------------------- sampling

def virtual_K(cfg: SamplerConfig) -> np.ndarray:
  f = cfg.width / 2 / np.tan(np.deg2rad(cfg.fov_deg) / 2)
  return np.array([[f, 0, (cfg.width - 1) / 2], [0, f, (cfg.height - 1) / 2], [0, 0, 1.0]])


def try_pair(poses, voxels, visible, angle_bin, rng, cfg: SamplerConfig):
  """One attempt: returns a dict (views, labels, stats) or (None, reason)."""
  from ufm_jax import geometry
  s = int(rng.integers(len(poses)))
  cs = poses[s].centre
  vis = visible[s]
  dist = np.linalg.norm(voxels[vis] - cs, axis=-1)
  near = vis[(dist >= cfg.min_dist) & (dist <= cfg.max_dist)]
  if not len(near):
    return None, "no voxel nearby"
  vox = int(near[rng.integers(len(near))])
  x = voxels[vox]
  ds = (x - cs) / np.linalg.norm(x - cs)
  cands = []
  for t, p in enumerate(poses):
    if t == s or not np.isin(vox, visible[t]):
      continue
    dt = x - p.centre
    if not cfg.min_dist <= np.linalg.norm(dt) <= cfg.max_dist:
      continue
    ang = np.degrees(np.arccos(np.clip(ds @ dt / np.linalg.norm(dt), -1, 1)))
    if angle_bin[0] <= ang < angle_bin[1]:
      cands.append((t, ang))
  if not cands:
    return None, "no target in angle bin"
  t, ang = cands[rng.integers(len(cands))]
  K = virtual_K(cfg)
  R0 = sample_rotation(ds, rng, cfg)
  R1 = sample_rotation(x - poses[t].centre, rng, cfg)
  views = []
  for p, R in ((poses[s], R0), (poses[t], R1)):
    img, depth = render_view(p, R, K, (cfg.height, cfg.width))
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, p.centre
    views.append(posed.View(img, depth, K, c2w))
  if not all(exposure_ok(v.image, cfg) for v in views):
    return None, "exposure"
  fwd = geometry.correspondence_from_depth(views[0].depth, K, views[0].cam2world, views[1].depth,
                                           K, views[1].cam2world, *cfg.tau)
  bwd = geometry.correspondence_from_depth(views[1].depth, K, views[1].cam2world, views[0].depth,
                                           K, views[0].cam2world, *cfg.tau)
  cf, cb = float(fwd["covisibility"].mean()), float(bwd["covisibility"].mean())
  if min(cf, cb) < cfg.min_covis:
    return None, "covisibility"
  err, n = match_error(views[0].image, views[1].image, fwd["flow"], fwd["covisibility"], cfg)
  if n < cfg.min_matches or err >= cfg.max_match_error:
    return None, "unsolvable"
  return dict(views=views, source_pose=s, target_pose=t, voxel=x.tolist(), angle=float(ang),
              covis_fwd=cf, covis_bwd=cb, match_error=err, matches=n), "ok"


def write_pair(out_dir: str, index: int, views) -> None:
  for sub in ("images", "depth", "camera_params", "poses"):
    os.makedirs(os.path.join(out_dir, sub), exist_ok=True)
  for k, v in enumerate(views):
    name = f"{index:08d}_{k}"
    path = os.path.join(out_dir, "images", name + ".png")
    tmp = path + ".tmp.png"
    if not cv2.imwrite(tmp, v.image[..., ::-1]):
      raise OSError(f"{path}: cannot write image")
    os.replace(tmp, path)
    exr.write_exr(os.path.join(out_dir, "depth", name + ".exr"), v.depth)
    for sub, arr in (("camera_params", v.K), ("poses", v.cam2world)):
      p = os.path.join(out_dir, sub, name + ".npy")
      with open(p + ".tmp", "wb") as f:
        np.save(f, arr)
      os.replace(p + ".tmp", p)


def sample_environment(source, scene: str, pose_indices, out_dir: str, total: int, seed: int,
                       cfg: SamplerConfig, progress: bool = True, start_index: int = 0):
  """Samples `total` pairs (split over the angle bins) from one trajectory into `out_dir`.

  Returns the list of per-pair records (also written to `<out_dir>/pairs_meta.jsonl`)."""
  import tqdm
  rng = np.random.default_rng(seed)
  poses = [load_cube_pose(source, scene, i) for i in tqdm.tqdm(
      pose_indices, desc=f"{scene}: cube maps", disable=not progress)]
  voxels, visible = voxelise(poses, cfg)
  records, index = [], start_index
  rejected: dict[str, int] = {}
  for angle_bin, count in zip(ANGLE_BINS, bin_counts(total)):
    got, attempts = 0, 0
    bar = tqdm.tqdm(total=count, desc=f"{scene}: {angle_bin[0]:.0f}-{angle_bin[1]:.0f} deg",
                    disable=not progress)
    while got < count and attempts < cfg.max_attempts_per_pair * max(count, 1):
      attempts += 1
      res, why = try_pair(poses, voxels, visible, angle_bin, rng, cfg)
      if res is None:
        rejected[why] = rejected.get(why, 0) + 1
        continue
      write_pair(out_dir, index, res.pop("views"))
      res.update(index=index, bin=list(angle_bin), scene=scene,
                 source_index=int(pose_indices[res["source_pose"]]),
                 target_index=int(pose_indices[res["target_pose"]]))
      records.append(res)
      index += 1
      got += 1
      bar.update(1)
    bar.close()
  os.makedirs(out_dir, exist_ok=True)
  path = os.path.join(out_dir, "pairs_meta.jsonl")
  previous = open(path).read() if os.path.isfile(path) else ""
  with open(path + ".tmp", "w") as f:  # rewritten whole, then renamed: never half-written
    f.write(previous + "".join(json.dumps(r) + "\n" for r in records))
  os.replace(path + ".tmp", path)
  return records, rejected
