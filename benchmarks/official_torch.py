"""The official PyTorch UFM, for timing it next to UFM-JAX in one process (benchmarks/inference.py
--official). Nothing of the official code is part of this repository: the user points at their
own clone.

  --official DIR  (or UFM_OFFICIAL=DIR): a clone of github.com/UniFlowMatch/UFM with its
      UniCeption submodule checked out (DIR/UniCeption), or any folder from which `uniflowmatch`
      and `uniception` import; with neither, whatever `import uniflowmatch` finds.
  --official_hub DIR  (or UFM_DINOV2_HUB=DIR): a local checkout of facebookresearch/dinov2.
      UniCeption builds the DINOv2 encoder with torch.hub.load('facebookresearch/dinov2', ...),
      which downloads the hub code and pretrained weights; with a local checkout it is built
      from there without weights (the snapshot's weights replace them either way), offline.

Both sides load the same official-layout snapshot and see the same normalised images.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import time

import numpy as np

# Module-name patterns of the official model for each stage label of benchmarks/inference.py
# STAGES (UniCeption's module tree; the hub ViT sits at encoder.model).
OFFICIAL_STAGES = (
    ("patch embed", r"encoder\.model\.patch_embed"),
    ("encoder attention", r"encoder\.model\.blocks\.\d+\.attn"),
    ("encoder MLP", r"encoder\.model\.blocks\.\d+\.mlp"),
    ("fusion attention", r"info_sharing\.self_attention_blocks\.\d+\.attn"),
    ("fusion MLP", r"info_sharing\.self_attention_blocks\.\d+\.mlp"),
    ("flow head DPT feature", r"head1\.0\.0"),
    ("flow head regression", r"head1\.0\.1"),
    ("covisibility head DPT feature", r"uncertainty_head\.0\.0"),
    ("covisibility head regression", r"uncertainty_head\.0\.1"),
    ("refiner U-Net", r"unet_feature"),
    ("refiner classification head", r"classification_head"),
)
LOCAL_REFINEMENT = "refiner local refinement"   # a method of the official model, not a module


class Official:
  """The official model of a snapshot, called on NHWC uint8 pairs like the JAX model."""

  def __init__(self, torch, model, bf16: bool):
    self.torch, self.model, self.bf16 = torch, model, bf16
    self.version = f"torch {torch.__version__}, {torch.get_num_threads()} threads"

  def inputs(self, source, target):
    """NCHW float32 views from [B, H, W, 3] uint8 images, normalised by ufm_jax (bitwise the
    official uint8 normalisation)."""
    from ufm_jax.models import ufm
    views = []
    for i, img in enumerate((source, target)):
      x = np.asarray(ufm.normalize(np.asarray(img))).transpose(0, 3, 1, 2)
      views.append({"img": self.torch.from_numpy(np.ascontiguousarray(x)),
                    "data_norm_type": "dinov2", "symmetrized": False,
                    "instance": list(range(i * len(x), (i + 1) * len(x)))})
    return views

  def __call__(self, views):
    """flow [B, H, W, 2] and covisibility [B, H, W] as numpy float32. bf16: the whole forward
    under torch.autocast("cpu", bfloat16); the official `autocast("cuda", float32)` guard around
    its heads does not apply on a CPU, so its heads run in bf16 too."""
    torch = self.torch
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16)
    with torch.no_grad(), autocast:
      out = self.model(*views)
    flow = out.flow.flow_output.float().numpy().transpose(0, 2, 3, 1)
    covis = out.covisibility.mask.float().numpy()[:, 0]
    return flow, covis

  def stage_ms(self, views, runs: int) -> dict[str, float]:
    """Milliseconds per forward spent in each OFFICIAL_STAGES module (forward hooks, summed over
    its calls) and in the local refinement: the minimum over `runs` forwards."""
    stages: dict[str, float] = {}
    calls: dict[str, int] = {}
    handles, acc, starts = [], {}, {}
    for name, mod in self.model.named_modules():
      for label, pattern in OFFICIAL_STAGES:
        if re.fullmatch(pattern, name):
          def pre(_m, _a, key=name):
            starts[key] = time.perf_counter()

          def post(_m, _a, _o, key=name, label=label):
            acc[label] = acc.get(label, 0.0) + time.perf_counter() - starts.pop(key)
          handles += [mod.register_forward_pre_hook(pre), mod.register_forward_hook(post)]
          calls[label] = 0
    refine = getattr(self.model, "classification_refinement", None)
    if refine is not None:
      def timed(*a, **k):
        t0 = time.perf_counter()
        out = refine(*a, **k)
        acc[LOCAL_REFINEMENT] = acc.get(LOCAL_REFINEMENT, 0.0) + time.perf_counter() - t0
        return out
      self.model.classification_refinement = timed
    try:
      for _ in range(runs):
        acc.clear()
        self(views)
        for label, t in acc.items():
          stages[label] = min(stages.get(label, float("inf")), 1e3 * t)
    finally:
      for h in handles:
        h.remove()
      if refine is not None:
        del self.model.classification_refinement
    return stages


def _importable(names) -> bool:
  import importlib.util
  return all(importlib.util.find_spec(n) is not None for n in names)


def rerun_with_clone(clone: str | None) -> None:
  """A clone is a checkout, not an installed package: when `uniflowmatch` does not import, the
  benchmark starts again (same arguments) with the clone and its UniCeption submodule on
  PYTHONPATH. Once: the second run's environment says it was already extended."""
  if not clone or os.environ.get("UFM_OFFICIAL_ON_PATH") or not os.path.isdir(clone):
    return
  if _importable(("uniflowmatch", "uniception")):
    return
  paths = [p for p in (os.path.join(clone, "UniCeption"), clone) if os.path.isdir(p)]
  if os.environ.get("PYTHONPATH"):
    paths.append(os.environ["PYTHONPATH"])
  env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths), UFM_OFFICIAL_ON_PATH="1")
  sys.stdout.flush()
  os.execve(sys.executable, [sys.executable, *sys.argv], env)


@contextlib.contextmanager
def _local_dinov2_hub(torch, hub_dir):
  """torch.hub.load of facebookresearch/dinov2 served from a local checkout, without weights."""
  if not hub_dir:
    yield
    return
  original = torch.hub.load

  def load(repo, model, *args, **kwargs):
    if "dinov2" in str(repo):
      return original(hub_dir, model, source="local", pretrained=False)
    return original(repo, model, *args, **kwargs)
  torch.hub.load = load
  try:
    yield
  finally:
    torch.hub.load = original


def why_unavailable(clone: str | None, hub_dir: str | None) -> str | None:
  """Why the official code cannot run here (None: it can), checked before anything is written."""
  if not _importable(("torch",)):
    return "torch is not importable"
  if clone and not os.path.isdir(clone):
    return f"--official {clone}: no such folder"
  if not _importable(("uniflowmatch", "uniception")):
    return ("the official `uniflowmatch` / `uniception` packages are not importable "
            "(--official DIR or UFM_OFFICIAL=DIR: a clone of UniFlowMatch/UFM with its "
            "UniCeption submodule)")
  if hub_dir and not os.path.isfile(os.path.join(hub_dir, "hubconf.py")):
    return f"--official_hub {hub_dir}: no hubconf.py (a facebookresearch/dinov2 checkout)"
  return None


def load(snapshot: str, hub_dir: str | None, refine: bool, bf16: bool, threads: int):
  """(Official, None), or (None, why the load failed). The caller checks `why_unavailable`
  first (before writing a snapshot for it)."""
  import torch
  torch.set_num_threads(threads)
  try:
    import warnings
    with warnings.catch_warnings(), contextlib.redirect_stdout(sys.stderr):
      warnings.simplefilter("ignore")
      from uniflowmatch.models import ufm as official_ufm
      cls = (official_ufm.UniFlowMatchClassificationRefinement if refine
             else official_ufm.UniFlowMatchConfidence)
      with _local_dinov2_hub(torch, hub_dir):
        model = cls.from_pretrained(snapshot).eval()
  except Exception as e:  # noqa: BLE001 - any failure of the user's clone is reported, not raised
    return None, f"the official code failed to load {snapshot}: {type(e).__name__}: {e}"
  return Official(torch, model, bf16), None


def matmul_peaks(torch, shapes, runs: int = 2) -> dict[str, float]:
  """Best GFLOP/s of torch.mm in float32 and bfloat16 (oneDNN) at each [m, k] x [k, n] shape."""
  out = {}
  for dtype, label in ((torch.float32, "torch f32"), (torch.bfloat16, "torch bf16")):
    best = 0.0
    for m, k, n in shapes:
      a, b = torch.randn(m, k, dtype=dtype), torch.randn(k, n, dtype=dtype)
      torch.mm(a, b)
      for _ in range(runs):
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = max(best, 2 * m * k * n / (time.perf_counter() - t0) / 1e9)
    out[label] = best
  return out
