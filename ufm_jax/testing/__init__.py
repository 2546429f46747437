"""Helpers the tests and benchmarks share: tiny files and trees written in real on-disk formats
(`wide_trees`: the wide-baseline and benchmark datasets), random weights in official namings."""

from __future__ import annotations

import numpy as np


def hf_dinov2(depth=2, dim=8, grid=3, seed=0):
  """Random weights in the transformers Dinov2Model naming."""
  rng = np.random.default_rng(seed)
  r = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
  sd = {"embeddings.cls_token": r(1, 1, dim), "embeddings.mask_token": r(1, dim),
        "embeddings.position_embeddings": r(1, 1 + grid * grid, dim),
        "embeddings.patch_embeddings.projection.weight": r(dim, 3, 14, 14),
        "embeddings.patch_embeddings.projection.bias": r(dim),
        "layernorm.weight": r(dim), "layernorm.bias": r(dim)}
  for i in range(depth):
    p = f"encoder.layer.{i}."
    for n in ("query", "key", "value"):
      sd[p + f"attention.attention.{n}.weight"] = r(dim, dim)
      sd[p + f"attention.attention.{n}.bias"] = r(dim)
    sd[p + "attention.output.dense.weight"] = r(dim, dim)
    sd[p + "attention.output.dense.bias"] = r(dim)
    for n in ("norm1", "norm2"):
      sd[p + f"{n}.weight"], sd[p + f"{n}.bias"] = r(dim), r(dim)
    sd[p + "layer_scale1.lambda1"], sd[p + "layer_scale2.lambda1"] = r(dim), r(dim)
    sd[p + "mlp.fc1.weight"], sd[p + "mlp.fc1.bias"] = r(4 * dim, dim), r(4 * dim)
    sd[p + "mlp.fc2.weight"], sd[p + "mlp.fc2.bias"] = r(dim, 4 * dim), r(dim)
  return sd
