"""Goodput (WORKDIR/goodput.json, ufm_jax.training.goodput) and profiles
(`--config.profile_steps`, ufm_jax.training.profiling): the accounting of hand-made run records,
and a synthetic run killed with SIGKILL between checkpoints, restarted, whose file still adds up."""

import json
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from ufm_jax.training import goodput, profiling
from ufm_jax.testing import train_support

REPO = pathlib.Path(__file__).resolve().parents[1]
PARTS = ("productive_s", "lost_s", "compile_s", "checkpoint_s", "data_wait_s", "eval_s",
         "unaccounted_s", "other_s")


def _run(start, last, wall, step, compile_s, ckpt, data, ev, ended, gap=None):
  r = {"started_at": 0.0, "written_at": wall, "ended": ended, "start_step": start,
       "last_step": last, "wall_s": wall, "step_s": step, "compile_s": compile_s,
       "checkpoint_s": ckpt, "data_wait_s": data, "eval_s": ev}
  if gap is not None:
    r["unaccounted_after_s"] = gap
  return r


def test_totals_of_a_killed_and_restarted_run():
  # Run A: steps 1-8 in 4 s of loop time, killed 3 s before run B started; B resumed from the
  # checkpoint of step 5, so A's steps 6-8 (3 of its 8) were computed again: 4 x 3 / 8 = 1.5 s.
  a = _run(0, 8, 10.0, 4.0, 2.0, 1.0, 0.5, 0.5, ended=False, gap=3.0)
  b = _run(5, 10, 6.0, 2.5, 1.0, 0.5, 0.0, 0.0, ended=True)
  t = goodput.totals([a, b])
  assert t["wall_s"] == 19.0                       # 10 + 3 (unaccounted) + 6
  assert t["lost_s"] == 1.5 and t["productive_s"] == 5.0       # (4 - 1.5) + 2.5
  assert t["unaccounted_s"] == 3.0
  assert t["compile_s"] == 3.0 and t["checkpoint_s"] == 1.5
  assert t["other_s"] == 4.0                       # A: 13 - 11, B: 6 - 4
  assert t["restarts"] == 1 and t["goodput"] == round(5.0 / 19.0, 4)
  assert sum(t[k] for k in PARTS) == pytest.approx(t["wall_s"], abs=1e-9)


def test_a_restart_from_scratch_loses_every_step_before_it():
  a = _run(0, 8, 10.0, 4.0, 2.0, 0.0, 0.0, 0.0, ended=False, gap=1.0)
  b = _run(0, 3, 5.0, 1.0, 2.0, 0.0, 0.0, 0.0, ended=False)
  c = _run(2, 4, 5.0, 2.0, 2.0, 0.0, 0.0, 0.0, ended=True)
  t = goodput.totals([a, b, c])
  # A: all 8 steps lost (B restarted at 0); B: step 3 lost (C restarted at 2): 1 x 1/3.
  assert t["lost_s"] == pytest.approx(4.0 + 1.0 / 3, abs=1e-3)
  assert t["productive_s"] == pytest.approx(2.0 / 3 + 2.0, abs=1e-3)
  assert t["restarts"] == 2


def test_tracker_accumulates_across_instances(tmp_path):
  first = goodput.Tracker(tmp_path, started=time.time() - 2.0)
  first.resumed(0)
  with first.timed("data_wait"):
    time.sleep(0.05)
  time.sleep(0.06)                   # the steps' own time
  first.step(3)
  first.write()                      # then "killed": no ended write
  second = goodput.Tracker(tmp_path)
  second.resumed(1)
  second.step(2)
  t = second.write(ended=True)
  saved = json.loads((tmp_path / goodput.FILE).read_text())
  assert [r["ended"] for r in saved["runs"]] == [False, True]
  assert saved["restarts"] == t["restarts"] == 1
  assert saved["runs"][0]["data_wait_s"] >= 0.05
  assert saved["lost_s"] > 0 and saved["wall_s"] >= 2.0
  assert sum(saved[k] for k in PARTS) == pytest.approx(saved["wall_s"], abs=0.01)


def test_close_writes_once_and_ends_the_run(tmp_path):
  t = goodput.Tracker(tmp_path)
  first = t.close()
  time.sleep(0.02)
  assert t.close() == first         # the second call (atexit after the loop's) changes nothing
  saved = json.loads((tmp_path / goodput.FILE).read_text())
  assert saved["runs"][0]["ended"] is True and saved["wall_s"] == first["wall_s"]


def test_profile_steps_values():
  assert profiling.profile_steps(None) is None and profiling.profile_steps("") is None
  assert profiling.profile_steps("3:6") == (3, 6)
  for bad in ("3", "6:3", "0:2", "a:b", "3:3", "3:6:9"):
    with pytest.raises(ValueError, match=r"profile_steps=.*expected A:B"):
      profiling.profile_steps(bad)


def test_a_bad_profile_steps_is_one_error_line(tmp_path):
  out = subprocess.run(
      [sys.executable, str(REPO / "train.py"), f"--config={REPO}/configs/synthetic.py",
       f"--workdir={tmp_path / 'wd'}", "--config.profile_steps=5-9"],
      capture_output=True, text=True, timeout=300, cwd=REPO, env=_env(tmp_path / "cache"))
  assert out.returncode == 2
  assert out.stderr.strip() == ("error: --config.profile_steps='5-9': expected A:B, the steps A "
                                "to B-1 (1 <= A < B), e.g. 10:15")
  assert not (tmp_path / "wd").exists()


def _env(cache):
  return train_support.subprocess_env(REPO, cache)


def _train(workdir, cache, name, *args):
  out, err = (open(workdir.parent / f"{name}.{s}", "w") for s in ("out", "err"))
  cmd = [sys.executable, str(REPO / "train.py"), f"--workdir={workdir}",
         f"--config={REPO}/configs/synthetic.py:steps=100000,batch=2,size=56,eval=false",
         "--config.ckpt_steps=50", "--config.keep_ckpt=2", "--config.log_training_steps=1", *args]
  return subprocess.Popen(cmd, env=_env(cache), stdout=out, stderr=err, cwd=REPO)


def _read(path):
  try:
    return json.loads(path.read_text())
  except (FileNotFoundError, ValueError):
    return None


@pytest.mark.slow
def test_sigkill_between_checkpoints_then_restart_adds_up(tmp_path):
  """Run 1 (with a profile of steps 2-3) is killed with SIGKILL some steps after its checkpoint
  of step 50; run 2 resumes from that checkpoint and finishes. goodput.json counts both runs,
  the steps run 1 made after its checkpoint as lost, and its parts add up to wall_s."""
  wd, cache = tmp_path / "wd", tmp_path / "cache"
  proc = _train(wd, cache, "first", "--config.profile_steps=2:4")
  t0 = time.time()
  while True:
    g = _read(wd / goodput.FILE)
    last = g["runs"][-1]["last_step"] if g else 0
    if 55 <= last and 5 <= last % 50 <= 40:
      break
    assert proc.poll() is None, (wd.parent / "first.err").read_text()[-3000:]
    assert time.time() - t0 < 600, "run 1 too slow"
    time.sleep(0.02)
  proc.send_signal(signal.SIGKILL)
  proc.wait(60)
  killed = _read(wd / goodput.FILE)
  assert killed["runs"][0]["ended"] is False
  written = killed["runs"][0]["last_step"]
  # The profile of steps 2-3 was written before the kill.
  assert list((wd / "profile").glob("plugins/profile/*/*.xplane.pb"))

  # The newest complete checkpoint (orbax renames a step's folder into place when its write
  # ends): step 50 (or 100), or step 1 if that write had not finished at the kill.
  complete = [int(p.name) for p in (wd / "checkpoints").iterdir() if p.name.isdigit()]
  proc = _train(wd, cache, "second", f"--config.total_steps={written + 5}")
  assert proc.wait(600) == 0, (wd.parent / "second.err").read_text()[-3000:]
  out = (wd.parent / "second.out").read_text()
  resumed = int(out.split("resumed from step ")[1].split()[0]) if "resumed from" in out else 0
  assert resumed == max(complete, default=0) and resumed < written
  g = _read(wd / goodput.FILE)
  assert g["restarts"] == 1 and [r["ended"] for r in g["runs"]] == [False, True]
  assert g["runs"][1]["start_step"] == resumed and g["runs"][1]["last_step"] == written + 5
  assert g["lost_s"] > 0 and g["unaccounted_s"] > 0
  assert sum(g[k] for k in PARTS) == pytest.approx(g["wall_s"], abs=0.01)
  assert all(g[k] >= 0 for k in PARTS) and g["goodput"] == round(g["productive_s"] / g["wall_s"], 4)
  # Run 1's lost share: its loop time per step x the steps after the checkpoint run 2 took.
  r1 = g["runs"][0]
  assert g["lost_s"] == pytest.approx(r1["step_s"] * (written - resumed) / written, abs=2e-3)
  # The summary line comes after the loop's last line, before the checkpoint and next commands.
  summary = [x for x in out.splitlines() if x.startswith("goodput ")]
  assert len(summary) == 1 and "over 2 run(s)" in summary[0]
  assert out.index(summary[0]) < out.index("checkpoint: ")
  assert list((wd / "tb").glob("events.out.tfevents.*"))
  logged = [json.loads(x) for x in (wd / "goodput.jsonl").read_text().splitlines()]
  assert logged[-1]["restarts"] == 1 and logged[-1]["wall_s"] == g["wall_s"]
