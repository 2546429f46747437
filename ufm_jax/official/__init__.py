"""The official PyTorch UFM format (UniCeption modules, Hugging Face snapshots):

  keymap.py    torch state-dict names and layouts <-> Flax param paths and arrays
  config.py    official config.json <-> our model configs; the registry of official classes
  snapshot.py  `load_official(snapshot)` -> (model, variables); `save_official` writes one back
  dinov2_weights.py  released DINOv2 weights (Hub safetensors, original .pth) as encoder params

    model, variables = ufm_jax.load_official("path/to/UFM-Base")   # a snapshot folder
    ufm_jax.save_official(model, variables, "path/to/export")       # a new snapshot + model card

Our own checkpoint format (`python -m ufm_jax convert`) is `ufm_jax.runtime.model_io`. The names below
are imported on first use, so that importing the key map alone stays cheap.
"""

_LAZY = {
    "load_official": "snapshot", "save_official": "snapshot", "read_snapshot": "snapshot",
    "expected_param_shapes": "snapshot", "official_spec": "config",
    "register_official_class": "config", "official_config_dict": "config",
    "class_name": "config",
}


def __getattr__(name):
  if name in _LAZY:
    import importlib
    return getattr(importlib.import_module(f"ufm_jax.official.{_LAZY[name]}"), name)
  raise AttributeError(f"module 'ufm_jax.official' has no attribute {name!r}")


__all__ = list(_LAZY)
