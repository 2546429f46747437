"""Parameter counts of the released model structures (README: 'Using a released model').

  python benchmarks/param_counts.py

Shapes come from jax.eval_shape of each variant (nothing is allocated); a snapshot's own
config.json is authoritative for the release itself (`ufm_jax.load_official`).
"""

from ufm_jax.training import optim
from ufm_jax.models import ufm, variants

RELEASES = [  # (Hub ID, variant)
    ("infinity1096/UFM-Base", "ufm_base"),
    ("infinity1096/UFM-Refine", "ufm_refine"),
    ("infinity1096/UFM-Base-980", "ufm_base_980"),
    ("infinity1096/UFM-Refine-980", "ufm_refine"),
    ("infinity1096/UFM-Base-DINOv2L-init", "ufm_base_dinov2l_init"),
]


def main():
  print("| Hub ID | variant | parameters |")
  print("|---|---|---|")
  for hub_id, name in RELEASES:
    model = variants.build_model(name)
    n = optim.count_params(ufm.param_shapes(model))["total"]
    print(f"| {hub_id} | `{name}` | {n:,} ({n / 1e9:.2f}B) |")


if __name__ == "__main__":
  main()
