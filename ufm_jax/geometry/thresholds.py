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
