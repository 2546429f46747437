"""UFM-JAX: Unified Flow & Matching in JAX/Flax.

Top-level API (imported lazily so that `import ufm_jax` stays cheap). Every loader returns the
model and its Flax variables {"params"[, "batch_stats"]}: `model.apply(variables, source, target)`.
  - `load_official(snapshot)`: (model, variables) from a Hugging Face snapshot of the PyTorch
    release (a folder or a Hub ID).
  - `load(path)`: (model, variables) from whatever a command's --checkpoint takes: a converted
    checkpoint (`python -m ufm_jax convert`), a train.py workdir, a snapshot folder (a Hub ID with
    snapshot=True).
  - `save_official(model, variables, out_dir)`: the inverse of `load_official` (a new HF snapshot).
  - `predict(model, variables, source, target)`: the official high-level inference on HWC uint8
    images.
  - `match(model, variables, source, target)`: sparse matches (keypoints0/1, confidence) in pixels.
  - `load_exported(path)`: a callable over an artifact of `python -m ufm_jax export` (no model code).
  - `read_image(path)`: an image file as HWC uint8 RGB (the project's one image reader).
"""

__version__ = "0.1.0"

_LAZY = {
    "load_official": ("ufm_jax.official.snapshot", "load_official"),
    "load": ("ufm_jax.runtime.model_io", "load_model"),
    "save_official": ("ufm_jax.official.snapshot", "save_official"),
    "predict": ("ufm_jax.runtime.inference", "predict"),
    "load_exported": ("ufm_jax.tools.export", "load_exported"),
    "match": ("ufm_jax.tools.matching", "match"),
    "read_image": ("ufm_jax.data.io", "read_image"),
}


def __getattr__(name):
  if name in _LAZY:
    import importlib
    module, attr = _LAZY[name]
    return getattr(importlib.import_module(module), attr)
  raise AttributeError(f"module 'ufm_jax' has no attribute {name!r}")


__all__ = list(_LAZY)
