"""Folder, pair-list and video inference for `python -m ufm_jax infer` (many pairs, one forward).

Pairs come from `--frames DIR` (consecutive frames in natural sort order, `--stride k` apart),
`--pairs LIST.txt` (two paths per line, relative to the list) or a video file (OpenCV). They go
through `ufm_jax.predict` `--batch` at a time; the last batch is padded with its last pair so the
compiled forward sees one shape. Reading and writing run in a small thread pool beside the
device. Outputs per pair under OUT/<name> (`ufm_jax.runtime.outputs`): `.flo` always, `--save
npy,covis,panel` adds more; OUT/manifest.jsonl gets one line per pair (pair, files, mean covisibility, ms, or the error of an
unreadable image, which is skipped). Existing outputs are skipped unless `overwrite`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import itertools
import json
import pathlib
import time

import numpy as np

from ufm_jax.runtime import outputs
from ufm_jax.data import io

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")
SAVE_CHOICES = tuple(outputs.SAVE_CHOICES)


def list_pairs(list_file) -> list[tuple[str, str]]:
  root = pathlib.Path(list_file).parent
  pairs = []
  for n, line in enumerate(pathlib.Path(list_file).read_text().splitlines(), 1):
    parts = line.split("#", 1)[0].split()
    if not parts:
      continue
    if len(parts) != 2:
      raise ValueError(f"{list_file}:{n}: expected two image paths, got {len(parts)} fields")
    pairs.append(tuple(str(root / p) for p in parts))
  return pairs


def video_frames(path, stride: int = 1):
  """Pairs (frame i, frame i + stride) of a video, each frame (name, RGB uint8 image) with name
  frame_%06d, decoded as they are consumed (OpenCV): only stride + 1 frames are held at once."""
  import cv2
  cap = cv2.VideoCapture(str(path))
  if not cap.isOpened():
    raise ValueError(f"{path}: OpenCV cannot open this video")

  def pairs():
    window = collections.deque(maxlen=stride + 1)
    try:
      i = 0
      while True:
        ok, bgr = cap.read()
        if not ok:
          return
        window.append((f"frame_{i:06d}", cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)))
        i += 1
        if len(window) == stride + 1:
          yield window[0], window[-1]
    finally:
      cap.release()

  return pairs()


def pair_name(a, b) -> str:
  return f"{pathlib.Path(a).stem}__{pathlib.Path(b).stem}"


def run(model, variables, pairs, out_dir, *, batch: int = 1, save=(), overwrite=False,
        workers: int = 4, progress=True) -> dict:
  """pairs: an iterable of (source, target), each a path or a (name, image); consumed as it goes
  (a video is never decoded whole). Returns counts (done/skipped/failed) and seconds."""
  from tqdm import tqdm

  from ufm_jax.runtime import inference

  out_dir = pathlib.Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  counts = {"done": 0, "skipped": 0, "failed": 0}
  outputs.paths(out_dir, "check", save)  # an unknown --save choice fails before any work
  expected = outputs.predicted(model)

  def todo():
    for a, b in pairs:
      na, nb = (a[0] if isinstance(a, tuple) else a), (b[0] if isinstance(b, tuple) else b)
      name = pair_name(na, nb)
      files = outputs.paths(out_dir, name, save)
      # done: every file this model's predictions write (no covariance file without the head)
      if not overwrite and all(f.exists() for f in outputs.written(files, expected).values()):
        counts["skipped"] += 1
        continue
      yield a, b, str(na), str(nb), name, files

  def load(item):
    a, b = item[0], item[1]
    try:
      return item, (a[1] if isinstance(a, tuple) else io.read_image(a),
                    b[1] if isinstance(b, tuple) else io.read_image(b), None)
    except (OSError, ValueError) as e:
      return item, (None, None, str(e))

  # Reads run `ahead` pairs in front of the device and writes trail behind it, both bounded, so
  # memory stays flat however many pairs come.
  ahead = max(2 * batch, workers)
  pool = concurrent.futures.ThreadPoolExecutor(workers)
  loads, writes = collections.deque(), collections.deque()
  manifest = open(out_dir / "manifest.jsonl", "a")
  bar = tqdm(total=len(pairs) if hasattr(pairs, "__len__") else None, disable=not progress,
             unit="pair")
  t_start = time.perf_counter()
  try:
    items = todo()
    for it in itertools.islice(items, ahead):
      loads.append(pool.submit(load, it))
    while loads:
      chunk = []
      while loads and len(chunk) < batch:
        chunk.append(loads.popleft().result())
        nxt = next(items, None)
        if nxt is not None:
          loads.append(pool.submit(load, nxt))
      good = [(it, (x, y)) for it, (x, y, err) in chunk if err is None]
      for it, (_, _, err) in chunk:
        if err is not None:
          print(f"warning: skipping pair {it[2]} -> {it[3]}: {err}")
          manifest.write(json.dumps({"pair": [it[2], it[3]], "error": err}) + "\n")
          counts["failed"] += 1
      if good:
        srcs = [g[1][0] for g in good] + [good[-1][1][0]] * (batch - len(good))
        tgts = [g[1][1] for g in good] + [good[-1][1][1]] * (batch - len(good))
        t0 = time.perf_counter()
        preds = inference.predict(model, variables, srcs, tgts, batch_size=batch)[:len(good)]
        ms = 1e3 * (time.perf_counter() - t0) / len(good)
        for (it, (x, y)), pred in zip(good, preds):
          writes.append(pool.submit(outputs.write, it[5], x, y, pred))
          manifest.write(json.dumps({"pair": [it[2], it[3]], "name": it[4],
                                     "files": [str(f) for f in
                                               outputs.written(it[5], pred).values()],
                                     **({"mean_covisibility": float(np.mean(pred["covisibility"]))}
                                        if "covisibility" in pred else {}),
                                     "ms": round(ms, 2)}) + "\n")
          counts["done"] += 1
      while len(writes) > ahead:
        writes.popleft().result()
      bar.update(counts["done"] + counts["failed"] + counts["skipped"] - bar.n)
      bar.set_postfix(pairs_per_s=f"{counts['done'] / (time.perf_counter() - t_start):.2f}")
    while writes:
      writes.popleft().result()
    bar.update(counts["done"] + counts["failed"] + counts["skipped"] - bar.n)
  finally:
    bar.close()
    pool.shutdown(wait=True)
    manifest.close()
  counts["seconds"] = time.perf_counter() - t_start
  return counts
