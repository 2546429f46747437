"""Two real JAX processes on localhost: grain's ShardByJaxProcess picks each host's share, and the
hosts' batches are those of the explicit-index sharding (disjoint, complete: test_pipeline.py)."""

import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ufm_jax.data import mixture, pipeline

# Slow tier: two jax processes feeding one stream (pytest -m slow).
pytestmark = pytest.mark.slow

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_WORKER = textwrap.dedent("""
  import sys
  import jax
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2,
                             process_id=int(sys.argv[2]))
  import numpy as np
  from ufm_jax.data import mixture, pipeline
  cfg = pipeline.input_config(mixture.synthetic_mixture(num_pairs=8, size=(28, 42)), batch_size=8,
                            longest_side=28, num_workers=0, augment={})
  pipe = pipeline.create(cfg, seed=3, num_epochs=1)
  out = [b["image0"] for b in pipe]
  np.savez(sys.argv[3], process=jax.process_index(), count=jax.process_count(),
           batch=pipe.batch_size, *out)
""")


def _config():
  return pipeline.input_config(mixture.synthetic_mixture(num_pairs=8, size=(28, 42)), batch_size=8,
                             longest_side=28, num_workers=0, augment={})


@pytest.mark.multiprocess
def test_two_jax_processes_shard_the_stream(tmp_path):
  with socket.socket() as s:
    s.bind(("localhost", 0))
    port = s.getsockname()[1]
  env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""),
             JAX_PLATFORMS="cpu")
  procs = [subprocess.Popen([sys.executable, "-c", _WORKER, f"localhost:{port}", str(i),
                             str(tmp_path / f"p{i}.npz")], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
           for i in range(2)]
  for p in procs:
    out, _ = p.communicate(timeout=300)
    assert p.returncode == 0, out[-3000:]
  for i in range(2):
    got = np.load(tmp_path / f"p{i}.npz")
    assert int(got["process"]) == i and int(got["count"]) == 2 and int(got["batch"]) == 4
    want = [b["image0"] for b in pipeline.create(_config(), seed=3, num_epochs=1,
                                                  process_index=i, process_count=2)]
    arrays = [got[f"arr_{k}"] for k in range(len(want))]
    assert len(want) == 2 and len(got.files) == 3 + len(want)
    for a, b in zip(arrays, want):
      np.testing.assert_array_equal(a, b)
