"""Tiny on-disk trees for the wide-baseline readers, with a scene whose correspondences are known.

The scene is one textured plane n.X = d seen by two pinhole cameras. Depth is rendered
analytically (z-depth at pixel centres), and the true flow is the plane-induced homography
H = K1 (R + t n0^T / d0) K0^-1, a formula independent of the depth-reprojection code under test.
Each `write_<dataset>` stores the scene in that dataset's own on-disk conventions (w2c vs c2w,
OpenGL / NED axes, COLMAP pixel centres, range depth, millimetres, invalid markers), so a reader
that gets a convention wrong produces a flow that disagrees with H.

Run as a script to print per-sample load times at each dataset's native training-size shape:
  python -m ufm_jax.testing.wide_trees [H W]
"""

from __future__ import annotations

import json
import os

import cv2
import h5py
import numpy as np


def look_at(eye, target, up=(0.0, -1.0, 0.0), roll=0.0):
  """OpenCV c2w at `eye` looking at `target` (independent of ufm_jax.geometry on purpose)."""
  eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
  z = target - eye
  z /= np.linalg.norm(z)
  x = np.cross(z, up)
  x /= np.linalg.norm(x)
  y = np.cross(z, x)
  R = np.stack([x, y, z], 1)
  c, s = np.cos(roll), np.sin(roll)
  R = R @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
  T = np.eye(4)
  T[:3, :3], T[:3, 3] = R, eye
  return T


def K_of(fx, fy, cx, cy):
  return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


class PlaneScene:
  """Two views of the plane n.X = d (world units = metres)."""

  def __init__(self, hw0=(36, 48), hw1=None, K0=None, K1=None, c2w0=None, c2w1=None,
               normal=(0.15, -0.1, -1.0), point=(0.0, 0.0, 5.0), inv0=None, inv1=None):
    self.hw = [tuple(hw0), tuple(hw1 or hw0)]
    def default_K(hw, f):
      return K_of(f * hw[1], f * hw[1] * 1.02, hw[1] / 2 - 0.7, hw[0] / 2 + 0.4)
    self.K = [K0 if K0 is not None else default_K(self.hw[0], 0.9),
              K1 if K1 is not None else default_K(self.hw[1], 1.1)]
    self.c2w = [c2w0 if c2w0 is not None else look_at((0, 0, 0), (0.3, 0.2, 5.0)),
                c2w1 if c2w1 is not None else look_at((1.0, -0.4, 1.6), (0.0, 0.3, 5.2), roll=0.2)]
    n = np.asarray(normal, np.float64)
    self.n = n / np.linalg.norm(n)
    self.d = float(self.n @ np.asarray(point, np.float64))
    self.invalid = []
    for i, box in enumerate((inv0, inv1)):
      m = np.zeros(self.hw[i], bool)
      if box is None:  # default holes: a small rectangle in each view
        h, w = self.hw[i]
        box = (h // 5, h // 5 + max(2, h // 8), w // 6 + i * w // 2, w // 6 + i * w // 2 + max(2, w // 8))
      if box:
        m[box[0]:box[1], box[2]:box[3]] = True
      self.invalid.append(m)

  def rays_world(self, i):
    h, w = self.hw[i]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], -1)
    rc = pix @ np.linalg.inv(self.K[i]).T            # z = 1 camera rays
    return rc @ self.c2w[i][:3, :3].T, rc

  def z_depth(self, i):
    """Analytic z-depth; the holes are returned as 0."""
    rw, _ = self.rays_world(i)
    C = self.c2w[i][:3, 3]
    t = (self.d - self.n @ C) / (rw @ self.n)
    return np.where(self.invalid[i] | (t <= 0), 0.0, t)

  def range_depth(self, i):
    _, rc = self.rays_world(i)
    return self.z_depth(i) * np.linalg.norm(rc, axis=-1)

  def image(self, i):
    rw, _ = self.rays_world(i)
    C = self.c2w[i][:3, 3]
    t = (self.d - self.n @ C) / (rw @ self.n)
    X = C + rw * t[..., None]
    chans = [np.sin(3.1 * X[..., 0] + 1.7 * X[..., 1]), np.sin(2.3 * X[..., 1] - 2.9 * X[..., 0]),
             np.cos(4.0 * X[..., 0] * X[..., 1] + X[..., 2])]
    return np.clip(128 + 110 * np.stack(chans, -1), 0, 255).astype(np.uint8)

  def homography(self):
    T10 = np.linalg.inv(self.c2w[1]) @ self.c2w[0]
    R0 = self.c2w[0][:3, :3]
    n0 = R0.T @ self.n
    d0 = self.d - self.n @ self.c2w[0][:3, 3]
    H = self.K[1] @ (T10[:3, :3] + np.outer(T10[:3, 3], n0) / d0) @ np.linalg.inv(self.K[0])
    return H

  def expected(self):
    """Flow 0->1, in-view mask, target-in-hole mask, ambiguous mask (near borders / hole edges)."""
    h, w = self.hw[0]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    p = np.stack([u, v, np.ones_like(u)], -1) @ self.homography().T
    tgt = p[..., :2] / p[..., 2:]
    flow = tgt - np.stack([u, v], -1)
    h1, w1 = self.hw[1]
    inside = (tgt[..., 0] >= -0.5) & (tgt[..., 0] < w1 - 0.5) & (tgt[..., 1] >= -0.5) & \
        (tgt[..., 1] < h1 - 0.5) & (p[..., 2] > 0)
    # Within half a pixel of the border the target depth is extrapolated (clamped), and within
    # 0.05 px of the image edge the in-view test is numerically ambiguous.
    band = lambda x, n: ((x > -0.55) & (x < 0.05)) | ((x > n - 1.05) & (x < n - 0.45))
    near_border = band(tgt[..., 0], w1) | band(tgt[..., 1], h1)
    ti = np.clip(np.rint(tgt[..., 1]), 0, h1 - 1).astype(int)
    tj = np.clip(np.rint(tgt[..., 0]), 0, w1 - 1).astype(int)
    hole1 = self.invalid[1][ti, tj] & inside
    # Bilinear depth lookups may mix hole and valid neighbours within a pixel of the hole edge.
    hole_u8 = self.invalid[1].astype(np.uint8)
    grown = cv2.dilate(hole_u8, np.ones((3, 3), np.uint8)) > 0
    core = cv2.erode(hole_u8, np.ones((3, 3), np.uint8), borderValue=1) > 0
    near_hole = (grown[ti, tj] & ~core[ti, tj]) & inside
    return dict(flow=flow, inside=inside & ~self.invalid[0], hole1=hole1,
                ambiguous=near_border | near_hole, near_border=near_border,
                valid0=~self.invalid[0])


def check_plane_sample(sample, scene: PlaneScene, tol=2e-3, depth_tol=1e-4, units=1.0):
  """Asserts the sample's labels against the closed-form homography."""
  e = scene.expected()
  for key in ("image0", "image1"):
    assert sample[key].dtype == np.uint8 and sample[key].ndim == 3 and sample[key].shape[2] == 3
  assert sample["image0"].shape[:2] == scene.hw[0] and sample["image1"].shape[:2] == scene.hw[1]
  flow = sample["flow"]
  assert flow.shape == scene.hw[0] + (2,) and flow.dtype == np.float32
  m = e["inside"]
  assert m.sum() > 0.3 * m.size, "test scene should be mostly covisible"
  err = np.abs(flow - e["flow"]).max(-1)
  assert err[m].max() < tol, f"flow differs from the plane homography by {err[m].max():.4f} px"
  ok = ~e["ambiguous"]
  covis_exp = e["inside"] & ~e["hole1"]
  bad = (sample["covisibility"] != covis_exp) & ok
  assert not bad.any(), f"{bad.sum()} pixels with wrong covisibility"
  assert not sample["covisibility"][~e["valid0"]].any()
  cv_exp = e["valid0"] & ~e["hole1"]
  bad = (sample["covis_valid"] != cv_exp) & ~e["near_border"]
  assert (e["inside"] & ~e["ambiguous"]).mean() > 0.3
  assert not bad.any(), f"{bad.sum()} pixels with wrong covis_valid"
  assert (sample["flow_valid"] == e["valid0"]).all()
  meta = sample["meta"]
  for i in (0, 1):
    np.testing.assert_allclose(meta[f"K{i}"], scene.K[i], atol=1e-3)
    np.testing.assert_allclose(meta[f"cam2world{i}"][:3, :3], scene.c2w[i][:3, :3], atol=1e-4)
    np.testing.assert_allclose(meta[f"cam2world{i}"][:3, 3], scene.c2w[i][:3, 3] * units,
                               atol=1e-4 * max(units, 1))
    if f"depth{i}" in meta:
      np.testing.assert_allclose(meta[f"depth{i}"], scene.z_depth(i) * units,
                                 rtol=depth_tol, atol=depth_tol)


# ------------------------------------------------------------------------------------ file writers

def mkdir(*parts) -> str:
  path = os.path.join(*parts)
  os.makedirs(path, exist_ok=True)
  return path


def write_image(path, rgb):
  assert cv2.imwrite(path, np.ascontiguousarray(rgb[..., ::-1]),
                     [cv2.IMWRITE_JPEG_QUALITY, 95] if path.lower().endswith((".jpg", ".jpeg"))
                     else [])


def write_pfm(path, data):
  data = np.asarray(data, np.float32)
  tag = b"PF" if data.ndim == 3 else b"Pf"
  with open(path, "wb") as f:
    f.write(tag + b"\n" + f"{data.shape[1]} {data.shape[0]}\n".encode() + b"-1\n")
    f.write(np.ascontiguousarray(data[::-1]).astype("<f4").tobytes())


def write_mvsnet_cam(path, w2c, K, depth_min=0.5, interval=0.01):
  with open(path, "w") as f:
    f.write("extrinsic\n")
    for r in w2c:
      f.write(" ".join(f"{x:.10f}" for x in r) + "\n")
    f.write("\nintrinsic\n")
    for r in K:
      f.write(" ".join(f"{x:.10f}" for x in r) + "\n")
    f.write(f"\n{depth_min} {interval} 192 {depth_min + 191 * interval}\n")


def write_float3(path, arr):
  arr = np.asarray(arr, np.float32)
  with open(path, "wb") as f:
    f.write(b"float\n" + f"{arr.ndim}\n".encode())
    for d in reversed(arr.shape):
      f.write(f"{d}\n".encode())
    f.write(arr.astype("<f4").tobytes())


def rotmat_to_qvec(R):
  """3x3 rotation -> unit quaternion (w, x, y, z), Shepperd's method."""
  m = R
  tr = np.trace(m)
  if tr > 0:
    s = np.sqrt(tr + 1.0) * 2
    q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
  elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
    s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
    q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
  elif m[1, 1] > m[2, 2]:
    s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
    q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
  else:
    s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
    q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
  q = np.array(q)
  return q / np.linalg.norm(q)


BLENDED_SCENE = "5a2a95f032a1c655cfe3de62"  # seq_low % 10 != 0 -> train split


def write_blendedmvs(root, scene: PlaneScene, name=BLENDED_SCENE):
  d = os.path.join(root, name)
  for sub in ("blended_images", "cams", "rendered_depth_maps"):
    mkdir(d, sub)
  for i in (0, 1):
    write_image(os.path.join(d, "blended_images", f"{i:08d}.jpg"), scene.image(i))
    write_image(os.path.join(d, "blended_images", f"{i:08d}_masked.jpg"), scene.image(i) * 0)
    write_mvsnet_cam(os.path.join(d, "cams", f"{i:08d}_cam.txt"), np.linalg.inv(scene.c2w[i]),
                     scene.K[i])
    write_pfm(os.path.join(d, "rendered_depth_maps", f"{i:08d}.pfm"), scene.z_depth(i))
  with open(os.path.join(d, "cams", "pair.txt"), "w") as f:
    f.write("2\n0\n1 1 500.0\n1\n1 0 500.0\n")
  return name


def megadepth_scene(hw=(36, 48), pre_wh=((96, 72), (80, 60)), f=(80.0, 70.0), **kw):
  """MegaDepth's undistorted-image intrinsics are, by DUSt3R's rule, getOptimalNewCameraMatrix of
  the COLMAP camera (+ a pixel-centre convention of its own); the scene is rendered with them."""
  Ks, cams = [], []
  for (w, h), fi in zip(pre_wh, f):
    K_pre = K_of(fi, fi, w / 2 + 0.3, h / 2 - 0.2)
    K_post = cv2.getOptimalNewCameraMatrix(K_pre, np.zeros(4), (w, h), 0, (hw[1], hw[0]),
                                           centerPrincipalPoint=True)[0]
    Ks.append(K_post)
    cams.append((w, h, fi, K_pre[0, 2], K_pre[1, 2]))
  scene = PlaneScene(hw0=hw, K0=Ks[0], K1=Ks[1], **kw)
  scene.colmap_cams = cams
  return scene


def write_megadepth(root, scene, name="0001", sub="0"):
  dense = os.path.join(root, name, f"dense{sub}")
  mkdir(dense, "imgs"), mkdir(dense, "depths")
  sparse = mkdir(root, name, "sparse", "manhattan", sub)
  with open(os.path.join(sparse, "cameras.txt"), "w") as f:
    f.write("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, "
            "PARAMS[]\n# Number of cameras: 2\n")
    for i, (w, h, fi, cx, cy) in enumerate(scene.colmap_cams):
      f.write(f"{i + 1} SIMPLE_RADIAL {w} {h} {fi} {cx} {cy} 0\n")
  with open(os.path.join(sparse, "images.txt"), "w") as f:
    f.write("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, "
            "TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: 2\n")
    for i in (0, 1):
      w2c = np.linalg.inv(scene.c2w[i])
      q = rotmat_to_qvec(w2c[:3, :3])
      f.write(f"{i + 1} {' '.join(f'{x:.12f}' for x in q)} "
              f"{' '.join(f'{x:.12f}' for x in w2c[:3, 3])} {i + 1} img{i}.jpg\n")
      f.write("\n" if i == 0 else "1.0 2.0 -1\n")  # an empty 2D-points line must parse too
  for i in (0, 1):
    write_image(os.path.join(dense, "imgs", f"img{i}.jpg"), scene.image(i))
    with h5py.File(os.path.join(dense, "depths", f"img{i}.h5"), "w") as f:
      f.create_dataset("depth", data=scene.z_depth(i).astype(np.float32))
  return f"{name}/{sub}", "img0.jpg", "img1.jpg"


NED_FROM_OPENCV = np.array([[0.0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def tartanair_scene(hw=(40, 40), **kw):
  h, w = hw
  K = K_of(w / 2, h / 2, (w - 1) / 2, (h - 1) / 2)
  return PlaneScene(hw0=hw, K0=K, K1=K, **kw)


def write_tartanair_v2(root, scene, env="AbandonedFactory", traj="P000", cam="lcam_front",
                       frames=(3, 4)):
  d = mkdir(root, env, "Data_easy", traj)
  mkdir(d, f"image_{cam}"), mkdir(d, f"depth_{cam}")
  lines = []
  for k in range(max(frames) + 1):
    view = frames.index(k) if k in frames else 0
    c2w_ned = scene.c2w[view] @ NED_FROM_OPENCV.T
    q = rotmat_to_qvec(c2w_ned[:3, :3])  # w x y z
    t = c2w_ned[:3, 3]
    lines.append(" ".join(f"{x:.12f}" for x in (*t, q[1], q[2], q[3], q[0])))
    if k in frames:
      write_image(os.path.join(d, f"image_{cam}", f"{k:06d}_{cam}.png"), scene.image(view))
      depth = scene.z_depth(view).astype("<f4")
      assert cv2.imwrite(os.path.join(d, f"depth_{cam}", f"{k:06d}_{cam}_depth.png"),
                         depth.view(np.uint8).reshape(depth.shape + (4,)))
  with open(os.path.join(d, f"pose_{cam}.txt"), "w") as f:
    f.write("\n".join(lines) + "\n")
  return f"{env}/Data_easy/{traj}", f"{cam}/{frames[0]:06d}", f"{cam}/{frames[1]:06d}"


def write_scannetpp(root, scene, name="0a5c013435"):
  from ufm_jax.data.sources.exr import write_exr
  d = os.path.join(root, name)
  mkdir(d, "images"), mkdir(d, "rendered_depth")
  frames = []
  for i in (0, 1):
    fn = f"DSC{i:05d}"
    write_image(os.path.join(d, "images", fn + ".jpg"), scene.image(i))
    write_exr(os.path.join(d, "rendered_depth", fn + ".exr"), scene.z_depth(i), half=False)
    K = scene.K[i]
    frames.append(dict(frame_name=fn, file_path=f"images/{fn}.jpg",
                       rendered_depth=f"rendered_depth/{fn}.exr",
                       transform_matrix=scene.c2w[i].tolist(), fl_x=K[0, 0], fl_y=K[1, 1],
                       cx=K[0, 2], cy=K[1, 2], h=scene.hw[i][0], w=scene.hw[i][1]))
  with open(os.path.join(d, "scene_meta.json"), "w") as f:
    json.dump(dict(scene_name=name, dataset_name="scannetppv2", version="0.1",
                   camera_convention="opencv", camera_model="PINHOLE", scale_type="metric",
                   shared_intrinsics=False, frames=frames), f)
  return name, "DSC00000", "DSC00001"


def write_habitat(root, scene, path="hm3d/00042-abcd", key="000123", half=True):
  from ufm_jax.data.sources.exr import write_exr
  d = mkdir(root, path)
  for i, view in ((1, 0), (2, 1)):
    write_image(os.path.join(d, f"{key}_{i}.jpeg"), scene.image(view))
    write_exr(os.path.join(d, f"{key}_{i}_depth.exr"), scene.z_depth(view), half=half)
    with open(os.path.join(d, f"{key}_{i}_camera_params.json"), "w") as f:
      json.dump(dict(camera_intrinsics=scene.K[view].tolist(),
                     R_cam2world=scene.c2w[view][:3, :3].tolist(),
                     t_cam2world=scene.c2w[view][:3, 3].tolist()), f)
  return path, f"{key}_1", f"{key}_2"


def write_staticthings(root, scene, letter="A", seq="0042", frames=(("left", 6), ("right", 7))):
  for i, (cam, idx) in enumerate(frames):
    for kind in ("frames_finalpass", "frames_cleanpass", "depths", "poses"):
      mkdir(root, kind, "TRAIN", letter, seq, cam)
    mkdir(root, "intrinsics", "TRAIN", letter, seq)
    for kind in ("frames_finalpass", "frames_cleanpass"):
      write_image(os.path.join(root, kind, "TRAIN", letter, seq, cam, f"{idx:04d}.png"),
                  scene.image(i))
    base = ("TRAIN", letter, seq, cam, f"{idx:04d}.float3")
    write_float3(os.path.join(root, "depths", *base), scene.z_depth(i))
    write_float3(os.path.join(root, "poses", *base), np.linalg.inv(scene.c2w[i]))
    write_float3(os.path.join(root, "intrinsics", "TRAIN", letter, seq, f"{idx:04d}.float3"),
                 scene.K[i])
  return f"TRAIN/{letter}/{seq}", f"{frames[0][0]}/{frames[0][1]:04d}", \
      f"{frames[1][0]}/{frames[1][1]:04d}"


def write_dtu(root, scene, scan="scan1", views=(0, 1), light=3):
  """DTU keeps millimetres: the plane scene (metres) is written scaled by 1000."""
  mkdir(root, "Rectified", scan), mkdir(root, "Cameras"), mkdir(root, "Depths_raw", scan)
  for i, v in enumerate(views):
    write_image(os.path.join(root, "Rectified", scan, f"rect_{v + 1:03d}_{light}_r5000.png"),
                scene.image(i))
    w2c = np.linalg.inv(scene.c2w[i])
    w2c[:3, 3] *= 1000
    write_mvsnet_cam(os.path.join(root, "Cameras", f"{v:08d}_cam.txt"), w2c, scene.K[i],
                     depth_min=425, interval=2.5)
    depth = scene.z_depth(i) * 1000
    depth[scene.invalid[i]] = np.nan  # DTU marks missing depth with 0 or nan
    write_pfm(os.path.join(root, "Depths_raw", scan, f"depth_map_{v:04d}.pfm"), depth)
  with open(os.path.join(root, "Cameras", "pair.txt"), "w") as f:
    f.write(f"2\n{views[0]}\n1 {views[1]} 900.0\n{views[1]}\n1 {views[0]} 900.0\n")
  return scan, str(views[0]), str(views[1])


def write_eth3d_prepared(root, scene, name="courtyard"):
  from ufm_jax.data.sources.exr import write_exr
  d = os.path.join(root, name)
  mkdir(d, "images"), mkdir(d, "depth")
  frames = []
  for i in (0, 1):
    fn = f"DSC_{i:04d}"
    write_image(os.path.join(d, "images", fn + ".jpg"), scene.image(i))
    write_exr(os.path.join(d, "depth", fn + ".exr"), scene.z_depth(i))
    K = scene.K[i]
    frames.append(dict(frame_name=fn, file_path=f"images/{fn}.jpg", depth=f"depth/{fn}.exr",
                       transform_matrix=scene.c2w[i].tolist(), fl_x=K[0, 0], fl_y=K[1, 1],
                       cx=K[0, 2], cy=K[1, 2]))
  with open(os.path.join(d, "scene_meta.json"), "w") as f:
    json.dump(dict(scene_name=name, camera_convention="opencv", frames=frames), f)
  return name, "DSC_0000", "DSC_0001"


def write_tawb(root, scene, split="test", env="Sewerage", pair=7):
  from ufm_jax.data.sources.exr import write_exr
  d = os.path.join(root, split, env)
  for sub in ("images", "depth", "camera_params", "poses"):
    mkdir(d, sub)
  for i in (0, 1):
    n = f"{pair:08d}_{i}"
    write_image(os.path.join(d, "images", n + ".png"), scene.image(i))
    write_exr(os.path.join(d, "depth", n + ".exr"), scene.z_depth(i))
    np.save(os.path.join(d, "camera_params", n + ".npy"), scene.K[i])
    np.save(os.path.join(d, "poses", n + ".npy"), scene.c2w[i])
  return env, f"{pair:08d}_0", f"{pair:08d}_1"


def write_scannet1500(root, scene: PlaneScene, image_hw):
  """SuperGlue's pair list (K at 1296x968) + LoFTR-style color folders at `image_hw`."""
  sy, sx = 968 / image_hw[0], 1296 / image_hw[1]
  T = np.linalg.inv(scene.c2w[1]) @ scene.c2w[0]
  fields = []
  for i in (0, 1):
    K = scene.K[i].copy()
    K[0] *= sx
    K[1] *= sy
    fields.append(K)
  d = os.path.join(root, "scannet_test_1500", "scene0707_00", "color")
  os.makedirs(d)
  for i, f in ((0, 15), (1, 585)):
    write_image(os.path.join(d, f"{f}.jpg"), np.zeros(image_hw + (3,), np.uint8) + 40 * i)
  line = ["scene0707_00_frame-000015.jpg", "scene0707_00_frame-000585.jpg", "0", "0"]
  line += [f"{x:.10f}" for x in np.concatenate([fields[0].ravel(), fields[1].ravel(), T.ravel()])]
  with open(os.path.join(root, "scannet_test_pairs_with_gt.txt"), "w") as f:
    f.write(" ".join(line) + "\n")


def two_view_flow(h=48, w=64):
  """(flow, K, R, t): the dense flow of a smooth depth field seen by two pinhole cameras
  (x1 = R x0 + t), for pose estimation from exact flow."""
  K = np.array([[60.0, 0, w / 2 - 0.5], [0, 58.0, h / 2 - 0.5], [0, 0, 1]])
  ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
  depth = 4 + np.sin(xs / 9) + 0.5 * np.cos(ys / 7)
  rays = np.linalg.inv(K) @ np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)])
  X0 = rays * depth.ravel()
  R = _axis_rot((0, 1, 0), np.radians(6)) @ _axis_rot((1, 0, 0), np.radians(-3))
  t = np.array([0.4, 0.05, 0.1])
  X1 = R @ X0 + t[:, None]
  p1 = (K @ X1)[:2] / X1[2]
  flow = (p1 - np.stack([xs.ravel(), ys.ravel()])).T.reshape(h, w, 2)
  return flow, K, R, t


def _axis_rot(axis, ang):
  axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
  K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


class KubricScene:
  """Static background plane (segmentation id 0) + a moving square patch (id 1) seen by static
  cameras; frame t of the object pose: rotation about its normal and a translation."""

  def __init__(self, hw=(40, 60), num_frames=6, half=0.9):
    self.hw = hw
    h, w = hw
    self.K = [K_of(0.9 * w, 0.9 * w, w / 2 - 0.5, h / 2 - 0.5),
              K_of(0.9 * w, 0.9 * w, w / 2 - 0.5, h / 2 - 0.5)]
    self.c2w = [look_at((0, 0, 0), (0.2, 0.1, 6.0)), look_at((1.4, -0.5, 0.8), (0.1, 0.2, 6.0))]
    self.n = np.array([0.1, -0.05, -1.0])
    self.n /= np.linalg.norm(self.n)
    self.d = float(self.n @ np.array([0, 0, 6.0]))
    self.half = half
    self.num_frames = num_frames

  def obj_pose(self, t):
    T = np.eye(4)
    T[:3, :3] = _axis_rot((0.2, 0.1, 1.0), 0.08 * t) @ _axis_rot((1, 0, 0), np.pi + 0.2)
    T[:3, 3] = (0.15 * t - 0.3, 0.05 * t, 4.0)
    return T

  def cast(self, C, rays, t):
    """Distance along unit world rays to the first hit, and the hit's id."""
    tb = (self.d - self.n @ C) / (rays @ self.n)
    T = self.obj_pose(t)
    no, po = T[:3, 2], T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
      to = ((po - C) @ no) / (rays @ no)
    X = C + rays * to[..., None]
    local = (X - po) @ T[:3, :3]
    on = (to > 0) & (np.abs(local[..., 0]) <= self.half) & (np.abs(local[..., 1]) <= self.half)
    dist = np.where(on & (to < tb), to, tb)
    seg = (on & (to < tb)).astype(np.int32)
    return dist, seg

  def unit_rays(self, v):
    h, w = self.hw
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    rc = np.stack([uu, vv, np.ones_like(uu)], -1) @ np.linalg.inv(self.K[v]).T
    rw = rc @ self.c2w[v][:3, :3].T
    return rw / np.linalg.norm(rw, axis=-1, keepdims=True)

  def render(self, v, t):
    C = self.c2w[v][:3, 3]
    rays = self.unit_rays(v)
    dist, seg = self.cast(C, rays, t)
    X = C + rays * dist[..., None]
    T = self.obj_pose(t)
    local = np.where(seg[..., None] == 1, (X - T[:3, 3]) @ T[:3, :3], X)  # texture moves along
    chans = [np.sin(5.0 * local[..., 0] + 2.0 * local[..., 1]), np.cos(4.0 * local[..., 1]),
             np.sin(3.0 * local[..., 0] * local[..., 1] + seg)]
    img = np.clip(128 + 110 * np.stack(chans, -1), 0, 255).astype(np.uint8)
    return img, dist, seg

  def expected(self, v0, t0, v1, t1):
    C0, C1 = self.c2w[v0][:3, 3], self.c2w[v1][:3, 3]
    rays = self.unit_rays(v0)
    dist, seg = self.cast(C0, rays, t0)
    X = C0 + rays * dist[..., None]
    M = self.obj_pose(t1) @ np.linalg.inv(self.obj_pose(t0))
    Xm = np.where(seg[..., None] == 1, X @ M[:3, :3].T + M[:3, 3], X)
    w2c1 = np.linalg.inv(self.c2w[v1])
    Xc = Xm @ w2c1[:3, :3].T + w2c1[:3, 3]
    uv = Xc[..., :2] / Xc[..., 2:] * np.diag(self.K[v1])[:2] + self.K[v1][:2, 2]
    h, w = self.hw
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    flow = uv - np.stack([uu, vv], -1)
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] < w - 0.5) & (uv[..., 1] >= -0.5) & \
        (uv[..., 1] < h - 0.5) & (Xc[..., 2] > 0)
    r = np.linalg.norm(Xm - C1, axis=-1)
    first, _ = self.cast(C1, (Xm - C1) / r[..., None], t1)
    visible = inside & (first > r - 1e-3)
    # ambiguous: near object outlines in either image, or targets near the image border
    _, seg1 = self.cast(C1, self.unit_rays(v1), t1)
    edge = lambda s: cv2.dilate(s.astype(np.uint8), np.ones((5, 5), np.uint8)) != \
        cv2.erode(s.astype(np.uint8), np.ones((5, 5), np.uint8))
    ti = np.clip(np.rint(uv[..., 1]), 0, h - 1).astype(int)
    tj = np.clip(np.rint(uv[..., 0]), 0, w - 1).astype(int)
    near_border = (uv[..., 0] < 0.5) | (uv[..., 0] > w - 1.5) | (uv[..., 1] < 0.5) | \
        (uv[..., 1] > h - 1.5)
    ambiguous = edge(seg) | (inside & edge(seg1)[ti, tj]) | near_border
    return dict(flow=flow, covis=visible, ambiguous=ambiguous, seg0=seg, inside=inside)


def write_kubric4d(root, scene: KubricScene, name="scn00042", views=2):
  """Kubric's conventions: range depth TIFF, normalised sign-flipped K in a corner-origin frame,
  OpenGL camera-to-world quaternions (w first), palette segmentation PNG."""
  from ufm_jax.data.sources.kubric4d import write_index_png
  h, w = scene.hw
  palette = np.array([[0, 0, 0], [200, 30, 90]] + [[k, k, k] for k in range(2, 256)], np.uint8)
  for v in range(views):
    d = mkdir(root, name, f"frames_p0_v{v}")
    K = scene.K[v]
    Kn = [[-K[0, 0] / w, 0, -(K[0, 2] + 0.5) / w], [0, -K[1, 1] / h, -(K[1, 2] + 0.5) / h],
          [0, 0, -1]]
    R_gl = scene.c2w[v][:3, :3] @ np.diag([1.0, -1.0, -1.0])
    q = rotmat_to_qvec(R_gl)
    inst = dict(positions=[scene.obj_pose(t)[:3, 3].tolist() for t in range(scene.num_frames)],
                quaternions=[rotmat_to_qvec(scene.obj_pose(t)[:3, :3]).tolist()
                             for t in range(scene.num_frames)], asset_id="cube")
    meta = dict(scene=dict(resolution=[w, h], num_frames=scene.num_frames),
                camera=dict(K=Kn, positions=[scene.c2w[v][:3, 3].tolist()] * scene.num_frames,
                            quaternions=[q.tolist()] * scene.num_frames),
                instances=[inst])
    with open(os.path.join(root, name, f"{name}_p0_v{v}.json"), "w") as f:
      json.dump(meta, f)
    for t in range(scene.num_frames):
      img, dist, seg = scene.render(v, t)
      rgba = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], -1)
      assert cv2.imwrite(os.path.join(d, f"rgba_{t:05d}.png"), rgba[..., [2, 1, 0, 3]])
      assert cv2.imwrite(os.path.join(d, f"depth_{t:05d}.tiff"), dist.astype(np.float32))
      write_index_png(os.path.join(d, f"segmentation_{t:05d}.png"), seg, palette)
  return name


def timing_trees(hw):
  """(dataset, writer(root) -> None, get_source kwargs) for a load-time report at size hw."""
  def pairs_file(root, pair, split="train"):
    with open(os.path.join(root, f"pairs_{split}.txt"), "w") as f:
      f.write(" ".join(pair) + "\n")

  def plane(**kw):
    return PlaneScene(hw0=hw, **kw)

  def kub(root):
    name = write_kubric4d(root, KubricScene(hw=hw, num_frames=2))
    pairs_file(root, (name, "0/0", "1/1"))

  return [
      ("blendedmvs", lambda r: write_blendedmvs(r, plane()), {}),
      ("megadepth", lambda r: pairs_file(r, write_megadepth(r, megadepth_scene(
          hw=hw, pre_wh=((hw[1] * 2, hw[0] * 2),) * 2, f=(hw[1] * 1.8, hw[1] * 1.6)))), {}),
      ("tartanair_v2", lambda r: write_tartanair_v2(r, tartanair_scene(hw)), {"strides": (1,)}),
      ("scannetpp", lambda r: pairs_file(r, write_scannetpp(r, plane())), {}),
      ("habitat", lambda r: write_habitat(r, plane()), {}),
      ("staticthings", lambda r: write_staticthings(r, plane()), {}),
      ("kubric4d", kub, {}),
      ("eth3d", lambda r: pairs_file(r, write_eth3d_prepared(r, plane()), "test"), {}),
      ("dtu", lambda r: write_dtu(r, plane()), {}),
      ("tawb", lambda r: write_tawb(r, tartanair_scene(hw)), {}),
  ]


def report_load_times(hw=(420, 560), repeats=5):
  """{dataset: (wall ms, CPU ms)} per sample, single process, for each reader at size hw."""
  import tempfile
  import time
  from ufm_jax import data
  out = {}
  for name, writer, kwargs in timing_trees(hw):
    with tempfile.TemporaryDirectory() as tmp:
      writer(tmp)
      src = data.get_source(name, tmp, **kwargs)
      src[0]
      t, c = time.perf_counter(), time.process_time()
      for _ in range(repeats):
        src[0]
      out[name] = (1e3 * (time.perf_counter() - t) / repeats,
                   1e3 * (time.process_time() - c) / repeats)
  return out


if __name__ == "__main__":
  import sys
  hw = tuple(int(x) for x in sys.argv[1:3]) if len(sys.argv) > 2 else (420, 560)
  for name, (wall, cpu) in report_load_times(hw).items():
    print(f"{name:14s} {hw[1]}x{hw[0]}: {wall:7.1f} ms/sample wall, {cpu:7.1f} ms CPU")
