"""Stand-ins for the training-machinery tests (no tests here): a tiny flow model and a grain
pipeline of translated random images, so mesh/optimizer/checkpoint logic is tested in seconds.

Used by train.py through `config.model_fn` / `config.input.data_fn` ("ufm_jax.testing.train_support:...").
"""

import flax.linen as nn
import grain
import jax.numpy as jnp
import ml_collections
import numpy as np

from ufm_jax.training import config_lib


class TinyFlow(nn.Module):
  """Convs on the two stacked images -> flow (2) + covisibility logit (1). `encoder` names a
  sub-module so the per-group learning rates have something to bite on."""
  width: int = 8
  dtype: str = "float32"

  @nn.compact
  def __call__(self, source, target):
    dt = jnp.dtype(self.dtype)
    x = jnp.concatenate([source, target], -1).astype(jnp.float32) / 255.0 - 0.5
    x = nn.Conv(self.width, (3, 3), dtype=dt, name="encoder")(x)
    x = nn.gelu(x)
    x = nn.Conv(self.width, (3, 3), dtype=dt, name="info_sharing")(x)
    x = nn.gelu(x)
    y = nn.Conv(3, (3, 3), dtype=jnp.float32, name="head1")(x).astype(jnp.float32)
    return {"flow": 4.0 * y[..., :2], "covisibility_logits": y[..., 2],
            "covisibility": nn.sigmoid(y[..., 2])}


def tiny_model(model_cfg):
  return TinyFlow(**dict(model_cfg))


def _make_pair(i, seed, h, w):
  rng = np.random.default_rng([seed, i])
  d = rng.integers(-2, 3, size=2)
  big = rng.integers(0, 256, size=(h + 8, w + 8, 3), dtype=np.uint8)
  img0 = big[4:4 + h, 4:4 + w]
  img1 = big[4 - d[1]:4 - d[1] + h, 4 - d[0]:4 - d[0] + w]  # img1[y, x] = img0[y + dy, x + dx]...
  # ...so img0 pixel (x, y) appears in img1 at (x - dx, y - dy): flow = (-dx, -dy).
  flow = np.broadcast_to(np.array([-d[0], -d[1]], np.float32), (h, w, 2)).copy()
  ys, xs = np.mgrid[:h, :w]
  inside = (xs - d[0] >= 0) & (xs - d[0] < w) & (ys - d[1] >= 0) & (ys - d[1] < h)
  return {"image0": np.ascontiguousarray(img0), "image1": np.ascontiguousarray(img1),
          "flow": flow, "covisibility": inside, "flow_valid": inside,
          "covis_valid": np.ones((h, w), bool)}


def shifted_pairs(input_cfg, process_batch, seed):
  """Infinite grain iterator of batches; checkpointable via grain's handler."""
  h, w = input_cfg.get("shape", (14, 14))
  n = int(input_cfg.get("num_pairs", 64))
  import jax
  # Each process reads every P-th pair, so the P per-process batches form the global batch.
  pid, count = jax.process_index(), jax.process_count()
  ds = (grain.MapDataset.range(n).shuffle(seed=seed)[pid::count].repeat()
        .map(lambda i: _make_pair(int(i), seed, h, w)).batch(process_batch, drop_remainder=True))
  it = ds.to_iter_dataset().__iter__()
  return it, {"pairs_per_epoch": n, "image_shape": (h, w)}


def tiny_config(**overrides):
  c = config_lib.training_defaults(ml_collections.ConfigDict())
  c.total_steps = 10
  c.ckpt_steps = 5
  c.keep_ckpt = 2
  c.log_training_steps = 1
  c.sharding_min_size = 0      # the stand-in's tensors are all small: shard them anyway
  c.apply_kwargs = {}          # its batches are plain pairs, not symmetrized (a, b), (b, a) rows
  c.model_fn = "ufm_jax.testing.train_support:tiny_model"
  c.model = ml_collections.ConfigDict({"width": 8})
  c.model_init = None
  c.input = ml_collections.ConfigDict({"data_fn": "ufm_jax.testing.train_support:shifted_pairs",
                                       "batch_size": 8, "shape": (14, 14), "num_pairs": 64})
  c.optim = ml_collections.ConfigDict({
      "lr": {"default": 3e-3, "encoder": 1e-3}, "groups": {"encoder": "^encoder/"},
      "b1": 0.9, "b2": 0.95, "weight_decay": 0.05, "warmup_frac": 0.1, "grad_clip_norm": 1.0,
      "frozen": None, "trainable": None})
  c.loss = ml_collections.ConfigDict({   # the official 560 terms at their defaults
      "terms": ("robust_epe", "covisibility_ce"), "robust_epe": {"type": "robust"},
      "covisibility_ce": {"type": "bce"}})
  c.evals = ml_collections.ConfigDict()
  for k, v in overrides.items():
    c[k] = v
  return c


def get_config(arg=None):
  """python train.py --config=ufm_jax/testing/train_support.py --workdir=DIR (test stand-in)."""
  c = tiny_config()
  if arg:
    for kv in arg.split(","):
      k, v = kv.split("=")
      c[k] = type(c[k])(v) if c[k] is not None else v
  return c


def subprocess_env(repo, cache, **extra) -> dict:
  """The environment of a train.py subprocess in a test: this checkout first on the path, the
  CPU, its own compilation cache (every compile cached), no inherited XLA flags."""
  import os
  env = dict(os.environ)
  env["PYTHONPATH"] = str(repo)
  env["JAX_PLATFORMS"] = "cpu"
  env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
  env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
  env.pop("XLA_FLAGS", None)
  env.update(extra)
  return env
