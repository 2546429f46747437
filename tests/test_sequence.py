"""`python -m ufm_jax infer --frames/--pairs/VIDEO`: natural order, one compiled shape for all
batches, manifest, resume, and a bad image skipped with its path."""

import json

import numpy as np

from ufm_jax.tools import cli, sequence
from ufm_jax.data import io
from ufm_jax.data.io import read_flo
from ufm_jax.data.sources import frames


class _Shift:
  """Stand-in model: flow = (source mean - target mean) per pair; counts its traces."""

  inference_resolution = [(28, 42)]

  def __init__(self):
    self.traces = []

  def apply(self, variables, source, target):
    self.traces.append(source.shape)
    d = (source.mean((1, 2, 3)) - target.mean((1, 2, 3)))[:, None, None, None]
    flow = d + 0.0 * source[..., :2]
    return {"flow": flow, "covisibility": 0.5 + 0.0 * source[..., 0]}


def _frames(folder, n):
  folder.mkdir()
  for i in range(n):  # values 10 * i: a natural-order pair (i, i + 1) has flow -10
    io.write_image(folder / f"f{i}.png", np.full((28, 42, 3), 10 * i, np.uint8))
  return folder


def test_natural_sort_and_pair_list(tmp_path):
  d = _frames(tmp_path / "fr", 12)
  pairs = frames.frame_pairs(d, stride=2)
  assert [tuple(p.rsplit("/", 1)[1] for p in pr) for pr in pairs[:3]] == [
      ("f0.png", "f2.png"), ("f1.png", "f3.png"), ("f2.png", "f4.png")]
  assert pairs[-1][1].endswith("f11.png") and len(pairs) == 10
  (tmp_path / "list.txt").write_text("fr/f1.png fr/f10.png\n# comment\n\nfr/f2.png fr/f3.png\n")
  assert sequence.list_pairs(tmp_path / "list.txt")[0] == (str(tmp_path / "fr/f1.png"),
                                                         str(tmp_path / "fr/f10.png"))


def test_frames_batched_resumable_with_a_bad_image(tmp_path, monkeypatch, capsys):
  d = _frames(tmp_path / "fr", 6)
  (d / "f3.png").write_bytes(b"not a png")  # pairs (2,3) and (3,4) fail, the rest go on
  model = _Shift()
  monkeypatch.setattr(cli, "load_model", lambda *a, **k: (model, {}))
  out = tmp_path / "out"
  argv = ["infer", "--frames", str(d), "--checkpoint", str(tmp_path), "--out", str(out),
          "--batch", "2", "--save", "npy,panel"]
  assert cli.main(argv) == 0
  assert len(set(model.traces)) == 1 and model.traces[0][0] == 2  # one shape, padded last batch
  assert "f3.png" in capsys.readouterr().out
  lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
  ok = [x for x in lines if "error" not in x]
  bad = [x for x in lines if "error" in x]
  assert len(ok) == 3 and len(bad) == 2 and all("f3.png" in x["error"] for x in bad)
  np.testing.assert_allclose(read_flo(out / "f4__f5.flo"), -10.0, atol=1e-4)
  assert (out / "f0__f1_panel.png").exists() and (out / "f0__f1_flow.npy").exists()
  assert ok[0]["mean_covisibility"] == 0.5 and ok[0]["ms"] >= 0
  n_traces = len(model.traces)
  assert cli.main(argv) == 0  # resume: the three done pairs are skipped
  assert "0 pairs written, 3 already there, 2 failed" in capsys.readouterr().out
  assert len(model.traces) == n_traces


def test_video_input(tmp_path, monkeypatch):
  import cv2
  path = tmp_path / "v.avi"
  w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (42, 28))
  for i in range(4):
    w.write(np.full((28, 42, 3), 40 * i, np.uint8))
  w.release()
  monkeypatch.setattr(cli, "load_model", lambda *a, **k: (_Shift(), {}))
  assert cli.main(["infer", str(path), "--checkpoint", str(tmp_path), "--out",
                   str(tmp_path / "o")]) == 0
  assert sorted(p.name for p in (tmp_path / "o").glob("*.flo")) == [
      "frame_000000__frame_000001.flo", "frame_000001__frame_000002.flo",
      "frame_000002__frame_000003.flo"]
  np.testing.assert_allclose(read_flo(tmp_path / "o" / "frame_000000__frame_000001.flo"), -40, atol=2)
