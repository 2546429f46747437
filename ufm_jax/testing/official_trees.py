"""Tiny dataset trees in the official processed layouts (the `root_data_dir` a user of the UFM
training code has), written in the exact formats the official dataset classes and preprocess
scripts use: file names, npz keys, h5 dataset names, dtypes (little-endian), EXR depth.

Static datasets store the two-view plane scene of `wide_trees.PlaneScene` in each dataset's
conventions (Habitat's corner-origin principal point, Kubric's normalised sign-flipped K and
Blender axes, ScanNet++'s millimetre PNG depth), so a reader that gets a convention wrong gives
labels that disagree with the scene's closed-form homography (`wide_trees.check_plane_sample`).
Flow datasets store smooth textures, flow fields (with NaN / invalid regions where the format
has them) and distinct mask patterns; `FLOW_CONTENT[name]` keeps what was written so tests
compare what a reader returns with it.

  write_official_root(root, hw)   every dataset of the official 560 recipe under one data root
"""

from __future__ import annotations

import json
import os

import h5py
import numpy as np

from ufm_jax.data import io
from ufm_jax.data.sources import exr
from ufm_jax.testing import wide_trees as wide

BLENDED_SEQ = wide.BLENDED_SCENE            # seq_low % 10 != 0: train split
BLENDED_VAL_SEQ = "5a3cb4e4270f0e3f14d12f3a"  # seq_low % 10 == 0: val split
BLENDED_PAIRS_DTYPE = [("seq_high", "<u4"), ("seq_low", "<u8"), ("img1", "<u4"), ("img2", "<u4"),
                       ("score", "<f4")]
TAWB_FOLDER = "TartanAir/assembled/tartanair_640_mega_training_0328_good"


def texture(hw, seed) -> np.ndarray:
  """Smooth colour texture (H, W, 3) uint8."""
  h, w = hw
  v, u = np.mgrid[0:h, 0:w].astype(np.float32)
  a = np.random.default_rng(seed).uniform(0.05, 0.3, 6).astype(np.float32)
  chans = [np.sin(a[0] * u + a[1] * v), np.cos(a[2] * u - a[3] * v), np.sin(a[4] * u * a[5] * v)]
  return np.clip(128 + 110 * np.stack(chans, -1), 0, 255).astype(np.uint8)


def flow_field(hw, seed) -> np.ndarray:
  """Smooth flow (H, W, 2) float32 of a few pixels."""
  h, w = hw
  v, u = np.mgrid[0:h, 0:w].astype(np.float32)
  a = np.random.default_rng(seed).uniform(-1, 1, 4).astype(np.float32)
  return np.stack([3 * a[0] + 0.05 * a[1] * u, 2 * a[2] + 0.05 * a[3] * v], -1).astype(np.float32)


def mask(hw, seed, p=0.7) -> np.ndarray:
  return np.random.default_rng(seed).random(hw) < p


def flow_labels(hw, seed) -> dict:
  """One view's precomputed labels: flow (H, W, 2), the three masks."""
  return dict(flow=flow_field(hw, seed), non_occluded_mask=mask(hw, seed + 1),
              occlusion_supervision_mask=mask(hw, seed + 2, 0.9), fov_mask=mask(hw, seed + 3, 0.95))


# ------------------------------------------------------------------------------- static datasets

def _save_npz(path, **arrays):
  np.savez(path, **arrays)


def write_blendedmvs(data_root, scene: wide.PlaneScene | None = None):
  """blendedmvs_processed/<seq>/%08d.{jpg,exr,npz} + dust3r_data_pairs/blendedmvs_pairs.npy:
  pairs (0, 1) and (1, 0) of the train sequence, one of a val sequence, one of an excluded one."""
  scene = scene or wide.PlaneScene()
  d = wide.mkdir(data_root, "blendedmvs_processed", BLENDED_SEQ)
  wide.mkdir(data_root, "blendedmvs_processed", BLENDED_VAL_SEQ)
  for i in (0, 1):
    stem = os.path.join(d, f"{i:08d}")
    wide.write_image(stem + ".jpg", scene.image(i))
    exr.write_exr(stem + ".exr", scene.z_depth(i).astype(np.float32))
    _save_npz(stem + ".npz", intrinsics=scene.K[i].astype(np.float32),
              R_cam2world=scene.c2w[i][:3, :3].astype(np.float64),
              t_cam2world=scene.c2w[i][:3, 3].astype(np.float32))
  rows = [(BLENDED_SEQ, 0, 1, 0.9), (BLENDED_SEQ, 1, 0, 0.8), (BLENDED_VAL_SEQ, 0, 1, 0.5),
          ("00000000000000000000000c", 0, 1, 0.4)]   # officially excluded (a train seq_low)
  pairs = np.array([(int(s[:8], 16), int(s[8:], 16), a, b, c) for s, a, b, c in rows],
                   dtype=BLENDED_PAIRS_DTYPE)
  np.save(os.path.join(wide.mkdir(data_root, "dust3r_data_pairs"), "blendedmvs_pairs.npy"), pairs)
  return scene


def write_megadepth(data_root, scene: wide.PlaneScene | None = None):
  """megadepth_processed/<0001|0015>/0/img<i>.{jpg,exr,npz} + dust3r_data_pairs/
  megadepth_pairs.npz (scenes "0001 0", "0015 0" (val), images without extension, structured
  pairs); both scenes hold the same two views (the official class reads val scenes too)."""
  scene = scene or wide.PlaneScene()
  for name in ("0001", "0015"):
    d = wide.mkdir(data_root, "megadepth_processed", name, "0")
    for i in (0, 1):
      stem = os.path.join(d, f"img{i}")
      wide.write_image(stem + ".jpg", scene.image(i))
      exr.write_exr(stem + ".exr", scene.z_depth(i).astype(np.float32))
      _save_npz(stem + ".npz", intrinsics=scene.K[i].astype(np.float32),
                cam2world=scene.c2w[i].astype(np.float32))
  pairs = np.array([(0, 0, 1, 0.7), (1, 0, 1, 0.6), (0, 1, 0, 0.5)],
                   dtype=[("scene_id", "<u4"), ("im1_id", "<u4"), ("im2_id", "<u4"),
                          ("score", "<f4")])
  _save_npz(os.path.join(wide.mkdir(data_root, "dust3r_data_pairs"), "megadepth_pairs.npz"),
            scenes=np.array(["0001 0", "0015 0"]), images=np.array(["img0", "img1"]), pairs=pairs)
  return scene


def write_scannetpp(data_root, scene: wide.PlaneScene | None = None, name="0a5c013435"):
  """scannetpp_anymap_processed/train/{all_metadata.npz, <scene>/images/*.jpg,
  <scene>/depth/*.png (uint16 mm)}; pairs [(0, 1), (1, 0), (0, 1)]: the first two are train."""
  scene = scene or wide.PlaneScene()
  root = wide.mkdir(data_root, "scannetpp_anymap_processed", "train")
  wide.mkdir(root, name, "images"), wide.mkdir(root, name, "depth")
  names = ["DSC00000", "DSC00001"]
  for i, n in enumerate(names):
    wide.write_image(os.path.join(root, name, "images", n + ".jpg"), scene.image(i))
    io.write_png_depth16(os.path.join(root, name, "depth", n + ".png"), scene.z_depth(i), 1000.0)
  _save_npz(os.path.join(root, "all_metadata.npz"), counts=np.array([0]), scenes=np.array([name]),
            sceneids=np.array([0, 0]), images=np.array(names),
            intrinsics=np.stack(scene.K).astype(np.float64),
            trajectories=np.stack(scene.c2w).astype(np.float64),
            pairs=np.array([[0, 1], [1, 0], [0, 1]], np.int64))
  return scene


def write_staticthings(data_root, scene: wide.PlaneScene | None = None, letter="A", seq=42,
                       frames=(("l", 6), ("r", 7))):
  """staticthings3d_processed/{staticthings_pairs.npy, TRAIN/<A>/<seq>/<cam>/%04d_{clean,final}.jpg,
  %04d.exr, %04d.npz}; the final pass is the clean one 40 grey levels darker."""
  scene = scene or wide.PlaneScene()
  root = wide.mkdir(data_root, "staticthings3d_processed")
  cams = {"l": "left", "r": "right"}
  for i, (cam, idx) in enumerate(frames):
    d = wide.mkdir(root, "TRAIN", letter, f"{seq:04d}", cams[cam])
    img = scene.image(i)
    wide.write_image(os.path.join(d, f"{idx:04d}_clean.jpg"), img)
    wide.write_image(os.path.join(d, f"{idx:04d}_final.jpg"),
         np.clip(img.astype(int) - 40, 0, 255).astype(np.uint8))
    exr.write_exr(os.path.join(d, f"{idx:04d}.exr"), scene.z_depth(i).astype(np.float32))
    _save_npz(os.path.join(d, f"{idx:04d}.npz"), intrinsics=scene.K[i].astype(np.float32),
              cam2world=scene.c2w[i].astype(np.float32))
  (c1, i1), (c2, i2) = frames
  pairs = np.array([(letter.encode(), seq, c1.encode(), i1, c2.encode(), i2)],
                   dtype=[("scene", "S1"), ("seq", "<u2"), ("cam1", "S1"), ("im1", "<u2"),
                          ("cam2", "S1"), ("im2", "<u2")])
  np.save(os.path.join(root, "staticthings_pairs.npy"), pairs)
  return scene


def write_habitat(data_root, scene: wide.PlaneScene | None = None, path="apt_0", key="000123"):
  """habitat_processed/replica_cad_baked_lighting/{Habitat_35000_scenes_train.txt,
  <path>/<key>_<i>.jpeg, _depth.exr (float16), _camera_params.json}; view 1 = scene view 0,
  views 2..5 = scene view 1; the principal point is stored +0.5 (the official subtracts it)."""
  scene = scene or wide.PlaneScene()
  root = wide.mkdir(data_root, "habitat_processed", "replica_cad_baked_lighting")
  d = wide.mkdir(root, path)
  for i in range(1, 6):
    view = 0 if i == 1 else 1
    wide.write_image(os.path.join(d, f"{key}_{i}.jpeg"), scene.image(view))
    exr.write_exr(os.path.join(d, f"{key}_{i}_depth.exr"), scene.z_depth(view), half=True)
    K = scene.K[view].copy()
    K[:2, 2] += 0.5
    with open(os.path.join(d, f"{key}_{i}_camera_params.json"), "w") as f:
      json.dump(dict(camera_intrinsics=K.tolist(), R_cam2world=scene.c2w[view][:3, :3].tolist(),
                     t_cam2world=scene.c2w[view][:3, 3].tolist()), f)
  with open(os.path.join(root, "Habitat_35000_scenes_train.txt"), "w") as f:
    f.write(f"{path}/{key}\n")
  return scene


def write_kubric4d(data_root, scene: wide.KubricScene | None = None, seq=42):
  """kubric4d/{kubric4d_raw/scn%05d/frames_p0_v<v>/..., kubric4d_metadata/{sampled_pairs.npz,
  metadata/scn%05d.npz}}; the metadata K is what the official formula turns into scene.K."""
  scene = scene or wide.KubricScene(num_frames=4)
  base = wide.mkdir(data_root, "kubric4d")
  name = f"scn{seq:05d}"
  wide.write_kubric4d(wide.mkdir(base, "kubric4d_raw"), scene, name=name, views=2)
  h, w = scene.hw
  flip = np.diag([1.0, -1.0, -1.0])
  intr, extr = [], []
  for v in (0, 1):
    intr.append((scene.K[v] @ flip) / np.array([w, h, 1.0])[:, None])
    T = scene.c2w[v].copy()
    T[:3, :3] = T[:3, :3] @ flip
    extr.append(T)
  frames = range(scene.num_frames)
  pos = np.array([[[scene.obj_pose(t)[:3, 3] for t in frames]]] * 2)
  quat = np.array([[[wide.rotmat_to_qvec(scene.obj_pose(t)[:3, :3]) for t in frames]]] * 2)
  _save_npz(os.path.join(wide.mkdir(base, "kubric4d_metadata", "metadata"), f"{name}.npz"),
            intrinsics=np.array(intr, np.float64), extrinsics=np.array(extr, np.float64),
            positions=np.array([[c[:3, 3]] * scene.num_frames for c in extr]),
            orientations=np.array([[wide.rotmat_to_qvec(c[:3, :3])] * scene.num_frames
                                   for c in extr]),
            instances_position_scene=pos, instances_orientation_scene=quat)
  _save_npz(os.path.join(base, "kubric4d_metadata", "sampled_pairs.npz"),
            train_pairs=np.array([[seq, 0, 1, 0, 2], [seq, 1, 0, 3, 1]], np.int64),
            test_pairs=np.array([[seq, 0, 1, 1, 1]], np.int64))
  return scene


# --------------------------------------------------------------------------------- flow datasets

FLOW_CONTENT: dict[str, dict] = {}   # what the writers below stored, for the tests


def write_h5(path, **arrays):
  """Datasets chunked by row, gzip: as the official preprocess writes them."""
  with h5py.File(path, "w") as f:
    for k, v in arrays.items():
      f.create_dataset(k, data=v, chunks=(1,) + v.shape[1:], compression="gzip")


def write_sceneflow(data_root, dataset="flyingthings", hw=(30, 40), frames=(6, 7, 8),
                    flow_index=False, flow_layout="hwc"):
  """flyingthings3d_processed/{individual_quantities,flow}/train/ (Monkaa: monkaa_processed/
  {individual_quantities,flow}/ with seq = a scene name) as the official preprocess writes them:
  one `<a>_<b>.h5` per folder, index.json for the frames, job_df.csv (+ index.json if
  `flow_index`) for the pairs. Frame k's clean image is texture(seed 10k), final seed 10k + 5,
  right camera + 100. flow_layout 'hwc' = (N, H, W, 2) (what the preprocess writes), 'chw' =
  (N, 2, H, W)."""
  ft = dataset == "flyingthings"
  root = wide.mkdir(data_root, "flyingthings3d_processed" if ft else "monkaa_processed")
  sub = ("train",) if ft else ()
  iq, fl = wide.mkdir(root, "individual_quantities", *sub), wide.mkdir(root, "flow", *sub)
  seq = 0 if ft else "a_rain_of_stones_x2"
  lead = {"split": "TRAIN", "division": "A"} if ft else {}
  n = len(frames)
  images = {(c, p): np.stack([texture(hw, 10 * k + (5 if p == "final" else 0)
                                      + (100 if c == "right" else 0)) for k in frames])
            for c in ("left", "right") for p in ("clean", "final")}
  arrays = {f"frame_{p}pass_{c}": v for (c, p), v in images.items()}
  for c in ("left", "right"):
    arrays[f"depth_{c}"] = np.full((n,) + hw, 5.0, np.float32)
    arrays[f"intrinsics_{c}"] = np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
    arrays[f"pose_{c}"] = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
  write_h5(os.path.join(iq, f"0_{n - 1}.h5"), **arrays)
  with open(os.path.join(iq, "index.json"), "w") as f:
    json.dump({str(i): {"file_name": f"0_{n - 1}.h5", "file_index": i, **lead, "seq": seq,
                        "idx": k} for i, k in enumerate(frames)}, f)
  labels, flow_arrays = {}, {}
  for c in ("left", "right"):
    for v in (0, 1):
      per = [flow_labels(hw, 1000 * i + 10 * v + (500 if c == "right" else 0))
             for i in range(n - 1)]
      labels[(c, v)] = per
      for q in per[0]:
        stack = np.stack([p[q] for p in per])
        if q == "flow" and flow_layout == "chw":
          stack = np.ascontiguousarray(np.moveaxis(stack, -1, 1))
        flow_arrays[f"{c}_view{v}_{q}"] = stack
  write_h5(os.path.join(fl, f"0_{n - 2}.h5"), **flow_arrays)
  rows = [{**lead, "seq": seq, "pair0_id": a, "pair1_id": b} for a, b in zip(frames, frames[1:])]
  with open(os.path.join(fl, "job_df.csv"), "w") as f:
    cols = list(rows[0])
    f.write("," + ",".join(cols) + "\n")
    for i, r in enumerate(rows):
      f.write(f"{i}," + ",".join(str(r[c]) for c in cols) + "\n")
  if flow_index:
    with open(os.path.join(fl, "index.json"), "w") as f:
      json.dump({str(i): {"file_name": f"0_{n - 2}.h5", "file_index": i, **r}
                 for i, r in enumerate(rows)}, f)
  FLOW_CONTENT[dataset] = dict(images=images, labels=labels, root=root)
  return root


def write_spring(data_root, hw=(30, 40), seqs=("0001", "0040")):
  """spring_processed/<train|test>/<seq>/<left|right>/{images/%04d.png, flow/0001_0002.npz};
  sequences 38 and up go to test/ as the preprocess does. 2% of the forward flow is NaN and
  the masks of both views are cleared there (the preprocess's NaN handling)."""
  root = wide.mkdir(data_root, "spring_processed")
  content = {}
  for s in seqs:
    split = "train" if int(s) < 38 else "test"
    for ci, cam in enumerate(("left", "right")):
      d = wide.mkdir(root, split, s, cam)
      imgs = [texture(hw, 7 * int(s) + 3 * ci + k) for k in (0, 1)]
      for k, img in zip((1, 2), imgs):
        io.write_image(os.path.join(wide.mkdir(d, "images"), f"{k:04d}.png"), img)
      views = [flow_labels(hw, 300 * int(s) + 30 * ci + 5 * v) for v in (0, 1)]
      nan = np.random.default_rng(int(s) + ci).random(hw) < 0.02
      views[0]["flow"][nan] = np.nan
      for v in views:
        for q in ("non_occluded_mask", "occlusion_supervision_mask", "fov_mask"):
          v[q] = v[q] & ~nan
      arrays = {f"{q}_{i}": (np.ascontiguousarray(np.moveaxis(v[q], -1, 0)) if q == "flow"
                             else v[q]) for i, v in enumerate(views) for q in v}
      _save_npz(os.path.join(wide.mkdir(d, "flow"), "0001_0002.npz"), **arrays)
      content[(split, s, cam)] = dict(images=imgs, views=views)
  FLOW_CONTENT["spring"] = content
  return root


def write_hd1k(data_root, hw=(30, 40), n=2):
  """hd1k_processed/%04d.npz: img0, img1 uint8, flow (2, H, W) float32, valid bool."""
  root = wide.mkdir(data_root, "hd1k_processed")
  content = []
  for i in range(n):
    z = dict(img0=texture(hw, 40 + i), img1=texture(hw, 50 + i),
             flow=np.ascontiguousarray(np.moveaxis(flow_field(hw, 60 + i), -1, 0)),
             valid=mask(hw, 70 + i))
    _save_npz(os.path.join(root, f"{i:04d}.npz"), **z)
    content.append(z)
  FLOW_CONTENT["hd1k"] = content
  return root


def write_tawb(data_root, hw=(32, 32), flow_dtype=np.float32):
  """TartanAir/assembled/tartanair_640_mega_training_0328_good/train/: shard_0_1.h5 (pairs 0, 1;
  list-form index json), shard_2_2.h5 (pair 2; dict-form index json) and match_errors.json
  (holds forward_match_errors, and an entry 0 -> a file that does not exist: not an index)."""
  d = wide.mkdir(data_root, TAWB_FOLDER, "train")
  pairs = []
  for i in range(3):
    views = [flow_labels(hw, 800 + 10 * i + v) for v in (0, 1)]
    pairs.append(dict(img0=texture(hw, 900 + i), img1=texture(hw, 950 + i), views=views))
  for name, idx in (("shard_0_1", (0, 1)), ("shard_2_2", (2,))):
    arrays = dict(img0=np.stack([pairs[i]["img0"] for i in idx]),
                  img1=np.stack([pairs[i]["img1"] for i in idx]))
    for v, tag in ((0, "fwd"), (1, "bwd")):
      arrays[f"flow_{tag}"] = np.stack([np.moveaxis(pairs[i]["views"][v]["flow"], -1, 0)
                                        for i in idx]).astype(flow_dtype)
      for q, stem in (("non_occluded_mask", "non_occluded"),
                      ("occlusion_supervision_mask", "occlusion_supervision_mask"),
                      ("fov_mask", "fov_mask")):
        arrays[f"{stem}_{tag}"] = np.stack([pairs[i]["views"][v][q] for i in idx])
    write_h5(os.path.join(d, name + ".h5"), **arrays)
  with open(os.path.join(d, "shard_0_1.json"), "w") as f:
    json.dump({"0": ["shard_0_1.h5", 0], "1": ["shard_0_1.h5", 1]}, f)
  with open(os.path.join(d, "shard_2_2.json"), "w") as f:
    json.dump({"2": {"file_name": "shard_2_2.h5", "file_index": 0}}, f)
  with open(os.path.join(d, "match_errors.json"), "w") as f:
    json.dump({"forward_match_errors": [0.1, 0.2, 0.3], "0": ["nonexistent.h5", 0]}, f)
  FLOW_CONTENT["tartanair_v2"] = pairs
  return os.path.join(data_root, TAWB_FOLDER)


def write_flyingchairs(data_root, hw=(30, 40), n=3):
  """FlyingChairs/{data/%05d_img1.ppm, _img2.ppm, _flow.flo, FlyingChairs_train_val.txt} (the
  torchvision layout the official reader takes); pair 2 is in the val split."""
  root = wide.mkdir(data_root, "FlyingChairs")
  d = wide.mkdir(root, "data")
  for i in range(1, n + 1):
    for j in (1, 2):
      img = texture(hw, 20 * i + j)
      with open(os.path.join(d, f"{i:05d}_img{j}.ppm"), "wb") as f:
        f.write(f"P6\n{hw[1]} {hw[0]}\n255\n".encode() + img.tobytes())
    io.write_flo(os.path.join(d, f"{i:05d}_flow.flo"), flow_field(hw, 20 * i))
  with open(os.path.join(root, "FlyingChairs_train_val.txt"), "w") as f:
    f.write("".join("2\n" if i == 2 else "1\n" for i in range(1, n + 1)))
  return root


# ------------------------------------------------------------------------------------ everything

# Frame sizes (H, W) the official processed files have (preprocess outputs, native renders).
NATIVE = {"flyingthings": (540, 960), "monkaa": (540, 960), "spring": (560, 926),
          "hd1k": (560, 1330), "tartanair_v2": (640, 640), "flyingchairs": (384, 512)}


# Each dataset's folder under its data root, as the official layout names it (mixture.LAYOUTS).
FOLDERS = {"blendedmvs": "blendedmvs_processed", "megadepth": "megadepth_processed",
           "scannetpp": "scannetpp_anymap_processed/train",
           "staticthings": "staticthings3d_processed",
           "habitat": "habitat_processed/replica_cad_baked_lighting", "kubric4d": "kubric4d",
           "tartanair_v2": TAWB_FOLDER, "flyingthings": "flyingthings3d_processed",
           "monkaa": "monkaa_processed", "spring": "spring_processed", "hd1k": "hd1k_processed",
           "flyingchairs": "FlyingChairs"}


def write_official_dataset(data_root, name, hw=(36, 48)) -> str:
  """Dataset `name` of the official recipes in its official layout under `data_root`, at hw
  (TA-WB square at hw[1]). -> its folder, relative to data_root."""
  plane = wide.PlaneScene(hw0=tuple(hw))
  writers = {
      "blendedmvs": lambda: write_blendedmvs(data_root, plane),
      "megadepth": lambda: write_megadepth(data_root, plane),
      "scannetpp": lambda: write_scannetpp(data_root, plane),
      "staticthings": lambda: write_staticthings(data_root, plane),
      "habitat": lambda: write_habitat(data_root, plane),
      "kubric4d": lambda: write_kubric4d(data_root, wide.KubricScene(hw=tuple(hw), num_frames=4)),
      "tartanair_v2": lambda: write_tawb(data_root, (hw[1], hw[1])),
      "flyingthings": lambda: write_sceneflow(data_root, "flyingthings", tuple(hw)),
      "monkaa": lambda: write_sceneflow(data_root, "monkaa", tuple(hw)),
      "spring": lambda: write_spring(data_root, tuple(hw)),
      "hd1k": lambda: write_hd1k(data_root, tuple(hw)),
      "flyingchairs": lambda: write_flyingchairs(data_root, tuple(hw))}
  if name not in writers:
    raise KeyError(f"no official-layout writer for dataset {name!r}; known: {sorted(writers)}")
  writers[name]()
  return FOLDERS[name]


def write_official_root(data_root, hw=(36, 48), sizes=None) -> dict[str, str]:
  """Every dataset of the official 560 recipe in its official layout under `data_root`, at hw
  (TA-WB square at hw[1]) or at `sizes[name]` (e.g. NATIVE). -> {mixture name: folder}."""
  sizes = dict(sizes or {})
  return {name: write_official_dataset(data_root, name, sizes.get(name, hw)) for name in FOLDERS}
