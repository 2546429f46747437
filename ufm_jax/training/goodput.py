"""Where a training run's time goes, accumulated over its restarts: WORKDIR/goodput.json.

train.py opens a `Tracker` when it starts, tells it the step it resumed from, times the parts of
its loop that are not training steps (`timed`), and writes the file (atomically) when it starts,
at every log step and checkpoint and at the end, so a SIGKILL loses at most the time since the
last write. Every run is one record of `runs`; the totals are recomputed from the records at each
write, so the parts always add up:

  wall_s = productive_s + lost_s + compile_s + checkpoint_s + data_wait_s + eval_s
           + unaccounted_s + other_s

- productive_s: the loop's time outside the timed parts, for steps that count;
- lost_s: the same for steps computed again after a restart (those after the step the next run
  resumed from), at the run's mean time per step;
- compile_s: the run's first train_step call (tracing and compiling the step);
- checkpoint_s: restoring, saves (from the step's end: the save's device sync and its
  synchronous part; an async write's background part overlaps the next steps), the final wait;
- data_wait_s: waiting for the next batch (`next` on the device prefetch);
- eval_s: the evaluations (their compiles included);
- unaccounted_s: a run that ended without its final write (killed): the time from its last write
  to the next run's start. What it did then is unknown (steps that were lost, the dying, the
  scheduler's restart), so it is counted as itself, an upper bound of the killed run's lost tail;
- other_s: the rest of each run (start-up: imports, mesh, input pipeline, model and optimizer
  init; logging; shutdown).

wall_s is the sum of the runs' own times from start to last write plus the unaccounted gaps; the
time between a run that exited cleanly and the next start (the job waiting in a queue, or a
resume days later) is not the job's and is not counted. goodput = productive_s / wall_s. Only
process 0 keeps the file. docs/training.md ("Goodput") says how to read it.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import pathlib
import time

FILE = "goodput.json"
TIMED = ("compile", "checkpoint", "data_wait", "eval")
KEYS = ("wall_s", "productive_s", "lost_s", "compile_s", "checkpoint_s", "data_wait_s", "eval_s",
        "unaccounted_s", "other_s")


def _run_parts(run: dict, resumed_from: int | None) -> dict:
  """One run's seconds by category; `resumed_from`: the lowest step a later run restarted from
  (None: no later run)."""
  steps = max(0, run["last_step"] - run["start_step"]) if run["start_step"] is not None else 0
  lost_steps = 0
  if resumed_from is not None and steps:
    lost_steps = min(steps, max(0, run["last_step"] - max(resumed_from, run["start_step"])))
  lost = run["step_s"] * lost_steps / steps if steps else 0.0
  parts = {"wall_s": run["wall_s"] + run.get("unaccounted_after_s", 0.0),
           "productive_s": run["step_s"] - lost, "lost_s": lost,
           **{f"{k}_s": run[f"{k}_s"] for k in TIMED},
           "unaccounted_s": run.get("unaccounted_after_s", 0.0)}
  parts["other_s"] = parts["wall_s"] - sum(v for k, v in parts.items() if k != "wall_s")
  return parts


def totals(runs: list) -> dict:
  """The file's top-level figures from its run records (`_run_parts` summed)."""
  out = dict.fromkeys(KEYS, 0.0)
  for i, run in enumerate(runs):
    later = [r["start_step"] for r in runs[i + 1:] if r["start_step"] is not None]
    for k, v in _run_parts(run, min(later) if later else None).items():
      out[k] += v
  out = {k: round(v, 3) for k, v in out.items()}
  out["restarts"] = max(0, len(runs) - 1)
  out["goodput"] = round(out["productive_s"] / out["wall_s"], 4) if out["wall_s"] > 0 else None
  return out


def summary_line(figures: dict) -> str:
  f = figures
  share = lambda k: f"{k[:-2]} {f[k]:.1f} s"   # noqa: E731
  return (f"goodput {100 * (f['goodput'] or 0):.1f}% of {f['wall_s']:.1f} s over "
          f"{f['restarts'] + 1} run(s): " + ", ".join(share(k) for k in KEYS[1:]))


class Tracker:
  """One run's share of WORKDIR/goodput.json (module docstring). `active` False (processes other
  than 0): times nothing to disk."""

  def __init__(self, workdir, active: bool = True, started: float | None = None,
               at_exit: bool = False):
    self.path = pathlib.Path(workdir) / FILE
    self.active = active
    self.closed = False
    now = time.time()
    started = now if started is None else started
    self._t0 = time.monotonic() - (now - started)   # the run's start on the monotonic clock
    self.runs = self._previous() if active else []
    if self.runs and not self.runs[-1].get("ended"):
      # Killed after its last write: what it did until this start is unknown.
      self.runs[-1]["unaccounted_after_s"] = max(0.0, started - self.runs[-1]["written_at"])
    self.run = {"started_at": started, "written_at": started, "ended": False,
                "start_step": None, "last_step": 0, "wall_s": 0.0, "step_s": 0.0,
                **{f"{k}_s": 0.0 for k in TIMED}}
    self.runs.append(self.run)
    self._loop_t0 = None
    self._in_loop = 0.0      # timed seconds since the loop started
    self.write()
    if at_exit and active:
      # A run that stops on an error before its loop's own final write (a bad config, a failed
      # restore) still ends its record: only a killed process leaves time unaccounted.
      atexit.register(self.close)

  def _previous(self) -> list:
    if not self.path.exists():
      return []
    try:
      runs = json.loads(self.path.read_text())["runs"]
    except (ValueError, KeyError) as e:
      raise ValueError(f"{self.path}: not a goodput file this version wrote ({e}); move it "
                       f"aside to start the accounting afresh") from e
    return list(runs)

  def resumed(self, step: int):
    """The step this run starts from (its checkpoint's, 0 for a fresh run); the loop starts."""
    self.run["start_step"] = self.run["last_step"] = int(step)
    self._loop_t0 = time.monotonic()
    self._in_loop = 0.0

  def add(self, kind: str, seconds: float):
    if kind not in TIMED:
      raise KeyError(f"goodput: unknown kind {kind!r}; known: {TIMED}")
    self.run[f"{kind}_s"] += seconds
    if self._loop_t0 is not None:
      self._in_loop += seconds

  @contextlib.contextmanager
  def timed(self, kind: str):
    t = time.monotonic()
    try:
      yield
    finally:
      self.add(kind, time.monotonic() - t)

  def step(self, step: int):
    """The loop finished `step`."""
    self.run["last_step"] = int(step)

  def figures(self) -> dict:
    now = time.monotonic()
    self.run["wall_s"] = now - self._t0
    if self._loop_t0 is not None:
      self.run["step_s"] = max(0.0, now - self._loop_t0 - self._in_loop)
    return totals(self.runs)

  def close(self) -> dict:
    """The run's final write (once; later calls return the figures written then)."""
    if not self.closed:
      self._final = self.write(ended=True)
      self.closed = True
    return self._final

  def write(self, ended: bool = False) -> dict:
    """Writes the file (process 0) and returns its figures."""
    self.run["ended"] = bool(ended)
    figures = self.figures()
    self.run["written_at"] = self.run["started_at"] + self.run["wall_s"]
    if self.active:
      from ufm_jax.data import io
      io.write_json_atomic(self.path, {**figures, "runs": self.runs})
    return figures
