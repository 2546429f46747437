"""UFM-JAX: Unified Flow & Matching in JAX/Flax.

Top-level API (imported lazily so that `import ufm_jax` stays cheap):
  - `load_official(snapshot_dir)`: (model, params) from a Hugging Face snapshot of the PyTorch release.
  - `load(checkpoint_dir)`: (model, params) from a checkpoint written by `python -m ufm_jax convert`.
  - `save_official(model, params, out_dir)`: the inverse of `load_official` (a new HF snapshot).
  - `predict(model, params, source, target)`: the official high-level inference on HWC uint8 images.
  - `match(model, params, source, target)`: sparse matches (keypoints0/1, confidence) in pixels.
  - `load_exported(path)`: a callable over an artifact of `python -m ufm_jax export` (no model code).
  - `read_image(path)`: an image file as HWC uint8 RGB (the project's one image reader).
"""

__version__ = "0.1.0"

_LAZY = {
    "load_official": ("ufm_jax.official.snapshot", "load_official"),
    "load": ("ufm_jax.model_io", "load"),
    "save_official": ("ufm_jax.official.snapshot", "save_official"),
    "predict": ("ufm_jax.inference", "predict"),
    "load_exported": ("ufm_jax.export", "load_exported"),
    "match": ("ufm_jax.matching", "match"),
    "read_image": ("ufm_jax.data.io", "read_image"),
}


def __getattr__(name):
  if name in _LAZY:
    import importlib
    module, attr = _LAZY[name]
    return getattr(importlib.import_module(module), attr)
  raise AttributeError(f"module 'ufm_jax' has no attribute {name!r}")


__all__ = list(_LAZY)
