"""Running a trained model: loading any model path and predicting with it.

  model_io       what a path holds; `ufm_jax.load` (snapshot, converted checkpoint, workdir), our
                 converted-checkpoint format (`convert`)
  checkpoint     orbax checkpoints of a training state: written by training, read back here
  inference      `ufm_jax.predict`: the official resize, forward and region bookkeeping
  outputs        the files `infer` writes per prediction (one suffix table, one writer)
  viz            flow colour wheel, warps, panels
  compile_cache  JAX's persistent compilation cache for the CLI, evaluate.py and predict

Depends on models, official and data only; training, the evaluators and the tools build on it.
"""
