"""Depth reprojection thresholds (tau_d absolute, tau_r relative) per dataset: supplementary
Table S1, keyed by the lower-case names used by `ufm_jax.data.get_source`.

Datasets whose covisibility is provided by the dataset (Spring, HD1K, Sintel, KITTI) or
approximated by the FoV mask (FlyingChairs) have no entry.
"""

COVIS_THRESHOLDS = {
    # Static scenes: unprojected depth across cameras.
    "blendedmvs": (0.1, 0.005),
    "megadepth": (0.1, 0.005),
    "tartanair_v2": (0.1, 0.01),
    "scannetpp": (0.1, 0.005),
    "habitat": (0.1, 0.005),
    # Not in Table S1 (the paper lists StaticThings as a static scene in Table 1 only): we use the
    # static-scene value shared by 4 of the 5 rows, which is also tartanairpy's default.
    "staticthings": (0.1, 0.005),
    # Optical flow with scene flow (flow + disparity change) + reprojection threshold.
    "flyingthings": (0.01, 0.001),
    "monkaa": (0.01, 0.001),
    # Rigid posed objects.
    "kubric4d": (0.1, 0.005),
    # The embedded synthetic generator (not a paper dataset): scene units are metres-like, depths
    # 1..~20, so the static-scene value.
    "synthetic": (0.1, 0.005),
}

# Aliases readers may register under.
COVIS_THRESHOLDS["tartanair"] = COVIS_THRESHOLDS["tartanair_v2"]
COVIS_THRESHOLDS["ta_wb"] = COVIS_THRESHOLDS["tartanair_v2"]
COVIS_THRESHOLDS["scannetpp_v2"] = COVIS_THRESHOLDS["scannetpp"]
COVIS_THRESHOLDS["kubric"] = COVIS_THRESHOLDS["kubric4d"]
COVIS_THRESHOLDS["static_things"] = COVIS_THRESHOLDS["staticthings"]


# The benchmark sets, which Table S1 does not list: the static-scene values in the units each
# reader returns (metres for DTU and ETH3D; TA-WB is TartanAir geometry: the TartanAir row).
BENCH_THRESHOLDS = {"eth3d": (0.1, 0.005), "dtu": (0.01, 0.005), "tawb": (0.1, 0.01),
                    "scannet1500": (0.1, 0.005)}


def covis_thresholds(name: str) -> tuple[float, float]:
  """(tau_d, tau_r) for a dataset name: Table S1 first, then the benchmark values; an error
  lists the known names."""
  key = name.lower()
  table = {**BENCH_THRESHOLDS, **COVIS_THRESHOLDS}
  if key not in table:
    raise KeyError(f"no covisibility thresholds for dataset {name!r}; known: "
                   f"{', '.join(sorted(table))}")
  return tuple(table[key])


# The official training code's `covisible_rendering_parameters` (absolute, temperature, relative):
# covisible iff |sampled range - r| < absolute + relative * r - ln(0.5) * temperature
# (`ufm_jax.geometry.official_labels`). Official sources on the train branch (d8c421e):
RENDERING_PARAMETERS = {
    # uniflowmatch/datasets/<name>.py: blendedmvs.py:104, megadepth.py:107, scannetpp.py:81,
    # habitat.py:83, staticthings3d.py:75 (hypersim.py:143 has the same value).
    "blendedmvs": (0.1, 0.1, 0.005),
    "megadepth": (0.1, 0.1, 0.005),
    "scannetpp": (0.1, 0.1, 0.005),
    "habitat": (0.1, 0.1, 0.005),
    "staticthings": (0.1, 0.1, 0.005),
    # flow_postprocessing.py:308-314: the Kubric pathway passes these as function arguments.
    "kubric4d": (0.1, 0.1, 0.005),
    # preprocess_flyingthings.py:428-434, preprocess_monkaa.py:395-401: on z-depth, not range
    # (`ufm_jax.geometry.sceneflow`).
    "flyingthings": (0.01, 0.01, 0.001),
    "monkaa": (0.01, 0.01, 0.001),
    # Not official: the official TartanAir set (TA-WB training shards) ships its labels. Ours are
    # made from the raw TartanAir V2 depth with Table S1's (0.1, 0.01) plus the official
    # temperature term.
    "tartanair_v2": (0.1, 0.1, 0.01),
    # The embedded synthetic generator (not a paper dataset): the static-scene value.
    "synthetic": (0.1, 0.1, 0.005),
}
RENDERING_PARAMETERS["kubric"] = RENDERING_PARAMETERS["kubric4d"]
RENDERING_PARAMETERS["tartanair"] = RENDERING_PARAMETERS["tartanair_v2"]
RENDERING_PARAMETERS["scannetpp_v2"] = RENDERING_PARAMETERS["scannetpp"]
RENDERING_PARAMETERS["static_things"] = RENDERING_PARAMETERS["staticthings"]


def rendering_parameters(name: str) -> tuple[float, float, float] | None:
  """(absolute, temperature, relative) of a training dataset (`RENDERING_PARAMETERS`), or None
  for a dataset the official training code does not label from depth (benchmarks, flow sets)."""
  p = RENDERING_PARAMETERS.get(name.lower())
  return None if p is None else tuple(p)
