"""Local demo page: `python -m ufm_jax demo --checkpoint DIR [--snapshot] [--port 7860]`
(`serve(model, variables, ...)` from Python).

A Gradio app (the optional `[demo]` extra): upload two images (or pick the generated example
pair) and see the flow in the Middlebury colour wheel, the covisibility, the target warped into
the source and sampled matches drawn as lines, and for a model with a flow covariance its
uncertainty (sigma_max in px on a fixed log scale with a legend, `viz.uncertainty_view`); a
slider sets the covisibility threshold (pixels below it are greyed out and never matched) and the
matches download as the `.npz` that `python -m ufm_jax match` writes (with a covariance: each
match's covariance and precision, most certain first). The forward pass is `ufm_jax.predict` (one jitted forward per
inference shape); a changed threshold re-samples the cached prediction without running the model.

It binds 127.0.0.1 unless --host says otherwise, refuses uploads over --max-file-size, files that
are no image, and images with a side over --max-side or under the model's minimum
(`ufm_jax.runtime.inference.min_image_side`, the rule of every tool),
with a message naming the limit and the image's size, and makes a public share link only with
--share. Its API (`gradio_client`): `Client(url).predict(source,
target, threshold, num, api_name="/analyse")` -> (flow colours, covisibility, warped target,
matches drawing, matches.npz, summary, uncertainty (None for a model without a flow covariance)).
"""

from __future__ import annotations

import collections
import hashlib
import ipaddress
import os
import pathlib
import shutil
import tempfile
import threading
import time

import numpy as np

INSTALL_HINT = 'the demo needs the [demo] extra (gradio): pip install -e ".[demo]"'
DEFAULT_MAX_SIDE = 2048
DEFAULT_MAX_FILE_SIZE = "20mb"
DEFAULT_NUM = 2000
EXAMPLE_SIZE = (240, 320)  # (H, W): the 3:4 aspect of the released models' 420x560
MAX_LINES = 300            # matches drawn; the .npz holds all of them
CACHE_SECONDS = 3600       # how long the page's files stay fetchable (Gradio's delete_cache)


def check_size(image: np.ndarray, what: str, max_side: int) -> None:
  """Refuses an image with a side over max_side (this page's upload limit), naming the limit and
  the image's size. Too small an image is refused by `ufm_jax.predict` (min_image_side)."""
  h, w = image.shape[:2]
  if max(h, w) > max_side:
    raise ValueError(f"the {what} image is {h}x{w} px (HxW), over this demo's limit of {max_side} "
                     f"px per side (--max-side {max_side}); downscale it or restart the demo "
                     "with a larger --max-side")


def read_upload(payload, what: str) -> np.ndarray | None:
  """An uploaded image (Gradio's file payload: a dict or object with a `path`, or an array) as
  HWC uint8 RGB through the project's image reader; a file that is no readable image is refused
  with a message that names the input, not the server's temp path."""
  if payload is None or isinstance(payload, np.ndarray):
    return payload
  from ufm_jax.data import io
  path = payload.get("path") if isinstance(payload, dict) else getattr(payload, "path", None)
  if not path:
    return None
  try:
    return io.read_image(path)
  except (OSError, ValueError):
    raise ValueError(f"the {what} file is not an image this demo can read ({io.IMAGE_FORMATS})"
                     ) from None


def example_pair(folder) -> list[str]:
  """Renders one synthetic two-view pair (ufm_jax.data.synthetic) into `folder`: [source, target]."""
  from ufm_jax.data import io, synthetic
  fwd, = synthetic.generate_pair(3, synthetic.SyntheticConfig(size=EXAMPLE_SIZE, pair_type="flow"),
                                 directions=(0,))
  paths = [pathlib.Path(folder) / "example_source.png", pathlib.Path(folder) / "example_target.png"]
  io.write_image(paths[0], fwd["image0"])
  io.write_image(paths[1], fwd["image1"])
  return [str(p) for p in paths]


def colour_key(side: int = 96) -> np.ndarray:
  """The flow colour wheel as an image: the colour of a flow pointing from the centre to a pixel."""
  from ufm_jax.runtime import viz
  r = np.linspace(-1.0, 1.0, side, dtype=np.float32)
  u, v = np.meshgrid(r, r)
  key = viz.flow_to_color(np.stack([u, v], -1), max_flow=1.0)
  key[u * u + v * v > 1.0] = 255
  return key


class Analyser:
  """Prediction (cached by image content) -> the demo's views; no gradio in here."""

  def __init__(self, model, variables, out_dir, max_side: int = DEFAULT_MAX_SIDE,
               cache_size: int = 8, keep_s: float = CACHE_SECONDS):
    from ufm_jax.runtime import inference
    self.model, self.variables = model, variables
    self.out_dir = pathlib.Path(out_dir)
    self.max_side = max_side
    self.min_side = inference.min_image_side(model)
    self.cache_size = cache_size
    self.keep_s = keep_s
    self._cache: collections.OrderedDict = collections.OrderedDict()
    self._lock = threading.Lock()

  def response_dir(self, key: str) -> pathlib.Path:
    """A new folder for one response's files. Folders older than `keep_s` are removed first:
    Gradio copies a response's files into its own cache as it answers, and that cache keeps
    them for the same hour (build_app's delete_cache), so no client fetches ours after that."""
    self.out_dir.mkdir(parents=True, exist_ok=True)
    now = time.time()
    for old in self.out_dir.glob("response_*"):
      try:
        if now - old.stat().st_mtime > self.keep_s:
          shutil.rmtree(old, ignore_errors=True)
      except FileNotFoundError:  # another request removed it first
        pass
    return pathlib.Path(tempfile.mkdtemp(prefix=f"response_{key}_", dir=self.out_dir))

  def predict(self, source: np.ndarray, target: np.ndarray) -> tuple[str, dict, float]:
    """(content key, prediction at the source size, forward ms; 0 when it came from the cache)."""
    from ufm_jax.runtime import inference
    key = hashlib.sha1(b"".join(np.ascontiguousarray(x).tobytes() + str(x.shape).encode()
                                for x in (source, target))).hexdigest()[:16]
    with self._lock:  # gradio runs events in threads; one forward at a time on one model
      if key in self._cache:
        self._cache.move_to_end(key)
        return key, self._cache[key], 0.0
      t0 = time.perf_counter()
      pred = inference.predict(self.model, self.variables, source, target)
      ms = 1e3 * (time.perf_counter() - t0)
      self._cache[key] = pred
      while len(self._cache) > self.cache_size:
        self._cache.popitem(last=False)
    return key, pred, ms

  def __call__(self, source, target, threshold: float = 0.5, num: int = DEFAULT_NUM):
    """-> (flow colours, covisibility, warped target, matches drawing, matches .npz path, summary,
    uncertainty view or None)."""
    from ufm_jax.runtime import viz
    from ufm_jax.tools import matching
    source, target = read_upload(source, "source"), read_upload(target, "target")
    if source is None or target is None:
      raise ValueError("upload a source and a target image (or pick the example pair)")
    source, target = np.asarray(source), np.asarray(target)
    check_size(source, "source", self.max_side)
    check_size(target, "target", self.max_side)
    key, pred, ms = self.predict(source, target)
    flow, covis = pred["flow"], pred.get("covisibility")
    threshold, num = float(threshold), int(num)
    colours, warped = viz.flow_views(target, flow, covis, threshold=threshold)
    cov = pred.get("flow_covariance")
    uncertainty = None if cov is None else viz.uncertainty_view(cov)
    if covis is None:   # flow and warp only: matches are drawn by covisibility (matching.py)
      summary = ("this model predicts no covisibility (no non_occluded_mask adaptor): flow and "
                 "warp only, no covisibility view and no matches; "
                 + (f"forward {ms:.0f} ms" if ms else "prediction cached"))
      return colours, None, warped, None, None, summary, uncertainty
    m = matching.matches_from_dense(flow, covis, num=num, min_covisibility=threshold,
                                    target_hw=target.shape[:2], covariance=cov,
                                    covariance_inv=pred.get("flow_covariance_inv"))
    drawing = matching.draw_matches(source, target, m["keypoints0"], m["keypoints1"],
                                    max_lines=MAX_LINES)
    # Each response owns its files (as_files adds the pictures): identical concurrent requests
    # never share or replace one while Gradio copies it to its cache (#51).
    npz = matching.save_matches(self.response_dir(key) / f"matches_{key}_{threshold:.3f}_{num}.npz",
                                m, source.shape, target.shape)
    n = len(m["keypoints0"])
    why = matching.shortfall(m, num, threshold)
    summary = (f"{n} matches at covisibility >= {threshold:.2f} ({min(n, MAX_LINES)} drawn"
               + (f"; {why}" if why else "") + "); "
               f"{100 * float(np.mean(covis >= threshold)):.1f}% of source pixels covisible; "
               + (f"median match sigma {float(np.median(m['sigma'])):.2f} px; "
                  if cov is not None and n else "")
               + (f"forward {ms:.0f} ms" if ms else "prediction cached"))
    return (colours, viz.covisibility_to_image(covis), warped, drawing, str(npz), summary,
            uncertainty)


VIEW_FILES = {0: "flow.png", 1: "covisibility.png", 2: "warped.png", 3: "matches.png",
              6: "uncertainty.png"}


def as_files(views: tuple) -> tuple:
  """Analyser's views with every picture written as a PNG into the response's own folder (the
  one holding its .npz). Gradio saves a returned array under a name made from its content,
  writing the file in place: identical concurrent requests rewrote one file while other
  clients downloaded it, and a download came back cut (#51). A file it copies into its cache
  under a temporary name and renames, so each client reads a whole one."""
  from ufm_jax.data import io
  folder = pathlib.Path(views[4]).parent
  out = list(views)
  for i, name in VIEW_FILES.items():
    if out[i] is not None:
      io.write_image(folder / name, out[i])
      out[i] = str(folder / name)
  return tuple(out)


def build_app(analyser: Analyser, examples: list[list[str]] | None = None):
  """The gr.Blocks page around `analyser`; its API endpoint is /analyse."""
  import gradio as gr

  def analyse(source, target, threshold, num):
    try:
      return as_files(analyser(source, target, threshold, num))
    except ValueError as e:  # a refused input, not a bug: shown to the user (and API clients)
      raise gr.Error(str(e), title="Input refused", print_exception=False) from None

  with gr.Blocks(title="UFM-JAX demo", analytics_enabled=False,
                 delete_cache=(CACHE_SECONDS, CACHE_SECONDS)) as app:
    gr.Markdown("## UFM: dense flow and covisibility between two images\n"
                "Upload a source and a target image. The flow is defined on the source's pixels "
                "(where does each one land in the target); pixels below the covisibility "
                f"threshold are greyed out and never matched. Images from {analyser.min_side} to "
                f"{analyser.max_side} px per side.")
    with gr.Row():
      source = gr.Image(type="numpy", image_mode="RGB", label="source", sources=["upload", "clipboard"])
      target = gr.Image(type="numpy", image_mode="RGB", label="target", sources=["upload", "clipboard"])
    with gr.Row():
      threshold = gr.Slider(0.0, 1.0, value=0.5, step=0.01, label="covisibility threshold")
      num = gr.Slider(100, 20000, value=DEFAULT_NUM, step=100, label="matches to sample")
      run = gr.Button("Run", variant="primary")
    if examples:
      gr.Examples(examples=examples, inputs=[source, target], label="example pair (synthetic)")
    summary = gr.Textbox(label="summary", interactive=False)
    gr.Markdown("Flow colours: hue = direction, saturation = magnitude (see the key). "
                "Covisibility: white = also seen in the target.")
    with gr.Row():
      # Short labels: a panel's label is cut to the panel's width.
      flow = gr.Image(format="png", label="flow", interactive=False)
      gr.Image(value=colour_key(), format="png", label="key", interactive=False,
               show_label=True, width=120, height=120)
      covis = gr.Image(format="png", label="covisibility", interactive=False)
      warped = gr.Image(format="png", label="warped target", interactive=False)
    has_cov = getattr(getattr(analyser.model, "config", None), "flow_covariance", None) is not None
    uncertainty = gr.Image(format="png", label="uncertainty (sigma, px)", interactive=False,
                           visible=has_cov)
    drawing = gr.Image(format="png", label="sampled matches", interactive=False)
    npz = gr.File(label="matches.npz (keypoints0, keypoints1, confidence"
                  + (", covariance, precision, sigma: most certain first)" if has_cov else ")"),
                  interactive=False)
    outputs = [flow, covis, warped, drawing, npz, summary, uncertainty]
    inputs = [source, target, threshold, num]
    # preprocess=False: the uploads reach `analyse` as files and go through the project's image
    # reader (read_upload), so a file that is no image gets our message, not Gradio's (which
    # names the server's temp path).
    run.click(analyse, inputs, outputs, api_name="analyse", preprocess=False)
    # The sliders re-sample the cached prediction; only the button is the public API. `input`
    # fires on drags, arrow keys and typing in the number box alike (`release` only on a mouse
    # release); always_last drops the intermediate values of a drag.
    for s in (threshold, num):
      s.input(analyse, inputs, outputs, api_visibility="private", preprocess=False,
              trigger_mode="always_last")
  return app


def is_loopback(host: str) -> bool:
  if host == "localhost":
    return True
  try:
    return ipaddress.ip_address(host).is_loopback
  except ValueError:
    return False


def serve(model, variables, *, host: str = "127.0.0.1", port: int = 7860, share: bool = False,
          max_side: int = DEFAULT_MAX_SIDE, max_file_size: str = DEFAULT_MAX_FILE_SIZE) -> None:
  """Warms the model up on the example pair, then serves the page until Ctrl-C (needs gradio).
  `python -m ufm_jax demo` parses its arguments and calls this."""
  os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")  # no calls home from a local tool
  with tempfile.TemporaryDirectory(prefix="ufm_jax_demo_") as tmp:
    examples_dir, out_dir = pathlib.Path(tmp, "examples"), pathlib.Path(tmp, "out")
    examples_dir.mkdir()
    out_dir.mkdir()
    analyser = Analyser(model, variables, out_dir, max_side=max_side)
    pair = example_pair(examples_dir)
    if max(EXAMPLE_SIZE) <= max_side:
      from ufm_jax.data import io
      t0 = time.perf_counter()
      analyser(io.read_image(pair[0]), io.read_image(pair[1]))  # compiles before the first visitor
      print(f"model ready ({time.perf_counter() - t0:.1f} s warm-up on the example pair)", flush=True)
    else:
      pair = None
    app = build_app(analyser, [pair] if pair else None)
    if not is_loopback(host):
      print(f"warning: binding {host}: the demo is reachable from other machines", flush=True)
    if share:
      print("warning: --share makes the demo reachable by anyone with the public link", flush=True)
    # quiet: Gradio's own lines name its launch() arguments (`share=True`); ours name the flags.
    app.queue(default_concurrency_limit=1).launch(
        server_name=host, server_port=port, share=share, max_file_size=max_file_size,
        allowed_paths=[str(examples_dir), str(out_dir)], show_error=True, ssr_mode=False,
        inbrowser=False, quiet=True, prevent_thread_lock=True)
    # (with --share Gradio prints the public URL itself, quiet or not)
    print(f"* Running on local URL:  {app.local_url}" + (
        "" if share else "   (python -m ufm_jax demo --share also opens a public link)"), flush=True)
    app.block_thread()
