"""`python -m ufm_jax demo`: the page served by the CLI on a free local port with the base parity
fixture, driven end to end through its API with gradio_client; loopback-only binding; refused
inputs; and the message when the [demo] extra is missing."""

import os
import pathlib
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

from ufm_jax import testing
from ufm_jax.tools import cli, demo
from ufm_jax.data import io, synthetic

REPO = pathlib.Path(__file__).resolve().parents[1]
MAX_SIDE = 320          # the example pair (240x320) still fits
MAX_FILE_SIZE_KB = 200


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(reference_dir, tmp_path_factory):
  """(url, port, log path) of `python -m ufm_jax demo` on the base fixture, default --host."""
  testing.require_extra("demo", ("gradio", "gradio_client"))
  port = _free_port()
  log = tmp_path_factory.mktemp("demo") / "server.log"
  cmd = [sys.executable, "-m", "ufm_jax", "demo", "--checkpoint", str(reference_dir / "base"),
         "--snapshot", "--port", str(port), "--max-side", str(MAX_SIDE),
         "--max-file-size", f"{MAX_FILE_SIZE_KB}kb"]
  with open(log, "w") as out:
    proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=REPO)
  url = f"http://127.0.0.1:{port}/"
  try:
    deadline = time.monotonic() + 600
    while True:
      if proc.poll() is not None:
        pytest.fail(f"the demo exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
      try:
        with urllib.request.urlopen(url, timeout=5) as r:
          if r.status == 200:
            break
      except OSError:
        pass
      if time.monotonic() > deadline:
        pytest.fail(f"the demo did not answer on {url} within 600 s:\n{log.read_text()[-3000:]}")
      time.sleep(1)
    yield url, port, log
  finally:
    proc.terminate()
    try:
      proc.wait(30)
    except subprocess.TimeoutExpired:
      proc.kill()
      proc.wait()


@pytest.fixture(scope="module")
def client(server, tmp_path_factory):
  from gradio_client import Client
  return Client(server[0], verbose=False, analytics_enabled=False,
                download_files=str(tmp_path_factory.mktemp("downloads")))


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
  """A wide-baseline synthetic pair; the target cropped so the two sizes differ."""
  d = tmp_path_factory.mktemp("pair")
  fwd, = synthetic.generate_pair(0, synthetic.SyntheticConfig(size=(96, 128), pair_type="wide"),
                                 directions=(0,))
  src, tgt = d / "source.png", d / "target.png"
  io.write_image(src, fwd["image0"])
  io.write_image(tgt, fwd["image1"][:84, :112])
  return src, tgt


@pytest.mark.slow
def test_api_end_to_end_and_threshold_changes_matches(client, pair):
  from gradio_client import handle_file
  src, tgt = pair
  num = 20000  # more than the 96 x 128 source pixels: every eligible pixel is drawn
  runs = {}
  for thr in (0.1, 0.9):
    out = client.predict(handle_file(str(src)), handle_file(str(tgt)), thr, num,
                         api_name="/analyse")
    flow, covis, warped, drawing, npz, summary, uncertainty = out
    assert uncertainty is None            # the base fixture has no flow covariance
    for img in (flow, covis, warped):
      assert io.read_image(img).shape == (96, 128, 3)
    assert io.read_image(drawing).shape == (96, 128 + 112, 3)  # side by side, heights padded
    m = np.load(npz)
    assert m["image0_hw"].tolist() == [96, 128] and m["image1_hw"].tolist() == [84, 112]
    k0, k1, conf = m["keypoints0"], m["keypoints1"], m["confidence"]
    assert len(k0) == len(k1) == len(conf) > 0 and (conf >= thr).all()
    assert (k0 >= 0).all() and (k0[:, 0] <= 127).all() and (k0[:, 1] <= 95).all()
    assert (k1 >= -0.5).all() and (k1[:, 0] < 111.5).all() and (k1[:, 1] < 83.5).all()
    # the covisibility view and the matches' confidences are the same prediction
    grey = io.read_image(covis)[..., 0].astype(np.float32) / 255
    at = grey[k0[:, 1].astype(int), k0[:, 0].astype(int)]
    np.testing.assert_allclose(at, conf, atol=0.5 / 255 + 1e-6)
    assert f"{len(k0)} matches" in summary
    runs[thr] = (len(k0), summary, grey)
  (n_low, s_low, grey), (n_high, s_high, _) = runs[0.1], runs[0.9]
  assert n_high < n_low <= int((grey >= 0.1 - 0.5 / 255).sum())
  assert "forward" in s_low and "prediction cached" in s_high  # the slider does not re-run the model


@pytest.mark.slow
def test_concurrent_clients_each_get_their_whole_download(server, client, pair, tmp_path):
  """8 clients on loopback send 3 requests each at once, identical ones among them (the same pair
  and threshold from several clients): every download (the four pictures and the .npz) arrives
  whole, with the size and content of the same request answered alone. Gradio once wrote
  identical pictures to one shared file in place while other clients downloaded it."""
  from concurrent.futures import ThreadPoolExecutor, wait
  from gradio_client import Client, handle_file
  src, tgt = pair
  thresholds = (0.2, 0.5, 0.8)

  def contents(out):
    """(size, content) of each file of a response; the .npz by its arrays (its zip entries
    carry the time they were written), every member read (a cut zip fails its CRC)."""
    got = []
    for path in out[:5]:
      path = pathlib.Path(path)
      if path.suffix == ".npz":
        with np.load(path) as z:
          content = {k: z[k].tolist() for k in z.files}
      else:
        content = path.read_bytes()
      got.append((path.stat().st_size, content))
    return got

  alone = {thr: contents(client.predict(handle_file(str(src)), handle_file(str(tgt)), thr, 500,
                                        api_name="/analyse"))
           for thr in thresholds}

  def one_client(i):
    c = Client(server[0], verbose=False, analytics_enabled=False,
               download_files=str(tmp_path / f"client{i}"))
    got = []
    for j in range(3):
      thr = thresholds[(i + j) % 3]
      out = c.predict(handle_file(str(src)), handle_file(str(tgt)), thr, 500, api_name="/analyse")
      got.append((thr, contents(out)))
    return got

  with ThreadPoolExecutor(8) as pool:
    futures = [pool.submit(one_client, i) for i in range(8)]
    _, pending = wait(futures, timeout=300)
  assert not pending, f"{len(pending)} of 8 clients unanswered after 300 s"
  answers = [a for f in futures for a in f.result()]  # a cut download raises here
  assert len(answers) == 24
  for thr, got in answers:
    for (size, content), (want_size, want) in zip(got, alone[thr]):
      assert size == want_size and content == want, thr


def test_too_large_image_and_file_are_refused(server, client, pair, tmp_path):
  from gradio_client import handle_file
  from gradio_client.exceptions import AppError
  _, tgt = pair
  tall = tmp_path / "tall.png"
  io.write_image(tall, np.zeros((MAX_SIDE + 80, 100, 3), np.uint8))
  with pytest.raises(AppError) as e:
    client.predict(handle_file(str(tall)), handle_file(str(tgt)), 0.5, 100, api_name="/analyse")
  assert f"{MAX_SIDE + 80}x100" in str(e.value) and f"--max-side {MAX_SIDE}" in str(e.value)
  noise = tmp_path / "noise.png"  # incompressible: over the upload limit, within --max-side
  io.write_image(noise, np.random.default_rng(0).integers(0, 256, (300, 300, 3), dtype=np.uint8))
  assert noise.stat().st_size > MAX_FILE_SIZE_KB * 1000
  with pytest.raises(ValueError, match="exceeds the maximum file size"):  # the client checks first
    client.predict(handle_file(str(noise)), handle_file(str(tgt)), 0.5, 100, api_name="/analyse")
  import httpx
  with open(noise, "rb") as f:  # and the server refuses it without a client's check
    r = httpx.post(server[0] + "gradio_api/upload", files={"files": f}, timeout=60)
  assert r.status_code == 413, (r.status_code, r.text)


def test_a_file_that_is_no_image_and_a_too_small_image_are_refused(client, pair, tmp_path,
                                                                  reference_dir):
  """A renamed non-image gets our message, without the server's temp path; an image with a side
  under one pixel per encoder patch of the inference resolution is refused, naming the limit."""
  import json
  from gradio_client import handle_file
  from gradio_client.exceptions import AppError
  src, tgt = pair
  fake = tmp_path / "notimage.png"
  fake.write_bytes(b"this is not a png")
  with pytest.raises(AppError) as e:
    client.predict(handle_file(str(fake)), handle_file(str(tgt)), 0.5, 100, api_name="/analyse")
  text = str(e.value)
  assert "the source file is not an image" in text
  assert "/tmp" not in text and "notimage" not in text and "UnidentifiedImageError" not in text
  cfg = json.loads((reference_dir / "base" / "config.json").read_text())
  w_inf, h_inf = cfg["inference_resolution"]
  patch = cfg["encoder_kwargs"]["patch_size"]
  smallest = -(-min(w_inf, h_inf) // patch)   # one pixel per patch of the shorter side
  thin = tmp_path / "thin.png"
  io.write_image(thin, np.zeros((smallest - 1, 64, 3), np.uint8))
  with pytest.raises(AppError) as e:
    client.predict(handle_file(str(src)), handle_file(str(thin)), 0.5, 100, api_name="/analyse")
  assert f"{smallest - 1}x64" in str(e.value) and f"minimum of {smallest} px" in str(e.value)
  ok = tmp_path / "ok.png"
  io.write_image(ok, np.full((smallest, smallest, 3), 128, np.uint8))
  client.predict(handle_file(str(src)), handle_file(str(ok)), 0.5, 100, api_name="/analyse")


def test_sliders_update_on_input_events(client):
  """Typing in a slider's number box or using the arrow keys fires `input` (Gradio's `release`
  fires only on a mouse release): both sliders re-run the analysis on `input`, with the Run
  button's inputs and outputs."""
  cfg = client.config
  ids = {c["props"].get("label"): c["id"] for c in cfg["components"]}
  deps = cfg["dependencies"]
  run = next(d for d in deps if d.get("api_name") == "analyse")
  for label in ("covisibility threshold", "matches to sample"):
    wired = [d for d in deps if [ids[label], "input"] in [list(t) for t in d["targets"]]]
    assert len(wired) == 1, label
    assert wired[0]["inputs"] == run["inputs"] and wired[0]["outputs"] == run["outputs"]
    assert not [d for d in deps if [ids[label], "release"] in [list(t) for t in d["targets"]]]


def _listening(port: int) -> list[str]:
  """Local addresses (hex, as /proc/net/tcp* write them) of sockets listening on `port`."""
  found = []
  for table in ("/proc/net/tcp", "/proc/net/tcp6"):
    if not os.path.exists(table):
      continue
    for line in open(table).read().splitlines()[1:]:
      fields = line.split()
      addr, p = fields[1].split(":")
      if int(p, 16) == port and fields[3] == "0A":  # 0A: LISTEN
        found.append(addr)
  return found


def test_each_response_gets_its_own_folder_pruned_by_age(tmp_path):
  analyser = object.__new__(demo.Analyser)   # response_dir reads out_dir and keep_s only
  analyser.out_dir, analyser.keep_s = tmp_path, 3600
  a, b = analyser.response_dir("k"), analyser.response_dir("k")
  assert a != b and a.parent == b.parent == tmp_path
  (a / "m.npz").write_bytes(b"x")
  os.utime(a, (time.time() - 3601, time.time() - 3601))
  c = analyser.response_dir("k")
  assert not a.exists() and b.is_dir() and c.is_dir()


def test_binds_loopback_only_by_default(server):
  if not os.path.exists("/proc/net/tcp"):
    pytest.skip("reads the listening sockets from /proc/net/tcp (Linux)")
  _, port, log = server
  assert _listening(port) == ["0100007F"], (_listening(port), log.read_text()[-2000:])
  text = log.read_text()
  assert f"http://127.0.0.1:{port}" in text and "gradio.live" not in text
  assert "--share" in text and "share=True" not in text   # our flag, not Gradio's argument


def test_without_the_extra_exits_2_naming_it(monkeypatch, tmp_path, capsys):
  monkeypatch.setitem(sys.modules, "gradio", None)  # `import gradio` raises ImportError
  assert cli.main(["demo", "--checkpoint", str(tmp_path)]) == 2
  assert 'pip install -e ".[demo]"' in capsys.readouterr().err
