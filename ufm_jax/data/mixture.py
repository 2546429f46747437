"""The training mixtures as `input.datasets` blocks, and where each dataset lives under the data
root.

  from ufm_jax.data import mixture, pipeline
  config.input = pipeline.input_config(mixture.recipe("ufm560"), batch_size=96)

`input.data_root` is the official `root_data_dir` (UFM's preprocess_datasets/README.md): each
dataset is looked for in its official folder and layout first (`LAYOUTS`: the `<name>_processed`
folders, dust3r_data_pairs/, TartanAir/assembled/..., kubric4d/), then in the raw layout our
raw readers take, and `find_layout` says which one it found and why. A per-dataset `root`
(`--config.input.datasets.NAME.root=/path`, relative to data_root unless absolute) skips the
search: that folder must hold one of the two layouts. A dataset with neither folder is dropped
with a warning and the others keep their quotas; a folder that holds neither layout stops the
start-up, naming the files each layout expects.

Samples per epoch: `RECIPES` are the official recipes' quantity options (with the file each
number comes from), `QUOTAS` the paper's Table 1.
"""

from __future__ import annotations

import dataclasses
import glob
import os
from typing import Any, Iterable, Mapping

import ml_collections

# "Pairs in Epoch" of paper Table 1, keyed by the `ufm_jax.data.get_source` names.
QUOTAS = {
    "blendedmvs": 100_000,
    "megadepth": 100_000,
    "tartanair_v2": 100_000,
    "scannetpp": 100_000,
    "habitat": 25_000,
    "staticthings": 10_000,
    "kubric4d": 50_000,
    "flyingthings": 50_000,
    "flyingchairs": 25_000,
    "spring": 25_000,
    "monkaa": 5_000,
    "hd1k": 5_000,
}
ALL = tuple(QUOTAS)
# Table 1's "Wide Baseline" column (Kubric4D is the one dynamic wide-baseline set) ...
WIDE_BASELINE = ("blendedmvs", "megadepth", "tartanair_v2", "scannetpp", "habitat", "staticthings",
                 "kubric4d")
# ... and the small-motion optical-flow sets: the Table 4 "OF" ablation and the 980 bootstrap.
OPTICAL_FLOW = ("flyingthings", "flyingchairs", "spring", "monkaa", "hd1k")

DEFAULT_DATA_ROOT = os.environ.get("UFM_DATA_ROOT", "~/ufm_data")

# ----------------------------------------------------------------------------------------------
# The official recipes' samples per epoch (the `N @ Dataset(...)` terms of train_dataset_str in
# configs/dataset/quantity_options/ of the official train branch, commit d8c421e). Each number
# is drawn per epoch like the official ResizedDataset: every pair floor(N / len) times, the rest
# without replacement (ufm_jax.data.pipeline.draw_quota), from the seed and the epoch.
_OLD = "configs/dataset/quantity_options/train/old_setting_100k.yaml"
_OF = "configs/dataset/quantity_options/train/default.yaml:{key} (via opticalflow_100k.yaml)"
_SP = "configs/dataset/quantity_options/train/static_pinhole_100k.yaml:{key}"
_OPTICAL_FLOW_RECIPE = {
    "flyingthings": (50_000, _OF.format(key="flyingthings_pairs")),
    "flyingchairs": (25_000, _OF.format(key="flyingchairs_pairs")),
    "spring": (25_000, _OF.format(key="spring_pairs")),
    "hd1k": (5_000, _OF.format(key="hd1k_pairs")),
    "monkaa": (5_000, _OF.format(key="monkaa_pairs")),
}
RECIPES: dict[str, dict[str, tuple[int, str]]] = {
    # megatraining_560.sh: dataset=ufm_560_all -> quantity_options/train: old_setting_100k.
    "ufm560": {
        "blendedmvs": (100_000, _OLD), "megadepth": (100_000, _OLD), "scannetpp": (100_000, _OLD),
        "tartanair_v2": (100_000, _OLD + " (TartanairAssembled)"), "kubric4d": (100_000, _OLD),
        "staticthings": (10_000, _OLD), "flyingthings": (50_000, _OLD),
        "habitat": (25_000, _OLD), "flyingchairs": (25_000, _OLD), "spring": (25_000, _OLD),
        "hd1k": (5_000, _OLD), "monkaa": (5_000, _OLD)},
    # megatraining_980.sh and megatraining_refinement_980.sh: dataset=ufm_980_highres ->
    # quantity_options/train: opticalflow_100k, whose numbers are train/default.yaml's.
    "ufm980": _OPTICAL_FLOW_RECIPE,
    "refine980": _OPTICAL_FLOW_RECIPE,
    # megatraining_refinement_560.sh: dataset=static_pinhole -> static_pinhole_100k.
    "refine560": {
        "blendedmvs": (100_000, _SP.format(key="blendedmvs_pairs")),
        "megadepth": (100_000, _SP.format(key="megadepth_pairs")),
        "scannetpp": (100_000, _SP.format(key="scannet_pairs")),
        "staticthings": (10_000, _SP.format(key="static_things_pairs")),
        "habitat": (25_000, _SP.format(key="habitat_pairs"))},
}


def recipe(name: str, names: Iterable[str] | None = None,
           options: Mapping[str, Mapping[str, Any]] | None = None,
           split: str = "train") -> ml_collections.ConfigDict:
  """`input.datasets` of an official recipe (RECIPES), optionally restricted to `names`."""
  if name not in RECIPES:
    raise KeyError(f"unknown recipe {name!r}; known: {sorted(RECIPES)}")
  table = RECIPES[name]
  names = tuple(table) if names is None else tuple(names)
  unknown = [n for n in names if n not in table]
  if unknown:
    raise KeyError(f"recipe {name!r} has no quota for {unknown}; it trains on {list(table)}")
  return mixture(names, {n: table[n][0] for n in names}, options, split)


# ----------------------------------------------------------------------------------------------
# Where each dataset lives under the data root


@dataclasses.dataclass(frozen=True)
class Layout:
  """One on-disk layout of a dataset: the reader registered as `source` takes a folder (one of
  `folders`, relative to the data root) in which every entry of `expect` matches (an entry is a
  tuple of glob alternatives relative to that folder)."""
  kind: str                                  # "official" or "raw"
  source: str
  folders: tuple[str, ...]
  expect: tuple[tuple[str, ...], ...]
  docs: str                                  # where a user reads about it

  def missing(self, folder: str) -> list[str]:
    """The `expect` entries with no match in folder (empty: the folder holds this layout)."""
    out = []
    for alternatives in self.expect:
      if not any(next(glob.iglob(os.path.join(glob.escape(folder), a)), None) is not None
                 for a in alternatives):
        out.append(" or ".join(alternatives))
    return out

  def describe(self) -> str:
    return f"{self.kind} layout ({'; '.join(' or '.join(a) for a in self.expect)}; {self.docs})"


def _deep(*patterns, depth=4):
  """Glob alternatives for a file 1..depth folders below (no recursive `**`: it would walk a
  whole dataset tree before failing)."""
  return tuple(os.path.join(*(["*"] * d), p) for p in patterns for d in range(depth + 1))


_PAIRS = "../dust3r_data_pairs/{f}", "{f}"
LAYOUTS: dict[str, tuple[Layout, ...]] = {
    "blendedmvs": (
        Layout("official", "blendedmvs_official", ("blendedmvs_processed",),
               (("*/*.npz",), ("*/*.exr",),
                tuple(p.format(f="blendedmvs_pairs.npy") for p in _PAIRS)),
               "data/blendedmvs/README.md"),
        Layout("raw", "blendedmvs", ("blendedmvs",),
               (("*/blended_images/*.jpg",), ("*/cams/*_cam.txt",)), "data/blendedmvs/README.md")),
    "megadepth": (
        Layout("official", "megadepth_official", ("megadepth_processed",),
               (("*/*/*.npz",), ("*/*/*.exr",),
                tuple(p.format(f="megadepth_pairs.npz") for p in _PAIRS)),
               "data/megadepth/README.md"),
        Layout("raw", "megadepth", ("megadepth",),
               (("*/dense*/imgs/*",), ("*/dense*/depths/*.h5",)), "data/megadepth/README.md")),
    "scannetpp": (
        Layout("official", "scannetpp_official", ("scannetpp_anymap_processed/train",),
               (("all_metadata.npz",), ("*/images/*.jpg",), ("*/depth/*.png",)),
               "data/scannetpp/README.md"),
        Layout("raw", "scannetpp", ("scannetpp",), (("*/scene_meta.json",),),
               "data/scannetpp/README.md")),
    "tartanair_v2": (
        Layout("official", "tartanair_assembled",
               ("TartanAir/assembled/tartanair_640_mega_training_0328_good",
                "TartanAir/assembled/tartanair_640_mega_training_0203_pinhole_good"),
               (("train/*.h5",), ("train/*.json",)), "data/tartanair_v2/README.md"),
        Layout("raw", "tartanair_v2", ("tartanair_v2",), (("*/Data_*/P*/image_*",),),
               "data/tartanair_v2/README.md")),
    "kubric4d": (
        Layout("official", "kubric4d_official", ("kubric4d",),
               (("kubric4d_metadata/sampled_pairs.npz",), ("kubric4d_metadata/metadata/scn*.npz",),
                ("kubric4d_raw/scn*/frames_p0_v*",)), "data/kubric4d/README.md"),
        Layout("raw", "kubric4d", ("kubric4d",), (("scn*/scn*_p0_v*.json",),),
               "data/kubric4d/README.md")),
    "staticthings": (
        Layout("official", "staticthings_official", ("staticthings3d_processed",),
               (("staticthings_pairs.npy",), ("TRAIN/*/*/*/*.npz",)),
               "data/staticthings/README.md"),
        Layout("raw", "staticthings", ("staticthings",),
               (("frames_*pass/TRAIN",), ("depths/TRAIN",), ("poses/TRAIN",)),
               "data/staticthings/README.md")),
    "habitat": (
        Layout("official", "habitat_official", ("habitat_processed/replica_cad_baked_lighting",),
               (("Habitat_*_scenes_train.txt",), _deep("*_1_camera_params.json")),
               "data/habitat/README.md"),
        Layout("raw", "habitat", ("habitat",), (_deep("*_1.jpeg"),), "data/habitat/README.md")),
    "flyingthings": (
        Layout("official", "flyingthings_official", ("flyingthings3d_processed",),
               (("individual_quantities/train/index.json",), ("flow/train/*.h5",),
                ("flow/train/index.json", "flow/train/job_df.csv")),
               "data/flyingthings/README.md"),
        Layout("raw", "flyingthings", ("flyingthings",),
               (("frames_cleanpass/TRAIN",), ("optical_flow/TRAIN",), ("disparity/TRAIN",)),
               "data/flyingthings/README.md")),
    "monkaa": (
        Layout("official", "monkaa_official", ("monkaa_processed",),
               (("individual_quantities/index.json",), ("flow/*.h5",),
                ("flow/index.json", "flow/job_df.csv")), "data/monkaa/README.md"),
        Layout("raw", "monkaa", ("monkaa",),
               (("frames_cleanpass/*",), ("optical_flow/*",), ("disparity/*",)),
               "data/monkaa/README.md")),
    "flyingchairs": (
        # The official reader is torchvision's: root_data_dir/FlyingChairs (it is handed
        # root_data_dir/flyingchairs and takes its parent), which is our raw reader's layout.
        Layout("official", "flyingchairs", ("FlyingChairs",),
               (("data/*_flow.flo",), ("FlyingChairs_train_val.txt",)),
               "data/flyingchairs/README.md"),
        Layout("raw", "flyingchairs", ("flyingchairs",),
               (("data/*_flow.flo",), ("FlyingChairs_train_val.txt", "chairs_split.txt")),
               "data/flyingchairs/README.md")),
    "spring": (
        Layout("official", "spring_official", ("spring_processed",),
               (("train/*/*/flow/*.npz",), ("train/*/*/images/*.png",)), "data/spring/README.md"),
        Layout("raw", "spring", ("spring",), (("train/*/frame_left",), ("train/*/flow_FW_left",)),
               "data/spring/README.md")),
    "hd1k": (
        Layout("official", "hd1k_official", ("hd1k_processed",), (("*.npz",),),
               "data/hd1k/README.md"),
        Layout("raw", "hd1k", ("hd1k",), (("hd1k_input/image_2",), ("hd1k_flow_gt/flow_occ",)),
               "data/hd1k/README.md")),
}


class LayoutError(ValueError):
  """A dataset folder that holds none of its layouts."""


def find_layout(name: str, data_root: str | None, root: str | None = None):
  """(Layout, folder, why) of dataset `name`, or (None, looked_at, why) when none of its folders
  exists. `root` (absolute, or relative to data_root) is the one folder to look at; else each
  layout's folders under data_root, official first. Raises LayoutError when an existing folder
  holds no layout of the dataset, naming what each layout expects there."""
  layouts = LAYOUTS[name]
  base = os.path.expanduser(str(data_root)) if data_root is not None else None
  if root is not None:
    root = os.path.expanduser(str(root))
    if base is not None and not os.path.isabs(root):
      root = os.path.join(base, root)
    folders = [root]
  else:
    if base is None:
      raise ValueError(f"input.datasets.{name}: no root and no input.data_root to search")
    folders = list(dict.fromkeys(os.path.join(base, f) for l in layouts for f in l.folders))
  present = [f for f in folders if os.path.isdir(f)]
  if not present:
    return None, folders, f"neither {' nor '.join(folders)} exists"
  folder = present[0]   # folders are in preference order: the official ones first
  tried = []
  for layout in layouts:
    missing = layout.missing(folder)
    if not missing:
      if root is not None:
        why = f"{folder} (given as its root) holds the {layout.kind} layout"
      else:
        absent = folders[:folders.index(folder)]
        why = (f"{folder} holds the {layout.kind} layout"
               + (f" ({', '.join(absent)} absent)" if absent else ""))
      return layout, folder, why
    tried.append(f"{layout.describe()}: missing {', '.join(missing)}")
  raise LayoutError(f"dataset {name!r}: {folder} holds none of its layouts; " + " | ".join(tried))


def mixture(names: Iterable[str] = ALL, quotas: Mapping[str, int] | None = None,
            options: Mapping[str, Mapping[str, Any]] | None = None,
            split: str = "train") -> ml_collections.ConfigDict:
  """`input.datasets`: {name: {quota, root, options}} with the paper's Table 1 quotas unless
  `quotas` says otherwise. root is unset for the datasets of LAYOUTS (found under data_root by
  `find_layout`; a string given later is the one folder to read) and the name otherwise
  (relative to data_root)."""
  quotas = {**QUOTAS, **(quotas or {})}
  out = ml_collections.ConfigDict()
  for name in names:
    if name not in quotas:
      raise KeyError(f"no quota for dataset {name!r}; pass quotas={{{name!r}: N}}")
    root = (ml_collections.FieldReference(None, field_type=str) if name in LAYOUTS else name)
    out[name] = ml_collections.ConfigDict({
        "quota": int(quotas[name]), "root": root,
        "options": {"split": split, **dict((options or {}).get(name, {}))}})
  return out


def synthetic_mixture(num_pairs: int = 10_000, size=(112, 112), seed: int = 0,
                      **options) -> ml_collections.ConfigDict:
  """`input.datasets` of the embedded synthetic source alone (rendered on the fly, no files):
  one epoch = `num_pairs` pairs, each rendered at `size` (H, W)."""
  return ml_collections.ConfigDict({"synthetic": {
      "quota": int(num_pairs), "root": None,
      "options": {"split": "train", "num_pairs": int(num_pairs), "size": tuple(size),
                  "seed": int(seed), **options}}})
