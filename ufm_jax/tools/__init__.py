"""The tools people use UFM through: `python -m ufm_jax infer|export|match|demo|convert|...`.

  cli       the command line (only ufm_jax.__main__ imports it)
  sequence  folders of frames, pair lists and videos through batched predict
  matching  sparse matches from dense flow + covisibility (`ufm_jax.match`), drawing
  export    jax.export / ONNX artifacts and `ufm_jax.load_exported`
  demo      the local Gradio page

The top floor: built on runtime, the evaluators' metrics, official, data and models.
"""
